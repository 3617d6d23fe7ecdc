"""The simulator's injected errors for closed-loop skill tests (sim/fault hover, estimate, object knock), in-process
with the real physics: each does what the fault-injection tests rely on."""

from __future__ import annotations

import math

import numpy as np

from services.sim.vehicle import enu_to_ned
from shared.messages import JudgeRequest, Pose, Scenario, Vec3
from tests.sim.flight import Clock, make_core, to_offboard


def _core():
    return make_core(Scenario(seed=2, target_object="red cup", start=Pose(position=Vec3(x=0.0, y=0.0), yaw=0.0)))


def test_hover_offset_settles_the_vehicle_off_its_setpoint_and_its_estimate_shows_it():
    core = _core()
    clock, v = Clock(core), core.vehicle
    to_offboard(core, clock)
    v.params.hover_offset = (0.04, -0.03)
    goal = np.array([0.5, 0.3, 1.5])
    clock.fly(goal, 0.0, 6.0)
    truth = v.true_position_enu()
    assert np.linalg.norm(truth[:2] - (goal[:2] + [0.04, -0.03])) < 0.005, truth
    assert np.linalg.norm(v.position_enu() - truth) < 1e-6  # ideal estimate: it sees where it is


def test_estimate_offset_moves_the_vehicle_by_the_opposite_unseen():
    core = _core()
    clock, v = Clock(core), core.vehicle
    to_offboard(core, clock)
    goal = np.array([0.5, 0.3, 1.5])
    clock.fly(goal, 0.0, 5.0)
    v.params.estimate_offset = (0.3, 0.0, 0.0)
    clock.fly(goal, 0.0, 5.0)
    assert np.linalg.norm(v.position_enu()[:2] - goal[:2]) < 0.01  # the estimate says: on the setpoint
    assert np.linalg.norm(v.true_position_enu()[:2] - (goal[:2] - [0.3, 0.0])) < 0.01  # truly 0.3 m off
    assert np.allclose(enu_to_ned(np.array([0.3, 0.0, 0.0])), [0.0, 0.3, 0.0])


def test_a_knocked_object_lies_on_its_side_and_the_judge_says_it_is_not_upright():
    core = _core()
    w = core.world
    cup = w.by_name("red cup")
    support = cup.support
    assert core.judge(JudgeRequest(op="on_surface", object="red cup", surface=support)).ok
    assert w.knock_over("red cup")
    w.settle(1.0)
    cup = w.by_name("red cup")
    assert cup.tilt > math.radians(60), math.degrees(cup.tilt)
    assert not core.judge(JudgeRequest(op="on_surface", object="red cup", surface=support)).ok
    assert not w.knock_over("no such thing")


def test_a_knocked_box_lies_on_its_long_side_where_it_stood_whatever_its_yaw():
    # seed 8: the tissue box (24 x 12 x 10 cm) stands on the counter yawed 0.4 rad. Turned about the world x axis
    # it stood up partly on its long side, sank into the counter and was thrown through the floor.
    w = make_core(Scenario(seed=8, target_object="tissue box", destination="table")).world
    box = w.by_name("tissue box")
    where, top = box.center.copy(), w.by_name(box.support).top_z
    assert abs(box.yaw) > 0.3
    assert w.knock_over("tissue box")
    w.settle(1.0)
    box = w.by_name("tissue box")
    assert box.tilt > math.radians(80), math.degrees(box.tilt)
    assert np.linalg.norm(box.center[:2] - where[:2]) < 0.03, (box.center, where)
    assert abs(box.center[2] - (top + box.size[1] / 2)) < 0.01  # on its 24 x 10 cm side: 12 cm tall
