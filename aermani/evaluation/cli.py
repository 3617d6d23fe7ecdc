"""`aermani eval`: run the paper's task suites (or a user's tasks) on the real stack and write the report."""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from shared.errors import ConfigError
from shared.messages import BASELINES, VARIANTS
from shared.text import terminal_text

console = Console()


def _split(value: str | None) -> list[str] | None:
    if not value:
        return None
    return [v.strip() for v in value.split(",") if v.strip()]


def _interrupt(_signum: int, _frame: object) -> None:
    raise KeyboardInterrupt


def eval_command(
    backend: Annotated[str, typer.Option(help="Reasoner backend (`aermani vlm backends` lists them).")] = "rules",
    variant: Annotated[str, typer.Option(help="Prompt variant, or a comma list for a sweep, or 'all' "
                                              f"({', '.join(VARIANTS)}), or 'baselines' or one of the paper's "
                                              f"baseline frameworks ({', '.join(BASELINES)}; plan-once is "
                                              "plan_once), which need a model backend.")] = "full",
    episodes: Annotated[int | None, typer.Option(help="Episodes per suite cycling through its lines (opt-in: "
                                                      "with fewer episodes than lines some lines never run).")]
    = None,
    seeds_per_line: Annotated[int | None, typer.Option(min=1, max=100, help="Run every line of each suite on this "
                                                       "many layouts (episodes = lines x seeds); the default is 2 "
                                                       "for the built-in suites, each line once for --tasks.")]
    = None,
    split: Annotated[str, typer.Option(help="Split of the built-in suites: dev (work against it) or test (held "
                                            "out: headline figures only, never tuned on).")] = "dev",
    suites: Annotated[str | None, typer.Option(help="Comma list of suites (localization, clutter, sequential, "
                                                    "search); default all four.")] = None,
    tasks: Annotated[Path | None, typer.Option(help="JSON Lines file of your own tasks: {command, suite, "
                                                    "target_object, destination, seed} per line.")] = None,
    seed: Annotated[int, typer.Option(help="Base seed for layouts of tasks without their own seed.")] = 0,
    parallel: Annotated[int, typer.Option(min=1, max=16, help="Simulated vehicles run at once (ev1..evK).")] = 1,
    out: Annotated[Path, typer.Option(help="Output directory (episodes.jsonl, report.md, report.json, plots/); "
                                           "rerunning with the same directory resumes.")] = Path("runs/eval"),
    speed_factor: Annotated[float, typer.Option(help="Simulator speed versus wall clock.")] = 4.0,
    t_max: Annotated[float, typer.Option(help="T_max per episode, seconds (paper: 600).")] = 600.0,
    tolerance: Annotated[float | None, typer.Option(hidden=True, help="Deprecated and ignored: the judge's "
                                                    "criteria are each task's ('criteria').")] = None,
    model: Annotated[str, typer.Option(help="Model name for a model backend.")] = "",
    output_mode: Annotated[str, typer.Option(help="Answer decoding: auto, schema, text, or both (the same episodes "
                                                  "once per mode into OUT/schema and OUT/text, compared in "
                                                  "OUT/modes.md).")] = "auto",
    paper_history: Annotated[bool, typer.Option(help="The paper's History only: each step's DRT and action, no "
                                                     "live detections or world map (AERMANI_REASONER_PAPER_HISTORY)."
                                                )] = False,
    free_text_baselines: Annotated[bool, typer.Option(help="Decode the unstructured and ReAct baselines as free "
                                                           "text, as the paper did (no answer schema).")] = False,
    base_url: Annotated[str | None, typer.Option(help="Base URL of an OpenAI-compatible endpoint.")] = None,
    connect: Annotated[str | None, typer.Option(help="Use vehicles already running behind this Zenoh router "
                                                     "instead of launching a stack (with --vehicles).")] = None,
    vehicles: Annotated[str | None, typer.Option(help="Comma list of vehicle ids to use with --connect.")] = None,
    note: Annotated[str, typer.Option(help="Sentence put at the top of the report (what the backend is).")] = "",
    segmenter: Annotated[str | None, typer.Option(help="Perception segmenter: color (default, real computer "
                                                       "vision), sam3, or sim (ground-truth oracle); with "
                                                       "--fork-from the recorded one by default.")] = None,
    realism: Annotated[str, typer.Option(help="Simulator realism: realistic (default), harsh or ideal.")] = "realistic",
    report_only: Annotated[bool, typer.Option(help="Rebuild the report from OUT/episodes.jsonl, run nothing.")]
    = False,
    progress: Annotated[bool, typer.Option(help="Show the progress bar.")] = True,
    fork_from: Annotated[Path | None, typer.Option(help="Instead of the suites: fork this recorded MCAP log before "
                                                        "--step, --forks times per method (backend x variants), and "
                                                        "report each method's success from that moment.")] = None,
    step: Annotated[int | None, typer.Option(min=1, help="With --fork-from: the step to continue before.")] = None,
    forks: Annotated[int, typer.Option(min=1, max=100, help="With --fork-from: forks per method; the first "
                                                            "continues the recorded noise, the others draw it "
                                                            "from seeds 1..N-1.")] = 3,
    fork_task: Annotated[str | None, typer.Option("--task-id", help="With --fork-from: the task to fork (when the "
                                                                     "log holds several).")] = None,
) -> None:
    """Evaluate a backend and prompt variants on the paper's task suites: SR, ARR, RS, IAR, RT, TT; or, with
    --fork-from LOG --step K, from one moment of a recorded flight: N live forks per method, their success rates."""
    from aermani.evaluation.report import write_report
    from aermani.evaluation.runner import RunConfig, run
    from aermani.evaluation.tasks import SPLITS

    if tolerance is not None:
        # Kept so the commands of older reports still run; a run-wide knob would let the caller loosen the
        # judge, so the value is not used.
        console.print(f"[yellow]--tolerance {tolerance:g} is ignored: the judge's criteria are each task's "
                      "('criteria' in its suite line; docs/evaluation.md)[/yellow]")
    if report_only and fork_from is None:
        paths = write_report(out)
        console.print(f"report: {paths['markdown']}")
        return
    sweeps = {"all": list(VARIANTS), "baselines": list(BASELINES)}
    variants = sweeps.get(variant.strip()) or [v.replace("-", "_") for v in _split(variant) or ["full"]]
    bad = [v for v in variants if v not in (*VARIANTS, *BASELINES)]
    if bad:
        console.print(f"[red]unknown variants {bad}; known: {', '.join((*VARIANTS, *BASELINES))}[/red]")
        raise typer.Exit(2)
    if backend == "rules" and any(v in BASELINES for v in variants):
        console.print(f"[red]the rules backend does not emulate the baseline frameworks "
                      f"({', '.join(v for v in variants if v in BASELINES)}); run them with a model backend "
                      "(--backend openai or anthropic)[/red]")
        raise typer.Exit(2)
    if fork_from is not None or step is not None:
        if fork_from is None or step is None:
            console.print("[red]--fork-from and --step go together: the log and the step to continue before[/red]")
            raise typer.Exit(2)
        _fork_eval(fork_from, step, fork_task, backend, variants, model, forks, out, base_url=base_url,
                   segmenter=segmenter, speed_factor=speed_factor, t_max=t_max,
                   note=note, progress=progress, report_only=report_only)
        return
    if split not in SPLITS:
        console.print(f"[red]unknown split {split!r}; use one of {', '.join(SPLITS)}[/red]")
        raise typer.Exit(2)
    if connect and not vehicles:
        console.print("[red]--connect needs --vehicles (the ids of the simulated vehicles to use)[/red]")
        raise typer.Exit(2)
    if output_mode not in ("auto", "schema", "text", "both"):
        console.print(f"[red]unknown output mode {output_mode!r}; use auto, schema, text or both[/red]")
        raise typer.Exit(2)
    api_key = os.environ.get("AERMANI_REASONER_API_KEY")
    if seeds_per_line is not None and episodes is not None:
        console.print("[red]--seeds-per-line and --episodes both set the number of episodes; give one[/red]")
        raise typer.Exit(2)
    modes = ["schema", "text"] if output_mode == "both" else [output_mode]
    cfg = RunConfig(out=out, backend=backend, output_mode=modes[0], variants=variants, model=model, base_url=base_url,
                    paper_history=paper_history, free_text_baselines=free_text_baselines,
                    api_key=api_key,
                    episodes=episodes, seeds_per_line=seeds_per_line,
                    split=split, suites=_split(suites), tasks_file=tasks, seed=seed, parallel=parallel,
                    speed_factor=speed_factor, t_max_s=t_max, connect=connect,
                    vehicles=_split(vehicles), progress=progress, note=note, segmenter=segmenter or "color",
                    realism=realism)
    # SIGTERM (and SIGINT, which a background job ignores) stop the run cleanly: finished episodes are kept.
    signal.signal(signal.SIGTERM, _interrupt)
    signal.signal(signal.SIGINT, _interrupt)
    for mode in modes:
        mode_cfg = cfg if len(modes) == 1 else cfg.model_copy(update={"out": out / mode, "output_mode": mode})
        try:
            summary = run(mode_cfg)
        except ConfigError as exc:
            console.print(f"[red]{terminal_text(exc)}[/red]")
            raise typer.Exit(2)
        console.print(f"{summary.ran} episodes run ({mode} answers), {summary.skipped} already finished (resumed), "
                      f"{summary.wall_s:.0f} s; report: {mode_cfg.out / 'report.md'}")
        if summary.interrupted:
            console.print("[yellow]interrupted: rerun the same command to resume[/yellow]")
            raise typer.Exit(130)
    if len(modes) > 1:
        from aermani.evaluation.report import write_mode_comparison

        console.print(f"modes compared: {write_mode_comparison(out, modes)}")


def _fork_eval(log: Path, step: int, task_id: str | None, backend: str, variants: list[str], model: str, forks: int,
               out: Path, *, base_url: str | None, segmenter: str | None, speed_factor: float, t_max: float,
               note: str, progress: bool, report_only: bool = False) -> None:
    """`aermani eval --fork-from LOG --step K` (aermani/evaluation/forks.py)."""
    from aermani.demo import backend_key_env
    from aermani.evaluation.forks import ForkRunError, Method, counted, read_rows, run_forks, write_report
    from aermani.evaluation.runner import source_revision
    from aermani.fork import ForkError, read_fork_point

    try:
        point = read_fork_point(log, step, task_id)
    except ForkError as exc:
        console.print(f"[red]{terminal_text(exc)}[/red]")
        raise typer.Exit(2) from None
    methods = [Method(backend, v, model) for v in variants]
    seg = segmenter or point.segmenter or "color"
    if report_only:
        rows = read_rows(out)
    else:
        key_env = backend_key_env(backend, None)
        if isinstance(key_env, str):
            console.print(f"[red]{terminal_text(key_env)}[/red]")
            raise typer.Exit(2)
        signal.signal(signal.SIGTERM, _interrupt)
        try:
            rows = run_forks(point, methods, forks, out, base_url=base_url, segmenter=seg,
                             speed_factor=speed_factor, t_max=t_max, key_env=key_env, progress=progress)
        except ForkRunError as exc:
            console.print(f"[red]{terminal_text(exc)}[/red]")
            raise typer.Exit(2) from None
    config = {"speed_factor": speed_factor, "segmenter": seg, "t_max": t_max, "note": note, "forks": forks,
              **source_revision()}
    path = write_report(point, rows, out, config)
    for t in _fork_summary(rows):
        console.print(t)
    console.print(f"{len(rows)} forks; report: {path}")
    if not report_only and len(counted(rows)) < len(methods) * forks:
        console.print("[yellow]interrupted: rerun the same command to resume[/yellow]")
        raise typer.Exit(130)


def _fork_summary(rows) -> list[str]:
    from aermani.evaluation.forks import summary

    return [f"{terminal_text(t['method'])}: {t['successes']}/{t['forks']} succeeded, SR {t['sr']:.0f} % "
            f"[{t['sr_ci'][0]:.0f}, {t['sr_ci'][1]:.0f}]" for t in summary(rows)]


def diff_command(
    a: Annotated[Path, typer.Argument(help="Run A: an MCAP log, an evaluation directory or its episodes.jsonl.")],
    b: Annotated[Path, typer.Argument(help="Run B, compared with A step by step.")],
    task_a: Annotated[str | None, typer.Option(help="Only this task (task id, or an evaluation's episode id) of A.")]
    = None,
    task_b: Annotated[str | None, typer.Option(help="Only this task of B.")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print the comparison as JSON.")] = False,
) -> None:
    """Two recorded runs side by side, step by step: what was measured (detections, held object, position), the
    DRT, the skill and argument, the outcome code, the grounding check's flags; marks the first step where they
    diverge (skill, argument or outcome) and every differing step after it."""
    import json

    from aermani.evaluation.diff import diff_runs, render
    from aermani.evaluation.runs import RunError

    try:
        result = diff_runs(str(a), str(b), task_a, task_b)
    except RunError as exc:
        Console(stderr=True, soft_wrap=True).print(f"[red]{terminal_text(exc)}[/red]")
        raise typer.Exit(2)
    if json_out:
        typer.echo(json.dumps(result.as_dict(), indent=1))
        return
    console.print(render(result))


def register(app: typer.Typer) -> None:
    app.command("eval")(eval_command)
    app.command("diff")(diff_command)
