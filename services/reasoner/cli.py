"""`aermani vlm check FILE` (validate recorded model answers), `aermani vlm backends` and `aermani rereason LOG`
(the reasoner's decisions again, offline). `aermani demo` and `aermani vlm probe` start services, so they are the
application's (aermani/demo.py, aermani/probe.py)."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from shared.cli_helpers import command_group
from shared.messages import BASELINES, VARIANTS
from shared.text import plain_text, terminal_text

console = Console()


# --------------------------------------------------------------------------- vlm check


async def _live_library(connect: str, timeout: float):
    """The executor's registry if a router and an executor answer within `timeout`, else None."""
    from shared.cli_helpers import bus_if_up
    from shared.keys import Keys

    bus = await bus_if_up(connect, timeout)
    if bus is None:
        return None
    try:
        return await bus.query(Keys().skills, None, timeout=timeout)
    except Exception:
        return None
    finally:
        await bus.close()


def check_command(
    file: Annotated[Path, typer.Argument(help="One JSON-encoded string (a model answer) per line.")],
    variant: Annotated[str, typer.Option(help="Prompt variant the answers were given for "
                                              f"({', '.join((*VARIANTS, *BASELINES))}).")] = "full",
    connect: Annotated[str, typer.Option(help="Zenoh router to ask for the executor's live skill library.")]
    = "tcp/127.0.0.1:7447",
    offline: Annotated[bool, typer.Option(help="Use the built-in default skill library without asking.")] = False,
    coverage: Annotated[float, typer.Option(help="Fraction of skills the action predictions must cover.")] = 1.0,
) -> None:
    """Print, per line, whether the answer is accepted (and the skill) or the reason it is rejected."""
    from services.reasoner.baselines import restrict_library
    from services.reasoner.library import default_library
    from services.reasoner.parse import parse_answer
    from shared.errors import InvalidAnswer

    variant = variant.replace("-", "_")
    if variant not in (*VARIANTS, *BASELINES):
        console.print(f"[red]unknown variant {variant!r}; use one of {', '.join((*VARIANTS, *BASELINES))}[/red]")
        raise typer.Exit(2)
    try:
        lines = file.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        console.print(f"[red]cannot read {terminal_text(file)}: {terminal_text(exc)}[/red]")
        raise typer.Exit(2)
    library = None if offline else asyncio.run(_live_library(connect, 2.0))
    source = "executor's live registry" if library is not None else "built-in default library"
    library = restrict_library(variant, library or default_library())  # waypoint: the motion primitives only
    console.print(f"checking {file} against the {source} (variant {variant})")
    rejected = total = 0
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        total += 1
        try:
            raw = json.loads(line)
            if not isinstance(raw, str):
                raise ValueError("the line is JSON but not a string")
        except ValueError as exc:
            rejected += 1
            console.print(f"{n}: rejected: line is not a JSON-encoded string ({plain_text(exc)})", markup=False)
            continue
        try:
            p = parse_answer(raw, variant, library, coverage=coverage)
        except InvalidAnswer as exc:
            rejected += 1
            console.print(f"{n}: rejected: {plain_text(exc)}", markup=False)  # it may quote the answer
            continue
        except Exception as exc:  # the parser promises InvalidAnswer only; a bug still must not stop the file
            rejected += 1
            console.print(f"{n}: rejected: parser error {type(exc).__name__}: {plain_text(exc)} (please report)",
                          markup=False)
            continue
        call = p.ste.call
        console.print(f"{n}: accepted: {plain_text(call)}" + (" (recovered leniently)" if p.recovered else ""),
                      markup=False)
    console.print(f"{total - rejected}/{total} accepted, {rejected} rejected")
    if rejected:
        raise typer.Exit(1)


def backends_command() -> None:
    """List the registered policy backends (the values of AERMANI_REASONER_BACKEND and --backend)."""
    from services.reasoner.backends import BACKENDS, load_backend_modules
    from services.reasoner.settings import ReasonerSettings

    load_backend_modules(ReasonerSettings().backend_modules)
    for kind, cls in BACKENDS.items():
        console.print(f"{kind:<12} {cls.summary}", markup=False)


def register(app: typer.Typer) -> None:
    command_group(app, "vlm", "Tools for VLM answers and backends.",
                  {"check": check_command, "backends": backends_command})
    app.command("rereason")(rereason_cmd)


LogArg = Annotated[Path, typer.Argument(help="An MCAP log written by the recorder.", exists=True, dir_okay=False)]


def rereason_cmd(
    log: LogArg,
    backend: Annotated[str, typer.Option(help="Backend to re-run the decisions with (`aermani vlm backends`; "
                                              "replay reads --answers).")] = "rules",
    variant: Annotated[str | None, typer.Option(help="Prompt variant (default: the recorded one).")] = None,
    model: Annotated[str | None, typer.Option(help="Model name for a model backend.")] = None,
    task: Annotated[str | None, typer.Option(help="Only this task id.")] = None,
    answers: Annotated[Path | None, typer.Option(help="For --backend replay: the log whose recorded answers "
                                                     "to replay.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Machine-readable output.")] = False,
) -> None:
    """Re-run the reasoner's decision step offline on the recorded observations (same frames, same history)
    with another backend or variant; report agreement with the recorded decisions. No vehicle moves."""
    from services.reasoner.rereason import RereasonError, rereason_log

    try:
        res = asyncio.run(rereason_log(log, backend=backend, variant=variant, model=model, task_id=task,
                                       answers=answers))
    except RereasonError as exc:
        Console(stderr=True).print(f"[red]{terminal_text(exc)}[/red]")
        raise typer.Exit(2)
    if as_json:
        typer.echo(json.dumps(res.as_dict(), indent=2, default=str))
    else:
        typer.echo(plain_text(res.render(), lines=True))  # it quotes the answers' arguments and errors
