"""Point-mass dynamics, mode logic, failsafes, collisions, gripper physics and the judge, without sockets."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mav

from services.sim.core import SimCore
from services.sim.vehicle import (
    ACCEPTED,
    MAIN_AUTO,
    MAIN_OFFBOARD,
    SUB_LAND,
    SUB_LOITER,
    TEMPORARILY_REJECTED,
    enu_to_ned,
)
from shared.messages import JudgeRequest, Pose, Scenario, Vec3

DT = 0.01


class Clock:
    def __init__(self, core: SimCore) -> None:
        self.core, self.now = core, 100.0

    def run(self, seconds: float, setpoint=None, record=None) -> None:
        v = self.core.vehicle
        for i in range(int(round(seconds / DT))):
            self.now += DT
            if setpoint is not None and i % 5 == 0:  # a 20 Hz stream
                pos, yaw = setpoint
                v.setpoint(self.now, np.array(pos, float), None, yaw, None)
            v.update_modes(self.now)
            v.step(DT)
            if record is not None:
                record.append((v.p.copy(), v.v.copy(), v.yaw))


@pytest.fixture
def core():
    return SimCore(Scenario(seed=2, target_object="red cup", start=Pose(position=Vec3(x=0.0, y=0.0), yaw=0.0)))


def to_offboard(core: SimCore, clock: Clock, alt: float = 1.5) -> None:
    v = core.vehicle
    assert v.arm(True) == ACCEPTED
    sp = ([0.0, 0.0, -alt], math.pi / 2)
    assert v.set_mode(MAIN_OFFBOARD, 0, clock.now) == TEMPORARILY_REJECTED  # no setpoint yet
    clock.run(0.3, sp)
    assert v.set_mode(MAIN_OFFBOARD, 0, clock.now) == ACCEPTED  # PX4: a setpoint within COM_OF_LOSS_T
    clock.run(5.0, sp)
    assert abs(v.p[2] + alt) < 0.02 and not v.on_ground


def test_limits_and_convergence(core):
    clock, v = Clock(core), core.vehicle
    assert v.landed_state == mav.MAV_LANDED_STATE_ON_GROUND
    to_offboard(core, clock)
    trace: list = []
    goal = np.array([1.5, -1.0, -1.2])  # NED, inside the start clearing
    clock.run(8.0, (goal, math.pi / 2 + math.pi / 2), trace)
    pos = np.array([t[0] for t in trace])
    vel = np.array([t[1] for t in trace])
    yaw = np.array([t[2] for t in trace])
    assert np.linalg.norm(vel[:, :2], axis=1).max() <= 2.0 + 1e-9
    assert np.abs(vel[:, 2]).max() <= 1.0 + 1e-9
    acc = np.diff(vel[:, :2], axis=0) / DT
    assert np.linalg.norm(acc, axis=1).max() <= 3.0 + 1e-6
    yaw_rate = np.abs(np.diff(np.unwrap(yaw))) / DT
    assert yaw_rate.max() <= math.radians(90) + 1e-6
    assert np.linalg.norm(pos[-1] - goal) < 0.02
    overshoot = (pos[:, 0] - goal[0]).max()
    assert overshoot < 0.05
    assert abs(yaw[-1] - math.pi) < 0.01 or abs(yaw[-1] + math.pi) < 0.01


def test_arming_rules_and_offboard_failsafe(core):
    clock, v = Clock(core), core.vehicle
    assert v.arm(False) == ACCEPTED  # already disarmed
    to_offboard(core, clock)
    assert v.arm(True) == ACCEPTED
    assert v.arm(False) == TEMPORARILY_REJECTED  # in the air (PX4: "Disarming denied: not landed")
    assert v.takeoff(2.0) == ACCEPTED and v.set_mode(MAIN_OFFBOARD, 0, clock.now) in (ACCEPTED,
                                                                                        TEMPORARILY_REJECTED)
    clock.run(0.4)  # stream stops
    clock.run(0.3)
    assert (v.main_mode, v.sub_mode) == (MAIN_AUTO, SUB_LOITER)
    assert any("offboard" in t.lower() for _, t in v.events)
    hold = v.p.copy()
    clock.run(2.5)
    assert np.linalg.norm(v.p - hold) < 0.3 and not v.on_ground
    clock.run(1.0)
    assert (v.main_mode, v.sub_mode) == (MAIN_AUTO, SUB_LAND)
    clock.run(6.0)
    assert v.on_ground and v.landed_state == mav.MAV_LANDED_STATE_ON_GROUND
    assert not v.armed  # auto-disarm after landing
    assert v.arm(True) == ACCEPTED
    assert v.arm(False, force=True) == ACCEPTED


def test_collision_stops_and_is_reported(core):
    clock, v = Clock(core), core.vehicle
    to_offboard(core, clock, alt=0.5)  # below table height
    table = core.world.by_name("table")
    goal_enu = np.array([table.center[0], table.center[1], 0.5])
    clock.run(12.0, (enu_to_ned(goal_enu), math.pi / 2))
    assert "vehicle-table" in core.judge(JudgeRequest()).collisions
    assert core.world.vehicle_contacts(v.position_enu()) == []  # stopped at contact, not inside
    assert np.linalg.norm(v.position_enu()[:2] - goal_enu[:2]) > 0.25
    # Above the table there is no contact: climbing and flying over works.
    clock.run(4.0, (v.p + np.array([0, 0, -1.0]), math.pi / 2))
    clock.run(8.0, (enu_to_ned(np.array([table.center[0], table.center[1], 1.5])), math.pi / 2))
    assert np.linalg.norm(v.position_enu()[:2] - goal_enu[:2]) < 0.05


def test_gripper_capture_carry_release_and_judge(core):
    clock, v = Clock(core), core.vehicle
    to_offboard(core, clock)
    cup = core.world.by_name("red cup")
    home_support = cup.support
    above = np.array([cup.center[0], cup.center[1], 2.0])
    clock.run(10.0, (enu_to_ned(above), math.pi / 2))
    # Gripper 10 cm off the axis: nothing is captured.
    off = np.array([cup.center[0] + 0.10, cup.center[1], cup.top_z + 0.02 + 0.22])
    clock.run(6.0, (enu_to_ned(off), math.pi / 2))
    v.gripper(True)
    assert core.world.attached() is None and not core.judge(JudgeRequest(op="held")).ok
    v.gripper(False)
    on = np.array([cup.center[0], cup.center[1], cup.top_z + 0.02 + 0.22])
    clock.run(4.0, (enu_to_ned(on), math.pi / 2))
    v.gripper(True)
    held = core.judge(JudgeRequest(op="held"))
    assert held.ok and held.held == "red cup"
    assert not core.judge(JudgeRequest(op="on_surface", object="red cup", surface=home_support)).ok
    # It moves with the vehicle.
    dest = next(s for s in core.world.surfaces if s.name != home_support)
    clock.run(12.0, (enu_to_ned(np.array([dest.center[0], dest.center[1], 1.6])), math.pi / 2))
    assert np.linalg.norm(cup.center[:2] - dest.center[:2]) < 0.03
    assert abs(cup.top_z - (v.gripper_enu()[2])) < 1e-9
    v.gripper(False)
    res = core.judge(JudgeRequest(op="on_surface", object="red cup", surface=dest.name))
    assert res.ok, res.message
    assert not core.judge(JudgeRequest(op="on_surface", object="red cup", surface=home_support)).ok
    truth = {o.name: o for o in core.judge(JudgeRequest()).objects}
    assert truth["red cup"].support == dest.name and not truth["red cup"].attached
    # A tighter tolerance than the gap fails; a lifted object is not "on" anything.
    cup.center[2] += 0.1
    assert not core.judge(JudgeRequest(op="on_surface", object="red cup", surface=dest.name)).ok
    # Dropped over open floor, an object lands on the floor.
    cup.center[2] -= 0.1
    clock.run(8.0, (enu_to_ned(np.array([cup.center[0], cup.center[1], cup.top_z + 0.24])), 0.0))
    v.gripper(True)
    assert core.world.attached() is cup
    clock.run(10.0, (enu_to_ned(np.array([0.0, 0.0, 1.0])), 0.0))
    v.gripper(False)
    assert cup.support == "floor" and abs(cup.bottom_z - core.world.support_below(0, 0, 5)[1]) < 1e-9
    assert core.judge(JudgeRequest(op="on_surface", object="red cup", surface="floor")).ok


def test_reset_restores_everything(core):
    clock, v = Clock(core), core.vehicle
    to_offboard(core, clock)
    core.world.record_collision("wall")
    res = core.reset(Scenario(seed=9, target_object="apple"))
    assert res.ok and res.scenario.target_object == "apple"
    v = core.vehicle
    assert not v.armed and v.on_ground and not v.gripper_closed and v.p[2] == 0.0
    assert core.judge(JudgeRequest()).collisions == ()
    assert core.world.by_name("apple") is not None
    assert not core.reset(Scenario(destination="moon")).ok
    assert core.scenario.target_object == "apple"  # a failed reset leaves the world alone


def test_px4_arming_checks_rtl_and_estimate_failsafe(core):
    clock, v = Clock(core), core.vehicle
    v.set_estimate_valid(False)
    assert v.arm(True) == TEMPORARILY_REJECTED and not v.armed
    assert v.events[-1][1] == "Preflight Fail: No valid local position estimate"
    assert v.arm(True, force=True) == ACCEPTED and v.arm(False) == ACCEPTED
    v.set_estimate_valid(True)
    v.battery = 3.0
    assert v.arm(True) == TEMPORARILY_REJECTED and "battery" in v.events[-1][1]
    v.battery = 80.0
    assert v.rtl() == TEMPORARILY_REJECTED  # nothing to return from on the ground
    # RTL from a point away from home: climbs to RTL_RETURN_ALT, flies home, lands there; the disarm after it
    # leaves the vehicle in Hold, where it can arm again.
    to_offboard(core, clock, alt=1.0)
    clock.run(6.0, ([2.0, 1.0, -1.0], 0.0))
    assert np.linalg.norm(v.p[:2] - [2.0, 1.0]) < 0.05
    assert v.rtl() == ACCEPTED and v.mode_name == "AUTO.RTL"
    clock.run(3.0)
    assert v.p[2] < -1.9 and v.mode_name == "AUTO.RTL"  # climbed before going home
    clock.run(20.0)
    assert v.on_ground and np.linalg.norm(v.p[:2] - v.home[:2]) < 0.15 and not v.armed
    assert v.mode_name == "AUTO.LOITER" and v.arm(True) == ACCEPTED
    # Losing the estimate in the air lands at once (PX4's failsafe for modes that need a position).
    to_offboard(core, clock, alt=1.0)
    v.set_estimate_valid(False)
    assert v.mode_name == "AUTO.LAND" and "Failsafe" in v.events[-1][1]
    assert v.set_mode(MAIN_OFFBOARD, 0, clock.now) == TEMPORARILY_REJECTED


def test_battery_failsafe_takes_over_offboard_but_offboard_stays_possible(core):
    clock, v = Clock(core), core.vehicle
    to_offboard(core, clock, alt=1.0)
    v.battery_failsafe()
    assert v.mode_name == "AUTO.RTL" and "critical battery" in v.events[-1][1]
    # PX4 would let a stack switch back (a setpoint stream is there): not re-entering is the stack's duty.
    clock.run(0.2, ([0.0, 0.0, -1.0], 0.0))
    assert v.set_mode(MAIN_OFFBOARD, 0, clock.now) == ACCEPTED
