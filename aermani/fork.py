"""`aermani fork LOG --step K`: a recorded flight continued live from before one of its steps (issue 29).

The simulator records its whole state whenever a skill ends (`sim/state`, services/sim/snapshot.py). A fork reads
the log, takes the state recorded when step K-1's skill ended (the take-off's for K = 1), the working memory the
model was shown at step K and the History of steps 1..K-1, and starts the whole stack from there: the simulator
restored (the vehicle in the air, in Hold where it flew, the gripper holding what it held, the estimator's and
the disturbances' random states), the executor's memory put back, and the task continued from step K with the
recorded policy or another (`--backend`, `--model`, `--variant`). The new log's task status names its parent log,
task and step (`TaskStatus.forked_from`); its steps are numbered from K, so `aermani diff` lines two forks up.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import typer

from aermani.demo import backend_key_env, console, run_and_judge, run_on_stack, scenario_for
from shared.errors import AermaniError
from shared.messages import VARIANTS, ReasoningStep, SimState, WorkingMemory
from shared.text import terminal_text


class ForkError(AermaniError):
    """The log cannot be forked at that step (no such task or step, no simulator state recorded there)."""


@dataclass
class ForkPoint:
    """What a fork starts from, read from the parent log."""

    log: Path
    task_id: str
    vehicle_id: str
    command: str
    variant: str
    backend: str
    step: int
    before: list[ReasoningStep]
    """The recorded steps before `step`."""
    recorded: list[ReasoningStep]
    """The recorded steps from `step` on (what the parent did next)."""
    state: SimState
    memory: WorkingMemory | None
    segmenter: str | None
    """The parent's segmenter, from its perception health (None when the log has none)."""

    @property
    def world(self) -> dict[str, Any]:
        return json.loads(self.state.state)


def read_fork_point(log: Path, step: int, task_id: str | None = None) -> ForkPoint:
    """The fork point of `log` before step `step` of its task (the only one, or `task_id`)."""
    from services.reasoner.rereason import LogIndex, observed_steps
    from shared.keys import SIM_STATE, Keys
    from shared.mcaplog import read_topic, topic_of

    if not log.is_file():
        raise ForkError(f"{log}: no such file")
    try:
        index = LogIndex(log)
    except Exception as exc:
        raise ForkError(f"{log}: not a readable MCAP log ({type(exc).__name__}: {exc})") from exc
    tasks = [t for t in index.tasks if task_id in (None, t.task_id)]
    if not tasks:
        raise ForkError(f"{log} has no recorded task" + (f" {task_id}" if task_id else ""))
    if len(tasks) > 1:
        raise ForkError(f"{log} has {len(tasks)} tasks ({', '.join(t.task_id for t in tasks)}): name one with --task")
    task = tasks[0]
    numbers = [s.step for s in task.steps]
    if not numbers:
        raise ForkError(f"task {task.task_id} in {log} has no recorded step to continue before")
    if step not in numbers:
        raise ForkError(f"task {task.task_id} has no step {step} (its steps: {numbers[0]}..{numbers[-1]})")
    k = numbers.index(step)
    # The world when step K-1's skill ended; before step 1, when the take-off ended. Holds the loop commands
    # on a failure path carry no step (0) and are never a fork point.
    wanted = "takeoff" if step == 1 else None
    all_states = [v for _, v in read_topic(log, topic_of(task.vehicle_id, SIM_STATE)) if v.task_id == task.task_id]
    states = [v for v in all_states if v.step == step - 1 and v.skill != "hold" and wanted in (None, v.skill)]
    if not states:
        prev = task.steps[k - 1] if k > 0 else None
        if prev is not None and (prev.ste is None or prev.skill_state is None):
            why = f"step {step - 1} ran no skill (no valid answer), so no world was recorded at its end"
        elif step == 1:
            why = "no take-off of this task was recorded (a task started in the air has no world before step 1)"
        elif not all_states:
            why = ("no simulator state at all: only a simulated flight recorded with AERMANI_SIM_SNAPSHOTS on (the "
                   "default) can be forked")
        else:
            why = f"no simulator state was recorded when step {step - 1}'s skill ended"
        raise ForkError(f"cannot fork task {task.task_id} of {log} before step {step}: {why}; fork at another step")
    try:
        doc = json.loads(states[-1].state)
    except ValueError as exc:
        raise ForkError(f"the simulator state recorded after step {step - 1} is not JSON ({exc})") from None
    missing = [f for f in ("realism", "dynamics", "scenario") if not isinstance(doc, dict) or f not in doc]
    if missing:  # what the fork's stack is configured from
        raise ForkError(f"the simulator state recorded after step {step - 1} lacks {', '.join(missing)}")
    observed = observed_steps(index, task)
    obs = observed[k][1]
    segmenter = None
    for _, h in read_topic(log, Keys(task.vehicle_id).health("perception")):
        segmenter = str(h.details.get("segmenter", "")) or segmenter
    return ForkPoint(log=log, task_id=task.task_id, vehicle_id=task.vehicle_id, command=task.command,
                     variant=task.variant, backend=task.steps[0].backend, step=step, before=task.steps[:k],
                     recorded=task.steps[k:], state=states[-1], memory=obs.memory if obs is not None else None,
                     segmenter=segmenter)


def fork_env(point: ForkPoint, state_file: Path, *, backend: str, variant: str, segmenter: str,
             speed_factor: float, model: str, base_url: str | None, out_dir: Path | None) -> dict[str, str]:
    world = point.world
    env = {"AERMANI_SIM_RESTORE": str(state_file), "AERMANI_SIM_REALISM": str(world["realism"]),
           "AERMANI_SIM_DYNAMICS": str(world["dynamics"]), "AERMANI_SIM_SPEED_FACTOR": str(speed_factor),
           "AERMANI_VEHICLE_ID": point.vehicle_id,
           "AERMANI_PERCEPTION_SEGMENTER": segmenter, "AERMANI_REASONER_BACKEND": backend,
           "AERMANI_REASONER_VARIANT": variant,
           "AERMANI_RECORDER_SEGMENTATION": "1" if segmenter == "sim" else "0",
           "AERMANI_EXECUTOR_MEMORY_RESTORE": "1"}
    if model:
        env["AERMANI_REASONER_MODEL"] = model
    if base_url:
        env["AERMANI_REASONER_BASE_URL"] = base_url
    if out_dir is not None:
        env["AERMANI_RECORDER_OUT_DIR"] = str(out_dir)
    return env


async def _fork_task(stack, point: ForkPoint, t_max: float, result: dict) -> int:
    from services.reasoner.rereason import resume_steps
    from shared.bus import Bus, query_ready
    from shared.keys import Keys
    from shared.messages import ForkOrigin, MemoryRestore, Resume, Scenario, TaskRequest, now_ns

    keys = Keys(point.vehicle_id)
    world = point.world
    sc = Scenario.model_validate(world["scenario"])
    bus = await Bus.open(connect=[stack.endpoint])
    try:
        health = bus.subscribe(keys.health("recorder"), maxsize=5)
        detections = bus.subscribe(keys.detections, maxsize=10, overflow="latest")
        request = TaskRequest(command=point.command, t_max_s=t_max, resume=Resume(
            origin=ForkOrigin(log=point.log.name, task_id=point.task_id, step=point.step),
            history=tuple(resume_steps(point.before))))
        if point.memory is not None:
            reply = await query_ready(bus, keys.restore_memory, MemoryRestore(
                task_id=request.task_id, memory=point.memory, taken_ns=point.state.stamp_ns), timeout=30)
            if not reply.accepted:
                console.print(f"[red]the executor refused the recorded memory: {terminal_text(reply.reason)}[/red]")
                return 1
        # The parent decided step K with perception running; a fresh stack's first detections take a while (ci27:
        # the fork's step 5 saw "nothing recognised" where the parent saw the table and the cup). The task starts
        # once perception has published detections of frames rendered after the restore, twice (the second
        # reaches the reasoner's own subscription as surely).
        if not await _perception_live(detections, now_ns(), timeout=60.0):
            console.print("[yellow]perception published no detections within 60 s: the fork's first step decides "
                          "on what it has[/yellow]")
        parsed, accepted = scenario_for(point.command, None, None, sc.seed)
        objects = accepted or ((sc.target_object,) if sc.target_object else ())
        result.update(task_id=request.task_id)
        return await run_and_judge(bus, keys, request, objects, sc.destination if parsed.destination else None,
                                   result, health, stack)
    finally:
        await bus.close()


async def _perception_live(detections, since_ns: int, *, timeout: float, count: int = 2) -> bool:
    """Whether `count` detections of frames stamped after `since_ns` arrived within `timeout` seconds."""
    import asyncio

    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    seen = 0
    while seen < count:
        left = deadline - loop.time()
        if left <= 0:
            return False
        try:
            d = await detections.recv(timeout=left)
        except TimeoutError:
            return False
        if d.frame_stamp_ns > since_ns:
            seen += 1
    return True


def run_fork(point: ForkPoint, *, backend: str | None = None, variant: str | None = None, model: str = "",
             base_url: str | None = None, segmenter: str | None = None, speed_factor: float = 2.0,
             t_max: float = 600.0, log_dir: Path | None = None, out_dir: Path | None = None,
             extra_env: dict[str, str] | None = None, result: dict | None = None) -> int:
    """Start the stack from the fork point and continue the task; the exit code (0: it succeeded and the judge
    agrees). `result` receives what `aermani demo` gives (final status, steps, verdict, log)."""
    if backend is None:  # the recorded policy: `rules`, or `openai:<model>`
        backend, _, recorded_model = (point.backend or "rules").partition(":")
        model = model or recorded_model
    variant = variant or point.variant or "full"
    segmenter = segmenter or point.segmenter or "color"
    run_dir = log_dir or Path("runs") / time.strftime("%Y%m%d-%H%M%S") / "logs"
    run_dir.mkdir(parents=True, exist_ok=True)
    state_file = run_dir / "fork-state.json"
    state_file.write_text(point.state.model_dump_json())
    env = {**fork_env(point, state_file, backend=backend, variant=variant, segmenter=segmenter,
                      speed_factor=speed_factor, model=model, base_url=base_url, out_dir=out_dir),
           **(extra_env or {})}
    world = point.world
    console.print(f"fork of {terminal_text(point.log.name)} task {point.task_id} before step {point.step}: the world "
                  f"after step {point.state.step} ({terminal_text(point.state.skill or '?')}), "
                  f"{len(point.before)} steps of History; realism {world['realism']}, dynamics {world['dynamics']}, "
                  f"segmenter {terminal_text(segmenter)}, policy {terminal_text(backend)} ({variant})")
    out: dict = {} if result is None else result
    return run_on_stack(lambda stack: _fork_task(stack, point, t_max, out), env=env, log_dir=run_dir,
                        what="fork")


def fork_command(
    log: Annotated[Path, typer.Argument(help="The recorded MCAP log of a simulated flight.")],
    step: Annotated[int, typer.Option(help="Continue before this step: the world as it was when step K-1's skill "
                                           "ended, the History of steps 1..K-1.", min=1)],
    task: Annotated[str | None, typer.Option(help="The task to fork (when the log holds several).")] = None,
    backend: Annotated[str | None, typer.Option(help="Policy backend (default: the recorded one).")] = None,
    model: Annotated[str, typer.Option(help="Model name for a model backend.")] = "",
    variant: Annotated[str | None, typer.Option(help=f"Prompt variant ({', '.join(VARIANTS)}; default: the "
                                                     "recorded one).")] = None,
    base_url: Annotated[str | None, typer.Option(help="Endpoint of a model backend.")] = None,
    api_key_env: Annotated[str | None, typer.Option(help="Environment variable holding the backend's API key.")]
    = None,
    segmenter: Annotated[str | None, typer.Option(help="Perception segmenter (default: the recorded one).")] = None,
    speed_factor: Annotated[float, typer.Option(help="Simulator speed versus wall clock.")] = 2.0,
    t_max: Annotated[float, typer.Option(help="T_max of the continued task, seconds.")] = 600.0,
    out_dir: Annotated[Path | None, typer.Option(help="Where the fork's MCAP log goes (default: the recorder's).")]
    = None,
    log_dir: Annotated[Path | None, typer.Option(help="Service logs directory (default runs/<time>/logs).")] = None,
) -> None:
    """Continue a recorded flight live from before one of its steps, with its policy or another; the new log
    names its parent and step."""
    if variant is not None and variant not in VARIANTS:
        console.print(f"[red]unknown variant {terminal_text(repr(variant))}; use one of {', '.join(VARIANTS)}[/red]")
        raise typer.Exit(2)
    try:
        point = read_fork_point(log, step, task)
    except ForkError as exc:
        console.print(f"[red]{terminal_text(exc)}[/red]")
        raise typer.Exit(2) from None
    key_env = backend_key_env(backend or (point.backend or "rules").partition(":")[0], api_key_env)
    if isinstance(key_env, str):
        console.print(f"[red]{terminal_text(key_env)}[/red]")
        raise typer.Exit(2)
    code = run_fork(point, backend=backend, variant=variant, model=model, base_url=base_url, segmenter=segmenter,
                    speed_factor=speed_factor, t_max=t_max, log_dir=log_dir, out_dir=out_dir, extra_env=key_env)
    raise typer.Exit(code)


def register(app: typer.Typer) -> None:
    app.command("fork")(fork_command)
