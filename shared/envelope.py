"""The flight envelope (geofence box, altitude band, speed limit) and its checks, shared by the executor
(before a skill moves anything) and the autopilot bridge (on every command, whoever sent it).

Each check returns None when the rule holds, or a sentence saying what was refused and why; callers append
their own consequence. The defaults are the executor's; the bridge reads the executor's variables too
(AERMANI_EXECUTOR_GEOFENCE_MIN ...), so one setting moves both fences."""

from __future__ import annotations

import math
from typing import Protocol

from shared.messages import Vec3

GEOFENCE_MIN = (-3.8, -3.8, 0.0)
GEOFENCE_MAX = (3.8, 3.8, 2.5)
MIN_ALTITUDE = 0.3
MAX_ALTITUDE = 2.4
# The grasp/place descent is the lowest target the executor ever sends (the gripper hangs 0.22 m below).
MANIPULATION_MIN_ALTITUDE = 0.2
MAX_SPEED = 1.0


class Envelope(Protocol):
    """Anything with the envelope's fields (ExecutorSettings, BridgeSettings)."""

    geofence_min: tuple[float, float, float]
    geofence_max: tuple[float, float, float]
    min_altitude: float
    max_altitude: float
    max_speed: float


def check_settings(s: Envelope) -> None:
    """Settings both enforcers accept: a geofence box whose minimum is below its maximum on every axis and an
    altitude band 0 < min < max (a ValueError says which is not, for the settings validators)."""
    if any(lo >= hi for lo, hi in zip(s.geofence_min, s.geofence_max, strict=True)):
        raise ValueError("geofence_min must be below geofence_max on every axis")
    if not 0 < s.min_altitude < s.max_altitude:
        raise ValueError("need 0 < min_altitude < max_altitude")


def geofence_problem(p: Vec3, s: Envelope, what: str = "target") -> str | None:
    lo, hi = s.geofence_min, s.geofence_max
    for axis, v, a, b in (("x", p.x, lo[0], hi[0]), ("y", p.y, lo[1], hi[1]), ("z", p.z, lo[2], hi[2])):
        if not a <= v <= b:
            return (f"{what} ({p.x:.2f}, {p.y:.2f}, {p.z:.2f}) is outside the geofence ({axis} must stay in "
                    f"[{a:.2f}, {b:.2f}]); nothing was moved, choose another direction")
    return None


def altitude_problem(z: float, s: Envelope, low: float | None = None, what: str = "target") -> str | None:
    low = s.min_altitude if low is None else low
    if z < low - 1e-6:
        return (f"{what} altitude {z:.2f} m is below the minimum {low:.2f} m; nothing was moved, "
                "do not descend further")
    if z > s.max_altitude + 1e-6:
        return (f"{what} altitude {z:.2f} m is above the maximum {s.max_altitude:.2f} m; nothing was moved, "
                "do not climb further")
    return None


def speed_problem(speed: float | None, s: Envelope, what: str = "motion") -> str | None:
    if speed is None:
        return None
    if not math.isfinite(speed) or speed <= 0:
        return f"{what} speed {speed} is not a positive number; nothing was moved"
    if speed > s.max_speed + 1e-9:
        return (f"{what} speed {speed:.2f} m/s is above the limit {s.max_speed:.2f} m/s; nothing was moved, "
                "ask for a slower motion")
    return None


def outside_geofence(p: Vec3, s: Envelope, margin: float) -> bool:
    lo, hi = s.geofence_min, s.geofence_max
    return any(v < a - margin or v > b + margin for v, a, b in
               ((p.x, lo[0], hi[0]), (p.y, lo[1], hi[1]), (p.z, lo[2], hi[2])))
