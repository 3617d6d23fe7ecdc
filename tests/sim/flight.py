"""Drive a SimCore's vehicle in-process (no sockets): a wall clock, a 20 Hz setpoint stream, offboard."""

from __future__ import annotations

import math

import numpy as np

from services.sim.core import SimCore
from services.sim.vehicle import ACCEPTED, MAIN_OFFBOARD, TEMPORARILY_REJECTED, enu_to_ned, realism_params
from shared.messages import Scenario

DT = 0.01


def make_core(scenario: Scenario, realism: str = "ideal", dynamics: str | None = "kinematic") -> SimCore:
    """The kinematic body unless asked (its flight is exact, so tests of the modes, the judge, contacts and faults
    are about them, not about a hover's wander); `dynamics` None: the configured one (AERMANI_SIM_DYNAMICS)."""
    return SimCore(scenario, realism_params(realism), realism=realism, dynamics=dynamics)


class Clock:
    def __init__(self, core: SimCore) -> None:
        self.core, self.now = core, 100.0

    def run(self, seconds: float, setpoint=None, record=None, velocity=None) -> None:
        """`setpoint` = (NED position, NED yaw) or None; `velocity` = (NED velocity, NED yaw)."""
        v = self.core.vehicle
        for i in range(int(round(seconds / DT))):
            self.now += DT
            if setpoint is not None and i % 5 == 0:  # a 20 Hz stream
                pos, yaw = setpoint
                v.setpoint(self.now, np.array(pos, float), None, yaw, None)
            if velocity is not None and i % 5 == 0:
                vel, yaw = velocity
                v.setpoint(self.now, None, np.array(vel, float), yaw, None)
            v.update_modes(self.now)
            v.step(DT)
            if record is not None:
                record.append((v.p.copy(), v.v.copy(), v.yaw))

    def fly(self, enu, yaw_enu: float, seconds: float) -> None:
        self.run(seconds, (enu_to_ned(np.asarray(enu, float)), math.pi / 2 - yaw_enu))


def to_offboard(core: SimCore, clock: Clock, alt: float = 1.5, tolerance: float = 0.02) -> None:
    """Arm, switch to offboard and climb to `alt`; the estimate must then be within `tolerance` of it (a realistic
    hover wanders a few centimetres: give it room)."""
    v = core.vehicle
    assert v.arm(True) == ACCEPTED
    sp = ([v.p[0], v.p[1], -alt], v.yaw)
    assert v.set_mode(MAIN_OFFBOARD, 0, clock.now) == TEMPORARILY_REJECTED  # no setpoint yet
    clock.run(0.3, sp)
    assert v.set_mode(MAIN_OFFBOARD, 0, clock.now) == ACCEPTED  # PX4: a setpoint within COM_OF_LOSS_T
    clock.run(5.0, sp)
    assert abs(v.p[2] + alt) < tolerance and not v.on_ground


def grasp(core: SimCore, clock: Clock, name: str, yaw_enu: float, offset=(0.0, 0.0), depth: float = 0.03,
          lift_to: float = 1.6) -> bool:
    """Hover above the object at `yaw_enu`, descend so the gripper point is `depth` below its top (shifted by
    `offset` metres in x, y), close, lift; returns whether the judge says it is held."""
    from shared.messages import JudgeRequest

    obj = core.world.by_name(name)
    core.vehicle.gripper(False)
    x, y = obj.center[0] + offset[0], obj.center[1] + offset[1]
    clock.fly([x, y, obj.top_z + 0.6], yaw_enu, 8.0)
    clock.fly([x, y, obj.top_z - depth + 0.22], yaw_enu, 5.0)
    core.vehicle.gripper(True)
    clock.fly([x, y, obj.top_z - depth + 0.22], yaw_enu, 1.0)
    clock.fly([x, y, lift_to], yaw_enu, 4.0)
    return core.judge(JudgeRequest(op="held")).ok


def approach_point(core: SimCore, name: str, z: float) -> tuple[np.ndarray, np.ndarray, object]:
    """A point 1 m in front of the furniture's side facing the room centre, and the direction into it."""
    f = core.world.by_name(name)
    c = f.center
    d = -c[:2] / np.linalg.norm(c[:2])  # from the furniture towards the room centre
    t = min(f.size[0] / 2 / max(abs(d[0]), 1e-9), f.size[1] / 2 / max(abs(d[1]), 1e-9))
    start = np.array([c[0] + d[0] * (t + 1.0), c[1] + d[1] * (t + 1.0), z])
    return start, -d, f
