"""`aermani demo "COMMAND"`: the whole stack on one task. It starts the simulator, the bridge, perception, the
executor, the reasoner and the recorder, sets the scenario up for the command, streams each step and judges success
with the simulator's ground truth. It composes services, so it is the application's, not the reasoner's."""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from shared.messages import VARIANTS
from shared.text import terminal_text

console = Console()


def scenario_for(command: str, target: str | None, destination: str | None, seed: int):
    """A simulator scenario that makes the command meaningful (target, destination, needed extras)."""
    from services.reasoner.backends.rules import parse_command
    from shared.messages import Scenario

    plan = parse_command(command)
    extra: tuple[str, ...] = ()
    accept: tuple[str, ...] = ()
    out_of_view = bool(__import__("re").search(r"\b(find|locate|search|look for)\b", command.lower()))
    if target is None:
        if plan.choices:
            target, extra = plan.choices[0], (plan.choices[1],)
        elif plan.selector:
            # Two real boxes of different measured sizes (4.9 vs 2.4 litres); no object is named after the answer.
            big, small = "cardboard box", "cracker box"
            target, extra = (big, (small,)) if plan.selector == "larger" else (small, (big,))
        elif plan.category == "snack":
            target, accept = "apple", ("banana", "orange", "cracker box")
        else:
            target = plan.target
    if plan.excluded and "tool" in plan.excluded:
        extra = (*extra, "hammer", "wrench")
    if destination is None:
        destination = plan.destination
    return Scenario(seed=seed, target_object=target, destination=destination, extra_objects=extra,
                    target_out_of_view=out_of_view), (target, *accept) if target else accept


def demo_command(
    command: Annotated[str, typer.Argument(help="The natural-language command, e.g. \"pick up the red cup and "
                                                "place it on the table\".")],
    backend: Annotated[str, typer.Option(help="Policy backend (`aermani vlm backends` lists them).")] = "rules",
    variant: Annotated[str, typer.Option(help=f"Prompt variant ({', '.join(VARIANTS)}).")] = "full",
    seed: Annotated[int, typer.Option(help="Layout seed of the simulated room.")] = 0,
    target: Annotated[str | None, typer.Option(help="Scenario target object (default: read from the command).")]
    = None,
    destination: Annotated[str | None, typer.Option(help="Scenario destination surface (default: from the command).")]
    = None,
    speed_factor: Annotated[float, typer.Option(help="Simulator speed versus wall clock.")] = 2.0,
    segmenter: Annotated[str, typer.Option(help="Perception segmenter: color (real computer vision on the rendered "
                                                "pixels), sam3, or sim (ground-truth oracle, debugging only).")]
    = "color",
    realism: Annotated[str, typer.Option(help="Simulator realism: realistic (the depth camera's flaws, exposure, "
                                              "indoor air, a drifting pose estimate), harsh (stress) or ideal "
                                              "(debugging).")] = "realistic",
    model: Annotated[str, typer.Option(help="Model name for a model backend (empty: the backend's default).")] = "",
    base_url: Annotated[str | None, typer.Option(help="Endpoint of a model backend (e.g. a local vLLM).")] = None,
    t_max: Annotated[float, typer.Option(help="T_max, seconds.")] = 600.0,
    log_dir: Annotated[Path | None, typer.Option(help="Service logs directory (default runs/<time>/logs).")] = None,
    api_key_env: Annotated[str | None, typer.Option(help="Name of the environment variable that holds the model "
                                                         "backend's API key (the key itself never goes on the "
                                                         "command line).")] = None,
    override_preflight: Annotated[bool, typer.Option("--override-preflight", help="Fly even when the "
                                                     "preflight fails (PX4's failsafe parameters, link, "
                                                     "estimate, battery): for a simulator set up on purpose.")]
    = False,
) -> None:
    """Start the embedded stack (router, sim, bridge, perception, executor, reasoner, recorder), run the command,
    stream each step, and judge success with the simulator's ground truth."""
    if variant not in VARIANTS:
        console.print(f"[red]unknown variant {terminal_text(repr(variant))}; use one of {', '.join(VARIANTS)}[/red]")
        raise typer.Exit(2)
    key_env = backend_key_env(backend, api_key_env)
    if isinstance(key_env, str):
        console.print(f"[red]{terminal_text(key_env)}[/red]")
        raise typer.Exit(2)
    scenario, accepted = scenario_for(command, target, destination, seed)
    env = {"AERMANI_REASONER_BACKEND": backend, "AERMANI_REASONER_VARIANT": variant,
           "AERMANI_SIM_SPEED_FACTOR": str(speed_factor), "AERMANI_SIM_SEED": str(seed),
           "AERMANI_PERCEPTION_SEGMENTER": segmenter, "AERMANI_SIM_REALISM": realism,
           # The oracle's masks belong in the log (replay needs them); otherwise they are neither sent nor kept.
           "AERMANI_RECORDER_SEGMENTATION": "1" if segmenter == "sim" else "0"}
    if scenario.target_object:
        env["AERMANI_SIM_TARGET_OBJECT"] = scenario.target_object
    if scenario.destination:
        env["AERMANI_SIM_DESTINATION"] = scenario.destination
    if model:
        env["AERMANI_REASONER_MODEL"] = model
    if base_url:
        env["AERMANI_REASONER_BASE_URL"] = base_url
    env.update(key_env)
    if override_preflight:
        env["AERMANI_AUTOPILOT_BRIDGE_PREFLIGHT_OVERRIDE"] = "1"
        env.setdefault("AERMANI_AUTOPILOT_BRIDGE_PREFLIGHT_OVERRIDE_REASON", "aermani demo --override-preflight")
    code = run_demo(command, scenario, accepted, env=env, t_max=t_max, log_dir=log_dir)
    raise typer.Exit(code)


def backend_key_env(backend: str, api_key_env: str | None) -> dict[str, str] | str:
    """Before anything starts: the reasoner's key settings for `backend` (from `api_key_env` when named), or why
    it cannot run. A chat backend without its key would crash the reasoner at start and the demo would only time
    out; this says what to set instead."""
    if api_key_env:
        unknown = backend_problem(backend, key_needed=False)
        if unknown:
            return unknown
        key = os.environ.get(api_key_env, "")
        if not key:
            return f"no API key: --api-key-env names {api_key_env}, which is not set in this environment"
        return {"AERMANI_REASONER_API_KEY": key}
    problem = backend_problem(backend)
    if problem is not None:
        return problem + ("; or pass --api-key-env NAME" if problem.startswith("no API key") else "")
    return {}


def backend_problem(backend: str, *, key_needed: bool = True) -> str | None:
    """Why a reasoner set to `backend` could not start, said before anything starts (`aermani demo`, `aermani
    up`): an unknown backend or a broken plug-in module, or a chat backend whose key is set nowhere
    (AERMANI_REASONER_API_KEY or the provider's variable); None when it can start."""
    from services.reasoner.backends import BACKENDS, load_backend_modules
    from services.reasoner.backends.base import ChatBackend, missing_key
    from services.reasoner.settings import ReasonerSettings

    try:
        load_backend_modules(ReasonerSettings().backend_modules)
        cls = BACKENDS.lookup(backend)
    except Exception as exc:  # an unknown backend or a broken plug-in module: its own message says which
        return str(exc)
    if key_needed and issubclass(cls, ChatBackend) and cls.key_env and not (
            os.environ.get("AERMANI_REASONER_API_KEY") or os.environ.get(cls.key_env)):
        return missing_key(backend, cls.key_env)
    return None


DEMO_SERVICES = ("sim", "autopilot_bridge", "perception", "executor", "reasoner", "recorder")


def run_demo(command: str, scenario, accepted: tuple[str, ...], *, env: dict[str, str], t_max: float = 600.0,
             log_dir: Path | None = None, services: tuple[str, ...] = DEMO_SERVICES,
             result: dict | None = None) -> int:
    """Start the stack, run one task, print the verdict; returns the exit code (0 = success). `result`, when
    given, receives the final TaskStatus, the ReasoningSteps and the judge's verdict."""
    from pydantic import TypeAdapter

    # read as the bridge reads it (pydantic's bool: 1/true/yes/on...), from what the bridge will be given
    override = TypeAdapter(bool).validate_python(
        {**os.environ, **env}.get("AERMANI_AUTOPILOT_BRIDGE_PREFLIGHT_OVERRIDE") or "false")
    return run_on_stack(lambda stack: _demo_task(stack, command, scenario, accepted, t_max,
                                                 {} if result is None else result, override_preflight=override),
                        env=env, log_dir=log_dir, services=services)


def run_on_stack(body, *, env: dict[str, str], log_dir: Path | None = None,
                 services: tuple[str, ...] = DEMO_SERVICES, what: str = "demo") -> int:
    """Start the embedded stack (`services`, MAVLink on loopback), run `body(stack)` (a coroutine giving the exit
    code) and stop the stack whatever happens; the exit code (2: this checkout lacks a service)."""
    from aermani.launcher import Stack, available_services, loopback_mavlink_env

    have = available_services()
    missing = [s for s in services if s not in have and s != "recorder"]
    if missing:
        console.print(f"[red]this checkout lacks services {terminal_text(missing)}; cannot run the {what}[/red]")
        return 2
    names = [s for s in services if s in have]
    stack = Stack(names, env=loopback_mavlink_env(env), log_dir=log_dir)
    console.print(f"starting {', '.join(names)} (router {stack.endpoint}, logs in {stack.log_dir})")
    t0 = time.monotonic()
    try:
        stack.start(wait=True, timeout=180)
        console.print(f"stack up in {time.monotonic() - t0:.1f} s")
        return asyncio.run(body(stack))
    except KeyboardInterrupt:
        console.print("[yellow]interrupted[/yellow]")
        return 130
    except Exception as exc:
        console.print(f"[red]{what} failed: {type(exc).__name__}: {terminal_text(exc)}[/red]")
        return 1
    finally:
        stack.stop()


async def _preflight_passes(bus, keys, override: bool) -> bool:
    """The bridge's preflight before the task: a failure refuses to take off (the bridge would refuse the arm
    too) unless overridden, and is printed with every reason either way."""
    from shared.bus import query_ready
    from shared.messages import PreflightCommand

    res = await query_ready(bus, keys.autopilot_command, PreflightCommand(), timeout=30)
    for _ in range(20):  # no checks ran until the simulator's first heartbeat reaches the bridge (no link)
        if res.checks:
            break
        await asyncio.sleep(1.0)
        res = await query_ready(bus, keys.autopilot_command, PreflightCommand(), timeout=30)
    if res.ok:
        console.print(f"[green]{terminal_text(res.message)}[/green]")
        return True
    console.print(f"[red]{terminal_text(res.message)}[/red]")
    if override:
        console.print("[yellow]--override-preflight: flying anyway[/yellow]")
        return True
    console.print("[red]refusing to take off: fix the autopilot's configuration, or pass --override-preflight"
                  "[/red]")
    return False


async def _demo_task(stack, command: str, scenario, accepted: tuple[str, ...], t_max: float, result: dict,
                     override_preflight: bool = False) -> int:
    from shared.bus import Bus, query_ready
    from shared.keys import Keys
    from shared.messages import TaskRequest

    keys = Keys(stack.procs[0].vehicle_id)
    bus = await Bus.open(connect=[stack.endpoint])
    try:
        health = bus.subscribe(keys.health("recorder"), maxsize=5)
        reports = _config_reports(bus, keys)
        reset = await query_ready(bus, keys.sim_reset, scenario, timeout=30)
        if not reset.ok:
            console.print(f"[red]the simulator refused the scenario: {terminal_text(reset.message)} (use --target/"
                          "--destination)"
                          "[/red]")
            return 2
        sc = reset.scenario or scenario
        console.print(f"scenario: seed {sc.seed}, target {terminal_text(sc.target_object)}, destination "
                      f"{terminal_text(sc.destination)}")
        await _print_config(reports, result)
        if not await _preflight_passes(bus, keys, override=override_preflight):
            result["preflight"] = "refused"
            return 2
        # Judge what the command asked: the simulator fills in a destination for every layout, but a command
        # without one ("pick up the tissue box") succeeds when the object is held.
        objects = accepted or ((sc.target_object,) if sc.target_object else ())
        return await run_and_judge(bus, keys, TaskRequest(command=command, t_max_s=t_max), objects,
                                   sc.destination if scenario.destination else None, result, health, stack)
    finally:
        await bus.close()


def _config_reports(bus, keys):
    """Subscriptions to the health reports that say what actually runs (opened before anything is asked)."""
    return bus.subscribe(keys.health("perception"), maxsize=5), bus.subscribe(keys.health("sim"), maxsize=5)


async def _print_config(reports, result: dict) -> None:
    """What actually runs, from the services' own health reports (not from what was asked for)."""
    perception_health, sim_health = reports
    seg, real, body = "unknown", "unknown", "unknown"
    with contextlib.suppress(TimeoutError):
        seg = str((await perception_health.recv(timeout=10)).details.get("segmenter", "unknown"))
    with contextlib.suppress(TimeoutError):
        details = (await sim_health.recv(timeout=10)).details
        real, body = str(details.get("realism", "unknown")), str(details.get("dynamics", "unknown"))
    note = " (ground-truth oracle: the simulator's masks, not real perception)" if seg == "sim" else ""
    console.print(f"perception: {terminal_text(seg)}{note}")
    console.print(f"simulator: MuJoCo physics, {terminal_text(body)} vehicle, realism {terminal_text(real)}")
    result.update(segmenter=seg, realism=real, dynamics=body)


async def run_and_judge(bus, keys, request, objects: tuple[str, ...], destination: str | None, result: dict,
                        recorder_health, stack) -> int:
    """Send the task, stream its steps, judge it with the simulator's ground truth (`objects` held, or placed on
    `destination`) and say where its log is; the exit code (0 = the task succeeded and the judge agrees)."""
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from shared.tasks import follow_task, judge_episode, recorded_end

    t_max = request.t_max_s or 600.0
    console.print(f"[bold]task:[/bold] {terminal_text(request.command)}")
    with Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(), console=console,
                  transient=True) as progress:
        bar = progress.add_task("waiting for the first step...", total=None)

        def on_step(s) -> None:
            call = s.ste.call if s.ste else "(no valid answer)"
            why = (s.drt.reasoning or s.drt.summary or "") if s.drt else ""
            retries = f" [yellow]{s.retries} re-prompt(s)[/yellow]" if s.retries else ""
            state = s.skill_state.value if s.skill_state else "-"
            color = "green" if state == "succeeded" else "red"
            console.print(f"  {s.step:>3} {terminal_text(call):<38} [{color}]{state:<9}[/{color}]{retries} "
                          f"[dim]{terminal_text(why[:90])}[/dim]")
            progress.update(bar, description=f"step {s.step} done; thinking...")

        followed = await follow_task(bus, keys, request, on_step=on_step, timeout=t_max + 60)
    accept, final, steps = followed.accept, followed.final, followed.steps
    if not accept.accepted:
        console.print(f"[red]the reasoner refused the task: {terminal_text(accept.reason)}[/red]")
        return 1
    if final is None:
        console.print(f"[red]the task did not end within {t_max + 60:.0f} s[/red]")
        return 1
    calls = final.model_calls or 1
    speculated = (f", speculative steps {final.speculations_used} of {final.speculations} asked"
                  if final.speculations else "")
    console.print(f"task {final.state.value}: {terminal_text(final.message)} ({final.steps} steps, "
                  f"{final.model_calls} model calls, IAR {100 * final.invalid_answers / calls:.1f} %{speculated})")
    verdict_ = await judge_episode(bus, keys, objects, destination)
    ok, verdict = verdict_.success, verdict_.message
    console.print(("[bold green]SUCCESS[/bold green]" if ok else "[bold red]FAILURE[/bold red]") +
                  f" (simulator judge: {terminal_text(verdict)})")
    log_path, complete = await recorded_end(recorder_health, final.task_id, max((s.step for s in steps), default=0))
    if log_path and not complete:
        console.print("[yellow]the recorder had not taken the task's end within 10 s: its log may lack the last "
                      "steps[/yellow]")
    result.update(final=final, steps=steps, success=ok, verdict=verdict, log=log_path)
    console.print(f"log: {terminal_text(log_path)}" if log_path else
                  "log: no recorder running (no MCAP log written)")
    console.print(f"service logs: {stack.log_dir}")
    return 0 if ok and final.state.value == "succeeded" else 1


def register(app: typer.Typer) -> None:
    app.command("demo")(demo_command)
