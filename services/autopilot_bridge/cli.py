"""`aermani autopilot ...`: read the vehicle state and send autopilot commands by hand (bench tests, SITL)."""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from typing import Annotated, Any

import typer
from rich.console import Console

from services.autopilot_bridge.preflight import summary
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
    PreflightCheck,
    PreflightCommand,
    PreflightReport,
    TakeoffCommand,
    Vec3,
)
from shared.text import terminal_text

console = Console()
autopilot = typer.Typer(help="Vehicle state and autopilot commands through the autopilot bridge.",
                        no_args_is_help=True)



def _run(connect: str, vehicle: str, cmd: Any, timeout: float = 60.0) -> None:
    try:
        res: AutopilotResult = asyncio.run(query_once(connect, Keys(vehicle).autopilot_command, cmd,
                                                      timeout=timeout))
    except AermaniError as exc:
        console.print(f"[red]{terminal_text(exc)}[/red]")
        raise typer.Exit(2)
    colour = "green" if res.ok else "red"
    ack = f" {terminal_text(f'[{res.ack_name}]')}" if res.ack_name else ""
    console.print(f"[{colour}]{terminal_text(res.command)}: {'ok' if res.ok else 'failed'}{ack}[/{colour}] "
                  f"{terminal_text(res.message)}")
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
                    f"{terminal_text(s.mode):<12} armed={s.armed!s:<5} {s.landed_state.value:<9} "
                    f"pos=({s.position.x:6.2f}, {s.position.y:6.2f}, {s.position.z:5.2f}) "
                    f"yaw={math.degrees(s.yaw):6.1f} deg link={s.link_ok} offboard={s.offboard_ok} "
                    f"gripper={s.gripper.value} {terminal_text(s.message)}")
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


async def _bus_round_trip_ms(bus: Bus, keys: Keys) -> tuple[float | None, str]:
    """Median of three round trips to a drone-side service (the executor's skill list, a small answer from
    the vehicle's side of the link), or through the router alone when no executor runs; and which it was."""
    from shared.errors import NoResponder

    times = []
    for _ in range(3):
        t0 = time.monotonic()
        try:
            await bus.query(keys.skills, timeout=2.0)
        except NoResponder:
            break
        except AermaniError:
            return None, "executor"
        times.append((time.monotonic() - t0) * 1e3)
    if times:
        return sorted(times)[len(times) // 2], "executor"
    from shared.keys import alive_pattern

    t0 = time.monotonic()
    await bus.alive(alive_pattern(keys.vehicle_id), timeout=2.0)
    return (time.monotonic() - t0) * 1e3, "router only: no executor runs"


async def _measure_operator(bus: Bus, keys: Keys, window_s: float) -> tuple[float | None, float | None,
                                                                            float | None, float | None, str]:
    """(camera fps, newest frame's age s, MAVLink messages/s at the bridge, bus round trip ms, what the round
    trip reached) over `window_s`. Frame rates come from receive times; the frame's age compares its stamp with
    this machine's clock, so the drone's and the ground's clocks must agree (chrony/NTP)."""
    from shared.sensors import CompressedImage, decode_proto, stamp_to_ns

    frames = bus.subscribe(keys.camera_color, maxsize=256, overflow="drop_oldest")
    health = bus.subscribe(keys.health("autopilot_bridge"), maxsize=16, overflow="drop_oldest")
    bus_ms, reached = await _bus_round_trip_ms(bus, keys)
    arrivals: list[int] = []
    newest_stamp_ns: int | None = None
    counts: list[tuple[int, int]] = []  # (health stamp ns, mavlink_received)
    deadline = time.monotonic() + window_s
    while (left := deadline - time.monotonic()) > 0:
        with contextlib.suppress(TimeoutError):
            sample = await frames.recv_sample(timeout=min(left, 0.1))
            arrivals.append(sample.receive_ns)
            with contextlib.suppress(AermaniError):
                newest_stamp_ns = stamp_to_ns(decode_proto(CompressedImage, sample.payload).timestamp)
        while (h := health.recv_nowait()) is not None:
            if isinstance(h.details.get("mavlink_received"), int):
                counts.append((h.stamp_ns, h.details["mavlink_received"]))
    fps = (len(arrivals) - 1) / ((arrivals[-1] - arrivals[0]) / 1e9) \
        if len(arrivals) >= 2 and arrivals[-1] > arrivals[0] else None
    age = (time.time_ns() - newest_stamp_ns) / 1e9 if newest_stamp_ns is not None else None
    link_hz = None
    if len(counts) >= 2 and counts[-1][0] > counts[0][0]:
        link_hz = (counts[-1][1] - counts[0][1]) / ((counts[-1][0] - counts[0][0]) / 1e9)
    return fps, age, link_hz, bus_ms, reached


def preflight_cmd(connect: Connect = "tcp/127.0.0.1:7447", vehicle: Vehicle = "am1",
                  timeout: Annotated[float, typer.Option(help="Seconds to wait for the bridge's answer.")] = 30.0,
                  window: Annotated[float, typer.Option(help="Seconds to watch the camera and the link.")] = 3.0,
                  min_fps: Annotated[float, typer.Option(help="Camera frame rate required.")] = 5.0,
                  max_frame_age: Annotated[float, typer.Option(help="Newest camera frame's age allowed, s.")] = 0.5,
                  min_link_hz: Annotated[float, typer.Option(help="MAVLink messages/s the bridge must receive.")]
                  = 10.0,
                  max_bus_ms: Annotated[float, typer.Option(help="Bus round trip through the router allowed, ms.")]
                  = 200.0,
                  ) -> None:
    """Check that the vehicle is fit to fly before a task: PX4's failsafe parameters (offboard-loss action,
    geofence), read from the autopilot now, the link, estimate, landed state and battery (the bridge's take-off
    gate), and from here the camera's frame rate and frame age, the MAVLink message rate and the bus round trip.
    The verdict is published on autopilot/preflight, so a recording keeps it. Exit 0 when every check passes, 1
    when one fails (the bridge refuses to arm when one of its own fails), 2 when no bridge answers."""
    from rich.table import Table

    from services.autopilot_bridge.preflight import OperatorLimits, check_operator

    limits = OperatorLimits(min_fps=min_fps, max_frame_age_s=max_frame_age, min_link_hz=min_link_hz,
                            max_bus_ms=max_bus_ms)
    keys = Keys(vehicle)

    async def body() -> tuple[AutopilotResult, list[PreflightCheck]]:
        async with await Bus.open(connect=[connect]) as bus:
            res: AutopilotResult = await bus.query(keys.autopilot_command, PreflightCommand(), timeout=timeout)
            if not res.checks:
                return res, []
            fps, age, link_hz, bus_ms, reached = await _measure_operator(bus, keys, window)
            checks = [*res.checks, *check_operator(fps, age, link_hz, bus_ms, limits, reached)]
            bus.publish(keys.autopilot_preflight, PreflightReport(
                vehicle_id=vehicle, trigger="operator", ok=all(c.ok for c in checks), checks=tuple(checks)))
            await asyncio.sleep(0.2)  # let the report leave before the session closes
            return res, checks

    try:
        res, checks = asyncio.run(body())
    except AermaniError as exc:
        console.print(f"[red]{terminal_text(exc)}[/red]")
        raise typer.Exit(2)
    if not checks:  # the bridge ran no check (no link yet): its message says why
        console.print(f"[red]{terminal_text(res.message)}[/red]")
        raise typer.Exit(1)
    table = Table(title=f"preflight of {terminal_text(vehicle)}")
    for col in ("check", "value", "required", "verdict"):
        table.add_column(col)
    for c in checks:
        verdict = (f"[green]ok[/green]{' [yellow]note[/yellow] ' + terminal_text(c.reason) if c.reason else ''}"
                   if c.ok else f"[red]FAIL[/red] {terminal_text(c.reason)}")
        table.add_row(terminal_text(c.name), terminal_text(c.value or "not reported"), terminal_text(c.expected),
                      verdict)
    console.print(table)
    ok = all(c.ok for c in checks)
    text = terminal_text(summary(checks))
    console.print(f"[{'green' if ok else 'red'}]{text}[/{'green' if ok else 'red'}]")
    if not ok:
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    app.add_typer(autopilot, name="autopilot")
    app.command("preflight")(preflight_cmd)
