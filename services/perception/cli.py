"""`aermani perception object|place|detections`: ask a running perception service from the shell."""

from __future__ import annotations

import asyncio
from typing import Annotated

import typer
from rich.console import Console

from shared.cli_helpers import Connect, Vehicle, command_group, query_once
from shared.text import terminal_text

console = Console()



def register(app: typer.Typer) -> None:
    command_group(app, "perception", "Perception: localize objects and placement spots, watch detections.",
                  {"object": object_cmd, "place": place_cmd, "detections": detections_cmd})


async def _ask(connect: str, vehicle: str, key_name: str, query: str, size: tuple[float, float, float] | None):
    from shared.keys import Keys
    from shared.messages import LocalizeRequest, Vec3

    keys = Keys(vehicle)
    key = keys.localize_object if key_name == "object" else keys.localize_placement
    req = LocalizeRequest(query=query, object_size=Vec3(x=size[0], y=size[1], z=size[2]) if size else None)
    return await query_once(connect, key, req, timeout=10)


def _show(est) -> None:
    color = "green" if est.found else "yellow"
    console.print(f"[{color}]{terminal_text(est.reason)}[/{color}] {terminal_text(est.label or est.query)}: "
                  f"{terminal_text(est.message)}")
    console.print_json(est.model_dump_json(exclude_none=True))


def object_cmd(query: Annotated[str, typer.Argument(help="Object query, e.g. 'red cup'.")],
               connect: Connect = "tcp/127.0.0.1:7447", vehicle: Vehicle = "am1") -> None:
    """obj_localization: where is this object (world ENU), how big, how sure."""
    _show(asyncio.run(_ask(connect, vehicle, "object", query, None)))


def place_cmd(query: Annotated[str, typer.Argument(help="Surface query, e.g. 'round table'.")],
              size: Annotated[tuple[float, float, float] | None, typer.Option(help="Held object size x y z, m.")]
              = None, connect: Connect = "tcp/127.0.0.1:7447", vehicle: Vehicle = "am1") -> None:
    """placement_localization: a free spot on this surface and the release height."""
    _show(asyncio.run(_ask(connect, vehicle, "place", query, size)))


def detections_cmd(connect: Connect = "tcp/127.0.0.1:7447", vehicle: Vehicle = "am1",
                   timeout: Annotated[float, typer.Option(help="Seconds to wait.")] = 5.0) -> None:
    """Print the next perception/detections message."""
    from shared.bus import Bus
    from shared.keys import Keys
    from shared.messages import Detections

    async def body() -> Detections:
        async with await Bus.open(connect=[connect]) as bus:
            return await bus.subscribe(Keys(vehicle).detections).recv(timeout)

    try:
        dets = asyncio.run(body())
    except TimeoutError:
        console.print(f"[red]no detections within {timeout} s: is perception running with frames?[/red]")
        raise typer.Exit(1)
    for d in dets.items:
        c = d.centroid
        where = f"({c.x:.2f}, {c.y:.2f}, {c.z:.2f})" if c else "-"
        console.print(f"{terminal_text(d.category):9s} {terminal_text(d.label):15s} {where} conf {d.confidence:.2f} "
                      f"points {d.n_points}")
