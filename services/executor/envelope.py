"""The safety envelope: geofence, altitude band, vehicle health and forward clearance from the depth image.

Each check returns None when the rule holds, or a sentence written for the policy to read. The rules are
applied before a skill is accepted (nothing moves on a violation) and, for the vehicle-state rules, on
every state sample while a skill runs (see SkillContext.monitor)."""

from __future__ import annotations

import math
import time

import numpy as np

from services.executor.settings import ExecutorSettings
from shared.envelope import altitude_problem, geofence_problem, outside_geofence, speed_problem
from shared.frames import Mount
from shared.messages import LandedState, VehicleState
from shared.sensors import Intrinsics, backproject

# The geometric rules live in shared/ because the autopilot bridge applies them too.
__all__ = ["DepthClearance", "airborne", "altitude_problem", "geofence_problem", "offboard_problem",
           "outside_geofence", "speed_problem", "state_problem", "wrap"]


def airborne(state: VehicleState | None) -> bool:
    if state is None or not state.armed:
        return False
    return state.landed_state in (LandedState.IN_AIR, LandedState.LANDING) or (
        state.landed_state == LandedState.UNKNOWN and state.position.z > 0.15)


def state_problem(state: VehicleState | None, age_s: float, s: ExecutorSettings) -> str | None:
    """Health rules for anything that moves the vehicle."""
    if state is None:
        return "no vehicle state received yet: the autopilot bridge is not publishing; nothing was moved"
    if age_s > s.state_max_age_s:
        return (f"vehicle state is stale ({age_s:.2f} s old, limit {s.state_max_age_s:.2f} s): cannot fly "
                "safely; nothing was moved")
    if not state.link_ok:
        return "autopilot link is down (no heartbeats): nothing was moved"
    return None


def offboard_problem(state: VehicleState) -> str | None:
    """None when a skill may send setpoints: OFFBOARD is healthy, or PX4 holds the vehicle in the air in
    AUTO.LOITER (its offboard-loss Hold found by a restarted bridge, an abort's hold), which the bridge takes back
    into OFFBOARD for an operator's new command; it refuses the task PX4 took control from. Any other mode is
    PX4's or the pilot's to fly (RTL, a landing, POSCTL)."""
    if state.mode == "AUTO.LOITER" and state.link_ok and state.landed_state is LandedState.IN_AIR:
        return None
    if not state.offboard_ok:
        return (f"autopilot is not in healthy OFFBOARD control (mode {state.mode}): cannot send setpoints; "
                "nothing was moved")
    return None


class DepthClearance:
    """Forward clearance from the latest depth frame: points inside the corridor the airframe would sweep."""

    def __init__(self, intr: Intrinsics, stride: int = 4, mount: Mount | None = None) -> None:
        self.intr = intr
        self.stride = stride
        self.base_from_camera = (mount or Mount()).base_to_camera()
        self.depth: np.ndarray | None = None
        self.stamp_ns = 0
        self.receive_ns = 0

    def update(self, stamp_ns: int, depth_mm: np.ndarray) -> None:
        self.depth = depth_mm
        self.stamp_ns = stamp_ns
        self.receive_ns = time.time_ns()

    @property
    def age_s(self) -> float:
        return float("inf") if not self.receive_ns else (time.time_ns() - self.receive_ns) / 1e9

    def nearest_ahead(self, altitude: float, s: ExecutorSettings, length: float,
                      below: float | None = None) -> tuple[float | None, int]:
        """Nearest forward distance (body x) of an obstacle within `length` in the corridor, and the count of
        corridor points. None when the corridor is free. Points near the floor are ignored: the floor is not
        an obstacle to a level translation."""
        assert self.depth is not None
        d = self.depth[:: self.stride, :: self.stride].astype(np.float64) / 1000.0
        h, w = d.shape
        v, u = np.mgrid[0:h, 0:w]
        u = u * self.stride
        v = v * self.stride
        valid = (d > 0.05) & (d < 60.0)
        if not valid.any():
            return None, 0
        pts = backproject(u[valid].astype(np.float64), v[valid].astype(np.float64), d[valid], self.intr)
        body = pts @ self.base_from_camera[:3, :3].T + self.base_from_camera[:3, 3]
        floor_body_z = -altitude + 0.05
        lower = max(-(s.clearance_below if below is None else below), floor_body_z)
        inside = ((body[:, 0] > 0.0) & (body[:, 0] <= length) & (np.abs(body[:, 1]) <= s.clearance_half_width)
                  & (body[:, 2] >= lower) & (body[:, 2] <= s.clearance_above))
        n = int(inside.sum())
        if n < s.clearance_min_points:
            return None, n
        return float(np.min(body[inside, 0])), n

    def forward_problem(self, altitude: float, step: float, s: ExecutorSettings,
                        below: float | None = None) -> str | None:
        """A forward step's corridor; `below` (m under the body origin) overrides `clearance_below`, e.g. to
        include a held object hanging from the gripper."""
        if self.depth is None or self.age_s > s.depth_max_age_s:
            age = "never received" if self.depth is None else f"{self.age_s:.1f} s old"
            return (f"no fresh depth image ({age}): forward clearance cannot be verified; nothing was moved")
        need = step + s.clearance_margin
        dist, _n = self.nearest_ahead(altitude, s, need, below)
        if dist is not None:
            return (f"obstacle {dist:.2f} m ahead (a forward step of {step:.2f} m needs {need:.2f} m free); "
                    "nothing was moved: yaw, climb or move sideways first")
        return None


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi
