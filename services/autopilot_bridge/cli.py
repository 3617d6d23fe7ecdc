"""`aermani autopilot ...`: read the vehicle state and send autopilot commands by hand (bench tests, SITL)."""

from __future__ import annotations

import asyncio
import math
from typing import Annotated, Any

import typer
from rich.console import Console

from shared.bus import Bus
from shared.cli_helpers import Connect, Vehicle, query_once
from shared.errors import AermaniError
from shared.keys import Keys
from shared.messages import (
    ArmCommand,
    AutopilotResult,
    DisarmCommand,
    GotoCommand,
    GripperCommand,
    HoldCommand,
    LandCommand,
    PreflightCommand,
    TakeoffCommand,
    Vec3,
)

console = Console()
autopilot = typer.Typer(help="Vehicle state and autopilot commands through the autopilot bridge.",
                        no_args_is_help=True)



def _run(connect: str, vehicle: str, cmd: Any, timeout: float = 60.0) -> None:
    try:
        res: AutopilotResult = asyncio.run(query_once(connect, Keys(vehicle).autopilot_command, cmd,
                                                      timeout=timeout))
    except AermaniError as exc:
        console.print(f"[red]{exc}[/red]")
        raise typer.Exit(2)
    colour = "green" if res.ok else "red"
    ack = f" [{res.ack_name}]" if res.ack_name else ""
    console.print(f"[{colour}]{res.command}: {'ok' if res.ok else 'failed'}{ack}[/{colour}] {res.message}")
    if not res.ok:
        raise typer.Exit(1)


@autopilot.command()
def state(connect: Connect = "tcp/127.0.0.1:7447", vehicle: Vehicle = "am1",
          follow: Annotated[bool, typer.Option(help="Keep printing (Ctrl-C to stop).")] = False) -> None:
    """Print the vehicle state (and the bridge's health figures)."""

    async def body() -> None:
        bus = await Bus.open(connect=[connect])
        try:
            keys = Keys(vehicle)
            states = bus.subscribe(keys.autopilot_state, maxsize=1)
            health = bus.subscribe(keys.health("autopilot_bridge"), maxsize=1)
            while True:
                s = await states.recv(5.0)
                console.print(
                    f"{s.mode:<12} armed={s.armed!s:<5} {s.landed_state.value:<9} "
                    f"pos=({s.position.x:6.2f}, {s.position.y:6.2f}, {s.position.z:5.2f}) "
                    f"yaw={math.degrees(s.yaw):6.1f} deg link={s.link_ok} offboard={s.offboard_ok} "
                    f"gripper={s.gripper.value} {s.message}")
                h = health.latest_nowait()
                if h is not None and "jitter_p99_ms" in h.details:
                    d = h.details
                    console.print(f"  stream: interval p50 {d['interval_p50_ms']} ms, jitter p50 "
                                  f"{d['jitter_p50_ms']} / p99 {d['jitter_p99_ms']} ms, sent {d['setpoints_sent']}")
                if not follow:
                    return
                await asyncio.sleep(0.5)
        except TimeoutError:
            console.print("[red]no autopilot/state within 5 s: is the autopilot bridge running?[/red]")
            raise typer.Exit(2)
        finally:
            await bus.close()

    asyncio.run(body())


@autopilot.command()
def arm(connect: Connect = "tcp/127.0.0.1:7447", vehicle: Vehicle = "am1") -> None:
    """Arm the motors."""
    _run(connect, vehicle, ArmCommand())


@autopilot.command()
def disarm(connect: Connect = "tcp/127.0.0.1:7447", vehicle: Vehicle = "am1",
           force: Annotated[bool, typer.Option(help="Force past PX4's pre-checks (on the ground).")] = False,
           kill: Annotated[bool, typer.Option(help="Stop the motors even in the air: the vehicle falls "
                                                   "(emergency only; logged).")] = False) -> None:
    """Disarm the motors (in the air only with --kill)."""
    _run(connect, vehicle, DisarmCommand(force=force, kill=kill))


@autopilot.command()
def takeoff(altitude: Annotated[float, typer.Argument(help="Altitude above home, m.")] = 1.5,
            connect: Connect = "tcp/127.0.0.1:7447", vehicle: Vehicle = "am1") -> None:
    """Take off in OFFBOARD and hold at the altitude."""
    _run(connect, vehicle, TakeoffCommand(altitude=altitude), timeout=120.0)


@autopilot.command()
def goto(x: float, y: float, z: float,
         yaw_deg: Annotated[float, typer.Argument(help="Heading, degrees ENU (0 = +x, 90 = +y).")] = 0.0,
         speed: Annotated[float | None, typer.Option(help="Ramp the setpoint at this speed, m/s.")] = None,
         connect: Connect = "tcp/127.0.0.1:7447", vehicle: Vehicle = "am1") -> None:
    """Fly to a position (world ENU, m)."""
    _run(connect, vehicle, GotoCommand(position=Vec3(x=x, y=y, z=z), yaw=math.radians(yaw_deg), max_speed=speed))


@autopilot.command()
def hold(connect: Connect = "tcp/127.0.0.1:7447", vehicle: Vehicle = "am1") -> None:
    """Hold the current position."""
    _run(connect, vehicle, HoldCommand())


@autopilot.command()
def land(connect: Connect = "tcp/127.0.0.1:7447", vehicle: Vehicle = "am1") -> None:
    """Land where the vehicle is (AUTO.LAND)."""
    _run(connect, vehicle, LandCommand())


@autopilot.command()
def gripper(action: Annotated[str, typer.Argument(help="open or close")],
            connect: Connect = "tcp/127.0.0.1:7447", vehicle: Vehicle = "am1") -> None:
    """Open (release) or close (grab) the gripper."""
    if action not in ("open", "close"):
        console.print("[red]action must be open or close[/red]")
        raise typer.Exit(2)
    _run(connect, vehicle, GripperCommand(action=action))  # type: ignore[arg-type]


def preflight_cmd(connect: Connect = "tcp/127.0.0.1:7447", vehicle: Vehicle = "am1",
                  timeout: Annotated[float, typer.Option(help="Seconds to wait for the bridge's answer.")] = 30.0,
                  ) -> None:
    """Check that the vehicle is fit to fly before a task: PX4's failsafe parameters (offboard-loss action,
    geofence), read from the autopilot now, and the link, estimate, landed state and battery. Exit 0 when
    every check passes, 1 when one fails (the bridge also refuses to arm then), 2 when no bridge answers."""
    from rich.table import Table

    try:
        res: AutopilotResult = asyncio.run(query_once(connect, Keys(vehicle).autopilot_command, PreflightCommand(),
                                                      timeout=timeout))
    except AermaniError as exc:
        console.print(f"[red]{exc}[/red]")
        raise typer.Exit(2)
    table = Table(title=f"preflight of {vehicle}")
    for col in ("check", "value", "required", "verdict"):
        table.add_column(col)
    for c in res.checks:
        verdict = "[green]ok[/green]" if c.ok else f"[red]FAIL[/red] {c.reason}"
        table.add_row(c.name, c.value or "not reported", c.expected, verdict)
    if res.checks:
        console.print(table)
    colour = "green" if res.ok else "red"
    console.print(f"[{colour}]{res.message}[/{colour}]")
    if not res.ok:
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    app.add_typer(autopilot, name="autopilot")
    app.command("preflight")(preflight_cmd)
