"""What the services' `cli.py` files share: the `--connect`/`--vehicle` options, a command group, one query to
a running stack, and a bus that exists only when a router answers in time (`aermani/cli.py` loads the files)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Annotated, Any

import typer

if TYPE_CHECKING:
    from shared.bus import Bus

Connect = Annotated[str, typer.Option(help="Zenoh endpoint of the router.")]
Vehicle = Annotated[str, typer.Option(help="Vehicle id.")]


def command_group(app: typer.Typer, name: str, help: str, commands: dict[str, Callable[..., Any]]) -> typer.Typer:
    """Add `aermani <name> <command>` for each of `commands` (shows its help when called without one)."""
    group = typer.Typer(help=help, no_args_is_help=True)
    app.add_typer(group, name=name)
    for command, fn in commands.items():
        group.command(command)(fn)
    return group


async def query_once(connect: str, target: Any, request: Any = None, *, timeout: float) -> Any:
    """Open a bus to the router at `connect`, send one query to `target` (a declared key), close the bus."""
    from shared.bus import Bus

    async with await Bus.open(connect=[connect]) as bus:
        return await bus.query(target, request, timeout=timeout)


async def bus_if_up(connect: str, timeout: float) -> Bus | None:
    """A bus on the router at `connect`, or None when no router answers within `timeout` (for tools that
    use a running stack when there is one and work without it)."""
    from shared.bus import Bus

    try:
        return await Bus.open(connect=[connect], connect_timeout_s=timeout)
    except Exception:
        return None
