"""Preflight: the checks the bridge runs before it arms, and answers to a `preflight` command.

PX4 decides what happens when this stack fails mid-flight: the offboard-loss action runs when the setpoint
stream stops (the bridge, its link or its host died), the geofence action when the vehicle leaves its fence.
Those are PX4 parameters, set by whoever configured the airframe; a wrong value is invisible until the day it
matters. So before arming, the bridge reads them over MAVLink (PARAM_REQUEST_READ -> PARAM_VALUE) and checks
them with the vehicle's state: a fresh link, a local position estimate, on the ground and disarmed, enough
battery. A failed check refuses the arm with every reason; `AERMANI_AUTOPILOT_BRIDGE_PREFLIGHT_OVERRIDE=1` flies
anyway (logged on every arm).

The rules are for an indoor manipulation drone flown in OFFBOARD without a pilot on the sticks.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from shared.messages import LandedState, PreflightCheck


@dataclass(frozen=True)
class ParamRule:
    """One PX4 parameter: the values it may take to fly, said for a person, and why it matters."""

    name: str
    ok: Callable[[float], bool]
    expected: str
    reason: str
    show: Callable[[float], str] = lambda v: f"{v:g}"
    note: Callable[[float], str] = lambda v: ""
    """A caveat for an accepted value the operator should know (the check's `reason` when it passes)."""


# PX4 >= 1.14 enum values (COM_OBL_RC_ACT: 0 Position, 1 Altitude, 2 Manual, 3 Return, 4 Land, 5 Hold,
# 6 Terminate, 7 Disarm; GF_ACTION: 0 None, 1 Warning, 2 Hold, 3 Return, 4 Terminate, 5 Land).
OBL_NAMES = {0: "Position", 1: "Altitude", 2: "Manual", 3: "Return", 4: "Land", 5: "Hold", 6: "Terminate",
             7: "Disarm"}
GF_NAMES = {0: "None", 1: "Warning", 2: "Hold", 3: "Return", 4: "Terminate", 5: "Land"}


def _named(names: dict[int, str]) -> Callable[[float], str]:
    return lambda v: f"{v:g} ({names.get(int(v), 'unknown')})"


LAND_NOTE = ("Land lands wherever the vehicle is when the stack dies, possibly on furniture and on a held object; "
             "5 Hold (or 0 Position) is recommended: it holds until the restarted stack or the pilot lands clear")

RULES: tuple[ParamRule, ...] = (
    ParamRule("COM_OBL_RC_ACT", lambda v: int(v) in (0, 4, 5), "5 Hold or 0 Position (recommended), or 4 Land",
              "what PX4 does when the offboard setpoints stop (bridge, link or companion computer gone): Return "
              "climbs to the return altitude under a ceiling, Terminate and Disarm drop the vehicle, Altitude and "
              "Manual need a pilot on the sticks", _named(OBL_NAMES),
              lambda v: LAND_NOTE if int(v) == 4 else ""),
    ParamRule("COM_OF_LOSS_T", lambda v: 0.0 < v <= 1.0, "> 0 and <= 1 s",
              "how long PX4 flies on the last setpoint after the stream stops before the offboard-loss action"),
    ParamRule("GF_ACTION", lambda v: int(v) in (2, 5), "2 Hold or 5 Land",
              "what PX4 does at the geofence: None and Warning let a runaway vehicle leave the room, Return climbs, "
              "Terminate drops it", _named(GF_NAMES)),
    ParamRule("GF_MAX_HOR_DIST", lambda v: v > 0.0, "> 0 m (0 disables the horizontal fence)",
              "the horizontal geofence around home: PX4's own fence, behind the bridge's"),
    ParamRule("GF_MAX_VER_DIST", lambda v: v > 0.0, "> 0 m (0 disables the vertical fence)",
              "the vertical geofence above home: PX4's own ceiling, behind the bridge's"),
)
PARAM_NAMES = tuple(r.name for r in RULES)


def check_params(params: dict[str, float | None]) -> list[PreflightCheck]:
    """A check per rule; a parameter the autopilot did not report fails (its behaviour is unknown)."""
    out = []
    for r in RULES:
        v = params.get(r.name)
        if v is None or not math.isfinite(v):
            out.append(PreflightCheck(name=r.name, ok=False, expected=r.expected,
                                      reason=f"the autopilot did not report it: {r.reason}"))
            continue
        good = r.ok(v)
        out.append(PreflightCheck(name=r.name, ok=good, value=r.show(v), expected=r.expected,
                                  reason=r.note(v) if good else r.reason))
    return out


@dataclass(frozen=True)
class VehicleFacts:
    """What the bridge knows of the vehicle when the preflight runs."""

    link_ok: bool
    have_position: bool
    armed: bool
    landed_state: LandedState
    battery_remaining: float | None
    override: str


def check_state(f: VehicleFacts, min_battery: float) -> list[PreflightCheck]:
    """Link, estimate, on the ground and disarmed, battery, no pilot or failsafe in control."""
    battery = f.battery_remaining
    return [
        PreflightCheck(name="link", ok=f.link_ok, value="heartbeats" if f.link_ok else "none",
                       expected="PX4 HEARTBEATs", reason="" if f.link_ok else "no HEARTBEAT from PX4"),
        PreflightCheck(name="position", ok=f.have_position, value="LOCAL_POSITION_NED" if f.have_position else "none",
                       expected="a local position estimate",
                       reason="" if f.have_position else "OFFBOARD position control needs a local position estimate"),
        PreflightCheck(name="on_ground", ok=not f.armed and f.landed_state in (LandedState.ON_GROUND,
                                                                              LandedState.UNKNOWN),
                       value=f"{'armed' if f.armed else 'disarmed'}, {f.landed_state.value}",
                       expected="disarmed on the ground",
                       reason="" if not f.armed else "the vehicle is already armed: preflight is for the ground"),
        PreflightCheck(name="battery", ok=battery is None or battery >= min_battery,
                       value="not reported" if battery is None else f"{battery:.0f} %",
                       expected=f">= {min_battery:.0f} % (when reported)",
                       reason="" if battery is None or battery >= min_battery else
                       "too little charge for a task and the landing after it"),
        PreflightCheck(name="authority", ok=not f.override, value=f.override or "ours",
                       expected="no pilot or failsafe in control",
                       reason="" if not f.override else f"control was taken: {f.override}"),
    ]


@dataclass(frozen=True)
class OperatorLimits:
    """What `aermani preflight` requires of the parts the bridge cannot see from the vehicle's link."""

    min_fps: float = 5.0
    max_frame_age_s: float = 0.5
    min_link_hz: float = 10.0
    max_bus_ms: float = 200.0


def check_operator(fps: float | None, frame_age_s: float | None, link_hz: float | None, bus_ms: float | None,
                   lim: OperatorLimits, bus_reached: str = "executor") -> list[PreflightCheck]:
    """Camera frame rate and the newest frame's age, the MAVLink message rate the bridge receives, and the bus
    round trip through the router, measured from the operator's side over a few seconds."""
    camera_ok = (fps is not None and fps >= lim.min_fps and frame_age_s is not None
                 and frame_age_s <= lim.max_frame_age_s)
    return [
        PreflightCheck(
            name="camera", ok=camera_ok,
            value="no frame" if fps is None else f"{fps:.1f} fps, newest frame {frame_age_s:.2f} s old",
            expected=f">= {lim.min_fps:g} fps, frames <= {lim.max_frame_age_s:g} s old",
            reason="" if camera_ok else "perception localizes from the newest frame: a slow, stale or absent camera "
                                        "grasps at where the object was (check the camera's health and cable)"),
        PreflightCheck(
            name="mavlink_rate", ok=link_hz is not None and link_hz >= lim.min_link_hz,
            value="no bridge health" if link_hz is None else f"{link_hz:.0f} messages/s",
            expected=f">= {lim.min_link_hz:g} messages/s",
            reason="" if link_hz is not None and link_hz >= lim.min_link_hz else
            "a thin link delays the pose the skills close their loops on (check the baud rate and PX4's "
            "MAV_x_RATE / stream configuration)"),
        PreflightCheck(
            name="bus_round_trip", ok=bus_ms is not None and bus_ms <= lim.max_bus_ms,
            value="no answer" if bus_ms is None else f"{bus_ms:.0f} ms ({bus_reached})",
            expected=f"<= {lim.max_bus_ms:g} ms to the vehicle's services",
            reason="" if bus_ms is not None and bus_ms <= lim.max_bus_ms else
            "aborts and skill commands cross this link (check the Wi-Fi between ground and drone)"),
    ]


def summary(checks: list[PreflightCheck]) -> str:
    failed = [c for c in checks if not c.ok]
    if not failed:
        notes = "".join(f"; note: {c.name} = {c.value}: {c.reason}" for c in checks if c.reason)
        return f"preflight passed: {len(checks)} checks{notes}"
    return "preflight failed: " + "; ".join(
        f"{c.name} = {c.value or 'not reported'} (needs {c.expected}): {c.reason}" for c in failed)


class ParamReader:
    """Reads PX4 parameters by name over the bridge's MAVLink link: one PARAM_REQUEST_READ per name, answered
    by PARAM_VALUE (delivered to `on_param_value` by the bridge's reader), retried, None when never answered."""

    def __init__(self, send: Callable[[Any], bool], mav: Any) -> None:
        self._send, self._mav = send, mav
        self._waiting: dict[str, list[asyncio.Future[float]]] = {}

    def on_param_value(self, msg: Any) -> None:
        pid = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else msg.param_id.decode().rstrip("\x00")
        for fut in self._waiting.pop(pid, []):
            if not fut.done():
                fut.set_result(float(msg.param_value))

    async def read(self, target: tuple[int, int], names: tuple[str, ...], timeout_s: float = 1.0,
                   attempts: int = 3) -> dict[str, float | None]:
        out: dict[str, float | None] = {}
        for name in names:
            out[name] = None
            for _ in range(attempts):
                fut: asyncio.Future[float] = asyncio.get_running_loop().create_future()
                self._waiting.setdefault(name, []).append(fut)
                self._send(self._mav.param_request_read_encode(target[0], target[1], name.encode(), -1))
                try:
                    out[name] = await asyncio.wait_for(fut, timeout_s)
                    break
                except TimeoutError:
                    continue
                finally:
                    waiting = self._waiting.get(name, [])
                    if fut in waiting:
                        waiting.remove(fut)
        return out
