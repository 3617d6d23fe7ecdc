"""`aermani sim render|reset|judge|stats`: preview layouts offline and poke a running simulator."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from shared.cli_helpers import Connect, Vehicle, command_group, query_once
from shared.text import terminal_text

console = Console()



def register(app: typer.Typer) -> None:
    command_group(app, "sim", "The built-in simulator: preview layouts, reset, judge, stats.",
                  {"render": render_cmd, "reset": reset_cmd, "judge": judge_cmd, "stats": stats_cmd})


def _scenario(seed: int, target: str | None, destination: str | None, out_of_view: bool):
    from shared.messages import Scenario

    return Scenario(seed=seed, target_object=target, destination=destination, target_out_of_view=out_of_view)


def render_cmd(
    seed: Annotated[int, typer.Option(help="Layout seed.")] = 0,
    target: Annotated[str | None, typer.Option(help="Target object, e.g. 'red cup'.")] = None,
    destination: Annotated[str | None, typer.Option(help="Destination surface.")] = None,
    out_of_view: Annotated[bool, typer.Option(help="Put the target out of the initial view.")] = False,
    altitude: Annotated[float, typer.Option(help="Camera height above the start point, metres.")] = 1.5,
    realism: Annotated[str, typer.Option(help="realistic (stereo camera flaws), harsh or ideal.")] = "realistic",
    out: Annotated[Path, typer.Option(help="PNG to write (a _seg.png with instance colours goes beside it).")]
    = Path("sim_view.png"),
) -> None:
    """Render the start view of a scenario offline (no bus, no processes) and print its layout."""
    import cv2
    import numpy as np

    from services.sim.physics import look_for
    from services.sim.render import preview
    from services.sim.scenarios import ScenarioError, generate

    try:
        world, scen, start = generate(_scenario(seed, target, destination, out_of_view), look=look_for(realism))
    except ScenarioError as exc:
        console.print(f"[red]{terminal_text(exc)}[/red]")
        raise typer.Exit(2)
    frame = preview(world, np.array([start.position.x, start.position.y, altitude]), start.yaw, realism)
    cv2.imwrite(str(out), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
    palette = np.random.default_rng(0).integers(40, 255, (int(frame.instance.max()) + 1, 3), dtype=np.uint8)
    palette[0] = 0
    cv2.imwrite(str(out.with_name(out.stem + "_seg.png")), palette[frame.instance])
    console.print(scen.model_dump_json(indent=2), markup=False, highlight=False)
    visible = set(np.unique(frame.instance).tolist())
    for e in world.entities:
        if e.category in ("object", "surface", "furniture"):
            where = f"on {e.support}" if e.support else ""
            console.print(f"{e.id:4d} {e.name:15s} {e.category:9s} ({e.center[0]:+.2f}, {e.center[1]:+.2f}, "
                          f"{e.center[2]:+.2f}) {where:20s} {'visible' if e.id in visible else ''}", highlight=False)
    console.print(f"wrote {out}")


async def _query(connect: str, key_attr: str, vehicle: str, request):
    from shared.keys import Keys

    return await query_once(connect, getattr(Keys(vehicle), key_attr), request, timeout=20)


def reset_cmd(
    seed: Annotated[int, typer.Option(help="Layout seed.")] = 0,
    target: Annotated[str | None, typer.Option(help="Target object.")] = None,
    destination: Annotated[str | None, typer.Option(help="Destination surface.")] = None,
    out_of_view: Annotated[bool, typer.Option(help="Put the target out of the initial view.")] = False,
    connect: Connect = "tcp/127.0.0.1:7447",
    vehicle: Vehicle = "am1",
) -> None:
    """Reset the running simulator to a scenario (vehicle back on the ground, disarmed)."""
    res = asyncio.run(_query(connect, "sim_reset", vehicle, _scenario(seed, target, destination, out_of_view)))
    console.print(res.model_dump_json(indent=2), markup=False, highlight=False)
    if not res.ok:
        raise typer.Exit(1)


def judge_cmd(
    obj: Annotated[str | None, typer.Option("--object", help="With --surface: is this object on it?")] = None,
    surface: Annotated[str | None, typer.Option(help="Surface for --object.")] = None,
    connect: Connect = "tcp/127.0.0.1:7447",
    vehicle: Vehicle = "am1",
) -> None:
    """Ground truth from the running simulator (evaluation only)."""
    from shared.messages import JudgeRequest

    req = JudgeRequest(op="on_surface", object=obj, surface=surface) if obj else JudgeRequest(op="world")
    res = asyncio.run(_query(connect, "sim_judge", vehicle, req))
    console.print(res.model_dump_json(indent=2), markup=False, highlight=False)


def stats_cmd(connect: Connect = "tcp/127.0.0.1:7447", vehicle: Vehicle = "am1") -> None:
    """Frame rate, setpoint-stream intervals and MAVLink counters of the running simulator."""
    stats = asyncio.run(_query(connect, "sim_stats", vehicle, None))
    console.print_json(json.dumps(stats))
