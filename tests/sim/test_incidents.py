"""Incidents the simulator records besides the airframe's contacts, on real MuJoCo states: a gripper strike (a pad or
arm against furniture or an object other than the task's target), an object knocked (tipped or moved off what it
stood on while not in the pads) and an object dropped (it left the pads after a lift and fell). Each with a case that
must not be recorded. Simulated time only."""

from __future__ import annotations

import numpy as np
import pytest

from services.sim.physics import DROP_FALL, TIMESTEP
from shared.messages import JudgeRequest, Pose, Scenario, Vec3
from tests.sim.flight import Clock, grasp, make_core, to_offboard

START = Pose(position=Vec3(x=0.0, y=0.0), yaw=0.0)
# Seed 2: the red cup (target) on the counter, the soda can on the round table, the orange on the table.
SCENARIO = Scenario(seed=2, target_object="red cup", distractors=("soda can", "orange"), start=START)


def _flying():
    core = make_core(SCENARIO)
    clock = Clock(core)
    to_offboard(core, clock)
    return core, clock


def _kinds(core) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for i in core.judge(JudgeRequest()).incidents:
        out.setdefault(i.kind, []).append(i.thing)
    return out


def _texts(core) -> list[str]:
    return [t for _, t in core.vehicle.events]


def test_grasping_the_target_and_placing_it_records_nothing():
    core, clock = _flying()
    assert grasp(core, clock, "red cup", 0.0)
    table = core.world.by_name("table")
    cup = core.world.by_name("red cup")
    # Over the table (away from the orange), released 2 cm above its top: a placement, not a drop.
    x, y = float(table.center[0]) - 0.3, float(table.center[1])
    clock.fly([x, y, 1.6], 0.0, 10.0)
    release_z = table.top_z + cup.size[2] + 0.02 - 0.03 + 0.22
    clock.fly([x, y, release_z], 0.0, 6.0)
    core.vehicle.gripper(False)
    clock.fly([x, y, release_z], 0.0, 3.0)
    clock.fly([x, y, 1.6], 0.0, 4.0)
    assert core.judge(JudgeRequest(op="on_surface", object="red cup", surface="table")).ok
    res = core.judge(JudgeRequest())
    assert res.collisions == () and res.incidents == ()


def test_a_pad_coming_down_on_another_object_is_a_gripper_strike():
    core, clock = _flying()
    can = core.world.by_name("soda can")
    cx, cy = float(can.center[0]), float(can.center[1])
    # The right pad (9.6 cm to the vehicle's right, yaw 0) right above the can, the gripper point 2 cm into its top.
    clock.fly([cx, cy + 0.096, can.top_z + 0.4], 0.0, 10.0)
    assert "gripper" not in _kinds(core)
    clock.fly([cx, cy + 0.096, can.top_z - 0.02 + 0.22], 0.0, 3.0)
    res = core.judge(JudgeRequest())
    strike = next(i for i in res.incidents if i.kind == "gripper")
    assert strike.thing == "soda can" and "gripper-soda can" in res.collisions
    assert 10.0 < strike.t_s < core.world.sim_time  # simulated time since the reset
    assert "vehicle" not in _kinds(core)  # the pad, not the airframe
    assert any(t.startswith("Gripper struck the soda can") for t in _texts(core))


@pytest.mark.parametrize(("depth", "struck"), [(0.003, False), (0.015, True)])
def test_pads_pressed_into_a_table_top_strike_it(depth, struck):
    """The feet reach 5 mm below the pads: the vehicle put down with its feet `depth` into the table's top touches
    it with its pads only when the depth exceeds 5 mm."""
    core = make_core(SCENARIO)
    w = core.world
    table = w.by_name("table")
    feet_below = -w.by_name("floor").top_z  # the body origin stands this high above what its feet are on
    w.set_vehicle(np.array([table.center[0] - 0.3, table.center[1], table.top_z + feet_below - depth]), 0.0)
    w.step(TIMESTEP)  # one physics step: the contact as put down
    assert ("gripper-table" in w.collisions) is struck


def test_a_cup_swept_over_by_an_open_finger_is_knocked_and_a_lifted_one_is_not():
    core, clock = _flying()
    cup = core.world.by_name("red cup")
    x, y = float(cup.center[0]), float(cup.center[1])
    z = cup.top_z - 0.03 + 0.22
    # Fingers open, the vehicle's y axis along the sweep: the right pad passes through the cup's upper half.
    clock.fly([x, y + 0.25, 1.6], 0.0, 10.0)
    clock.fly([x, y + 0.25, z], 0.0, 5.0)
    assert "knocked" not in _kinds(core)
    clock.fly([x, y - 0.3, z], 0.0, 4.0)
    clock.fly([x, y - 0.3, 1.6], 0.0, 3.0)
    knocked = next(i for i in core.judge(JudgeRequest()).incidents if i.kind == "knocked")
    assert knocked.thing == "red cup" and ("tipped" in knocked.detail or "moved" in knocked.detail), knocked
    assert "gripper" not in _kinds(core)  # the target: touching it is no strike
    assert any(t.startswith("Knocked over the red cup") for t in _texts(core))


@pytest.mark.parametrize(("push_s", "knocked"), [(0.1, False), (0.4, True)])
def test_a_box_pushed_off_its_table_is_knocked_and_one_nudged_along_it_is_not(push_s, knocked):
    """The tissue box (0.15 kg, on the table 0.24 m from its -y edge) pushed towards that edge with 2 N at its base
    (no tipping moment): friction (0.7 x 0.15 kg x g = 1.0 N) stops it about 6 cm on after 0.1 s, 1 m on (over the
    edge, onto the floor) after 0.4 s."""
    core = make_core(Scenario(seed=2, target_object="red cup", distractors=("soda can", "orange", "tissue box"),
                              start=START))
    w = core.world
    box = w.by_name("tissue box")
    assert box.support == "table"
    b = w.obj_body["tissue box"]
    force = np.array([0.0, -2.0, 0.0])
    w.data.xfrc_applied[b, :3] = force
    w.data.xfrc_applied[b, 3:] = np.cross([0.0, 0.0, -box.size[2] / 2], force)  # applied at the base
    clock = Clock(core)
    clock.run(push_s)
    w.data.xfrc_applied[b] = 0.0
    clock.run(4.0)
    assert (box.support == "table") is not knocked, box.support
    assert ("knocked-tissue box" in w.collisions) is knocked


def test_a_cup_let_go_over_the_open_floor_is_dropped():
    core, clock = _flying()
    assert grasp(core, clock, "red cup", 0.0)
    clock.fly([0.0, 0.0, 1.2], 0.0, 10.0)
    assert "dropped" not in _kinds(core)
    core.vehicle.gripper(False)
    clock.fly([0.0, 0.0, 1.2], 0.0, 4.0)
    dropped = next(i for i in core.judge(JudgeRequest()).incidents if i.kind == "dropped")
    assert dropped.thing == "red cup" and "fell" in dropped.detail
    assert float(dropped.detail.split()[1]) > DROP_FALL
    assert "knocked" not in _kinds(core)  # a lifted object that falls was dropped, not knocked
    assert any(t.startswith("Dropped the red cup") for t in _texts(core))


def test_a_cup_slipping_out_of_the_pads_in_flight_is_dropped():
    core, clock = _flying()
    cup = core.world.by_name("red cup")
    x, y = float(cup.center[0]), float(cup.center[1])
    assert grasp(core, clock, "red cup", 0.0)
    assert core.world.slip("red cup")  # the grasp gives way (fault injection): it falls back onto the counter
    clock.fly([x, y, 1.6], 0.0, 4.0)
    assert cup.support == "counter"
    assert _kinds(core).get("dropped") == ["red cup"]
