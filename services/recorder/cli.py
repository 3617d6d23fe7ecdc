"""`aermani replay` and `aermani log show|export|recover` (`aermani rereason` is the reasoner's)."""

from __future__ import annotations

import asyncio
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from shared.cli_helpers import command_group
from shared.text import plain_text, terminal_text

console = Console()
err = Console(stderr=True)

LogArg = Annotated[Path, typer.Argument(help="An MCAP log written by the recorder.", exists=True, dir_okay=False)]


def register(app: typer.Typer) -> None:
    command_group(app, "log", "Inspect, report on and repair MCAP logs.",
                  {"show": show_cmd, "export": export_cmd, "recover": recover_cmd})
    app.command("replay")(replay_cmd)


def replay_cmd(
    log: LogArg,
    speed: Annotated[float, typer.Option(help="1 = original timing, 2 = twice as fast, 0 = as fast as possible.")]
    = 1.0,
    keys: Annotated[str | None, typer.Option(help="Only keys matching this key expression, "
                                                   "e.g. 'aermani/*/am1/reasoner/**'.")] = None,
    start: Annotated[float | None, typer.Option(help="Start this many seconds into the log.")] = None,
    end: Annotated[float | None, typer.Option(help="Stop this many seconds into the log.")] = None,
    connect: Annotated[str, typer.Option(help="Zenoh endpoint of the router.")] = "tcp/127.0.0.1:7447",
    include_control: Annotated[bool, typer.Option(help="Also republish abort and command keys (off: on a live "
                                                       "bus they would stop or move a vehicle).")] = False,
    vehicle: Annotated[str | None, typer.Option(help="Republish every vehicle's samples under this vehicle id.")]
    = None,
    remap: Annotated[list[str] | None, typer.Option(help="OLD=NEW vehicle id (repeatable).")] = None,
    onto_live: Annotated[bool, typer.Option("--onto-live", help="Replay onto a vehicle id whose autopilot bridge "
                                            "or simulator answers now (off: refused; replay beside it with "
                                            "--vehicle or --remap).")] = False,
) -> None:
    """Republish a log on Zenoh verbatim (same keys, bytes, encodings) so the web page, Foxglove and any
    service see the flight again. Abort and command keys are left out unless --include-control; a vehicle that
    is live now is refused unless --onto-live."""
    from services.recorder.replay import ReplayOntoLive, replay
    from shared.bus import Bus
    from shared.keys import vehicle_prefix

    mapping: dict[str, str] = {"*": vehicle} if vehicle else {}
    for item in remap or []:
        old, sep, new = item.partition("=")
        if not sep or not old or not new:
            err.print(f"[red]--remap {item!r}: use OLD=NEW, e.g. am1=replay1[/red]")
            raise typer.Exit(2)
        mapping[old] = new
    try:
        for new in mapping.values():
            vehicle_prefix(new)
    except ValueError as exc:
        err.print(f"[red]{terminal_text(exc)}[/red]")
        raise typer.Exit(2)

    async def run() -> None:
        bus = await Bus.open(connect=[connect])
        try:
            res = await replay(bus, log, speed=speed, keys=keys, start_s=start, end_s=end,
                               include_control=include_control, remap=mapping or None, onto_live=onto_live)
            # Let the last samples leave the session before it closes.
            await asyncio.sleep(0.5)
        finally:
            await bus.close()
        console.print(f"replayed {res.published} samples from {log} in {res.wall_s:.1f} s "
                      f"({(res.last_log_ns - res.first_log_ns) / 1e9:.1f} s of log)")
        if res.skipped_control:
            console.print(f"left out {sum(res.skipped_control.values())} control samples "
                          f"({', '.join(sorted(res.skipped_control))}); --include-control republishes them")

    try:
        asyncio.run(run())
    except KeyboardInterrupt:
        raise typer.Exit(130)
    except ReplayOntoLive as exc:
        err.print(f"[red]{terminal_text(exc)}[/red]")
        raise typer.Exit(2)


def show_cmd(
    log: LogArg,
    as_json: Annotated[bool, typer.Option("--json", help="Machine-readable output.")] = False,
    vehicle: Annotated[str | None, typer.Option(help="Only this vehicle id.")] = None,
) -> None:
    """A readable timeline of each task: command, every step's STE, reasoning, skill result and timing,
    final metrics."""
    from services.recorder.timeline import render_text, to_json

    if as_json:
        typer.echo(to_json(log, vehicle))
    else:
        typer.echo(plain_text(render_text(log, vehicle), lines=True))  # the models' reasoning, as data


class ExportFormat(StrEnum):
    """What `log export` writes."""

    html = "html"
    ros2 = "ros2"
    lerobot = "lerobot"


def export_cmd(
    log: LogArg,
    out: Annotated[Path, typer.Option(help="Directory for index.html and the frames (ros2: the new rosbag2 "
                                           "directory; lerobot: the dataset directory).")],
    vehicle: Annotated[str | None, typer.Option(help="Only this vehicle id.")] = None,
    fmt: Annotated[ExportFormat, typer.Option(
        "--format", help="html: a report, each step's camera frame beside its DRT; ros2: a ROS 2 bag (rosbag2, "
                         "MCAP storage, CDR): camera, camera_info, /tf, pose and reasoning steps; lerobot: a "
                         "LeRobot v3.0 training dataset, one frame per reasoning step, one episode per task "
                         "(docs/recording.md).")] = ExportFormat.html,
    ros2: Annotated[bool, typer.Option("--ros2", help="Same as --format ros2.")] = False,
    overwrite: Annotated[bool, typer.Option(help="lerobot: replace an earlier export in --out (a non-empty "
                                                 "directory is refused otherwise).")] = False,
) -> None:
    """An HTML report (the camera frame of each step beside its DRT), a ROS 2 bag, or a LeRobot dataset."""
    if ros2:
        if fmt not in (ExportFormat.html, ExportFormat.ros2):
            err.print(f"[red]--ros2 and --format {fmt.value} contradict each other[/red]")
            raise typer.Exit(2)
        fmt = ExportFormat.ros2
    if fmt is ExportFormat.ros2:
        from services.recorder.ros2 import Ros2ExportError, export_ros2

        try:
            typer.echo(export_ros2(log, out, vehicle).render())
        except Ros2ExportError as exc:
            err.print(f"[red]{terminal_text(exc)}[/red]")
            raise typer.Exit(2)
        return
    if fmt is ExportFormat.lerobot:
        _export_lerobot(log, out, vehicle, overwrite)
        return
    from services.recorder.timeline import export_html

    index = export_html(log, out, vehicle)
    console.print(f"wrote {index}")


def _export_lerobot(log: Path, out: Path, vehicle: str | None, overwrite: bool) -> None:
    from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn

    from services.recorder.lerobot import LeRobotExportError, export_lerobot

    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), TaskProgressColumn(), TimeElapsedColumn(),
                  console=err, transient=True) as progress:
        bar = progress.add_task("reading the log", total=None)

        def on_progress(done: int, total: int) -> None:
            progress.update(bar, completed=done, total=total or None)

        try:
            res = export_lerobot(log, out, vehicle, overwrite=overwrite, on_progress=on_progress)
        except LeRobotExportError as exc:
            progress.stop()
            err.print(f"[red]{terminal_text(exc)}[/red]")
            raise typer.Exit(2)
    typer.echo(plain_text(res.render(), lines=True))


def recover_cmd(
    log: Annotated[Path, typer.Argument(help="A log that was not finished (recorder killed, power lost).",
                                        exists=True, dir_okay=False)],
    out: Annotated[Path | None, typer.Option(help="Where the repaired log goes (default <LOG>.recovered.mcap).")]
    = None,
) -> None:
    """Salvage every complete chunk of an unfinished log into a finished, indexed one."""
    from shared.mcaplog import recover

    dst = out or log.with_suffix(".recovered.mcap")
    if dst.resolve() == log.resolve():
        err.print("[red]--out must differ from the broken log[/red]")
        raise typer.Exit(2)
    res = recover(log, dst)
    state = "the log was complete" if res.complete else f"stopped at: {res.error or 'end of file'}"
    typer.echo(f"recovered {res.messages} messages in {len(res.channels)} channels from {res.chunks} "
               f"complete chunks into {dst} ({state})")
