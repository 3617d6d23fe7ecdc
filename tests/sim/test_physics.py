"""Contact physics of the MuJoCo world: grasps hold only by friction between aligned fingers, released objects
fall off edges, flying into furniture is a recorded collision."""

from __future__ import annotations

import math

import numpy as np

from shared.messages import JudgeRequest, Pose, Scenario, Vec3
from tests.sim.flight import Clock, approach_point, grasp, make_core, to_offboard

START = Pose(position=Vec3(x=0.0, y=0.0), yaw=0.0)


def _flying(scenario: Scenario):
    core = make_core(scenario)
    clock = Clock(core)
    to_offboard(core, clock)
    return core, clock


def test_box_grasped_45_degrees_off_its_axis_is_not_held_while_aligned_holds():
    scen = Scenario(seed=1, target_object="tissue box", distractors=(), start=START)
    # Aligned: the fingers close across the 12 cm side.
    core, clock = _flying(scen)
    box = core.world.by_name("tissue box")
    assert grasp(core, clock, "tissue box", box.yaw)
    assert abs(core.vehicle.finger_width - box.size[1]) < 0.01
    assert box.center[2] > 1.2  # lifted with the vehicle
    # 45 degrees off: the box's extent across the fingers (25 cm) exceeds their opening (18 cm); the pads come
    # down on its lid, close on nothing, and it stays on the table.
    core, clock = _flying(scen)
    box = core.world.by_name("tissue box")
    home = box.support
    assert not grasp(core, clock, "tissue box", box.yaw + math.pi / 4)
    assert core.world.holding() is None
    assert box.center[2] < 1.0 and box.support == home


def test_object_released_half_over_an_edge_falls_and_one_released_inside_stays():
    scen = Scenario(seed=2, target_object="red cup", start=START)
    for inside, stays in ((-0.01, False), (0.08, True)):
        core, clock = _flying(scen)
        cup = core.world.by_name("red cup")
        assert grasp(core, clock, "red cup", 0.0)
        dest = next(s for s in core.world.surfaces if s.name != cup.support and s.shape == "box")
        # Centre `inside` metres inside the destination's +x edge (negative: past it, over the air).
        x = dest.center[0] + dest.size[0] / 2 - inside
        y = float(dest.center[1])
        z = dest.top_z + cup.size[2] + 0.02 - 0.03 + 0.22
        clock.fly([x, y, 1.6], 0.0, 12.0)
        clock.fly([x, y, z], 0.0, 5.0)
        core.vehicle.gripper(False)
        clock.fly([x, y, z], 0.0, 0.5)
        clock.fly([x, y, 1.6], 0.0, 3.0)
        on = core.judge(JudgeRequest(op="on_surface", object="red cup", surface=dest.name))
        assert on.ok == stays, on.message
        if not stays:
            assert cup.center[2] < dest.top_z  # fell off: below the top, on the floor or against the side


def test_flying_into_the_shelf_is_a_recorded_collision():
    core, clock = _flying(Scenario(seed=5, start=START))
    v = core.vehicle
    start, into, shelf = approach_point(core, "shelf", 0.5)
    clock.fly([0.0, 0.0, 0.5], 0.0, 3.0)
    clock.fly(start, 0.0, 8.0)
    assert core.world.collisions == []
    clock.fly([shelf.center[0], shelf.center[1], 0.5], 0.0, 6.0)
    res = core.judge(JudgeRequest())
    assert "vehicle-shelf" in res.collisions
    contact = next(c for c in core.world.contacts if c.name == "shelf")
    assert contact.crash and v.crashed and not v.armed  # at cruise speed: a crash, motors off
    p = v.true_position_enu()
    assert not shelf.contains_xy(p[0], p[1], -0.2)  # the airframe did not pass through it
    assert np.isfinite(p).all()
