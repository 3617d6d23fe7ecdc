"""The gripper on real MuJoCo physics, like a small real one: fingers coupled by one servo, closing at its speed,
squeezing with its force limit, rubber pads whose own friction rules their contacts (priority), pads and arms
colliding with objects, furniture and the floor. Simulated time only."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from services.sim.physics import (
    CLOSING_SPEED,
    FINGER_KP,
    FINGER_MAX_HALF,
    FINGER_MAX_OPENING,
    GRIP_FORCE,
    PAD_FRICTION,
)
from shared.messages import JudgeRequest, Pose, Scenario, Vec3
from tests.sim.flight import DT, Clock, grasp, make_core, to_offboard

START = Pose(position=Vec3(x=0.0, y=0.0), yaw=0.0)


def _core(target: str = "red cup", seed: int = 2):
    # Seed 2: the red cup on the counter, the table (1.2 x 0.8 m at (2.6, -2.75)) empty; seed 1: the green bottle.
    return make_core(Scenario(seed=seed, target_object=target, distractors=(), start=START))


def _pad_contacts(w, geom: int) -> list[int]:
    """Indices of the contacts between a finger pad and `geom`."""
    out = []
    for i in range(w.data.ncon):
        c = w.data.contact[i]
        if geom in (c.geom1, c.geom2) and (c.geom1 in w.finger_geoms or c.geom2 in w.finger_geoms):
            out.append(i)
    return out


def test_fingers_are_coupled_and_close_at_the_servo_speed():
    core = _core()
    clock = Clock(core)
    to_offboard(core, clock)
    w, v = core.world, core.vehicle
    jl, jr = w._jnt["finger_left"], w._jnt["finger_right"]
    hover = ([0.0, 0.0, -1.5], v.yaw)
    v.gripper(True)  # closing on nothing, in the air
    widths, skew = [], 0.0
    for _ in range(150):
        clock.run(DT, hover)
        widths.append(w.finger_width())
        skew = max(skew, abs(float(w.data.qpos[jl] - w.data.qpos[jr])))
    assert skew < 1e-3  # one servo, one linkage: both fingers travel together
    half = next(i for i, x in enumerate(widths) if x < FINGER_MAX_OPENING / 2) * DT
    assert half == pytest.approx(FINGER_MAX_OPENING / 2 / CLOSING_SPEED, abs=0.05)  # 0.6 s to half closed
    assert widths[int(0.3 / DT)] > FINGER_MAX_OPENING - 0.3 * CLOSING_SPEED - 0.015  # never faster than the servo
    assert widths[-1] < 0.01
    v.gripper(False)
    clock.run(0.6, hover)
    assert w.finger_width() == pytest.approx(0.6 * CLOSING_SPEED, abs=0.02)  # opening at the same speed
    clock.run(0.9, hover)
    assert w.data.qpos[jl] > FINGER_MAX_HALF - 0.005 and w.data.qpos[jr] > FINGER_MAX_HALF - 0.005


@pytest.mark.parametrize("priority", [True, False])
def test_each_pad_squeezes_with_the_servo_force_and_its_own_friction(priority):
    core = _core()
    w = core.world
    cup_geom = w.model.geom("e" + str(w.by_name("red cup").id)).id
    w.model.geom_friction[cup_geom, 0] = 1.5  # a cup grippier than rubber: the pads' coefficient still rules
    if not priority:
        for g in w.finger_geoms:
            w.model.geom_priority[g] = 0  # the negative case: MuJoCo then takes the larger coefficient
    clock = Clock(core)
    to_offboard(core, clock)
    assert grasp(core, clock, "red cup", 0.0)
    normal = dict.fromkeys(w.finger_geoms, 0.0)
    force = np.zeros(6)
    contacts = _pad_contacts(w, cup_geom)
    assert contacts
    for i in contacts:
        c = w.data.contact[i]
        assert c.friction[0] == pytest.approx(PAD_FRICTION if priority else 1.5)
        mujoco.mj_contactForce(w.model, w.data, i, force)
        normal[c.geom1 if c.geom1 in w.finger_geoms else c.geom2] += force[0]
    for n in normal.values():  # each pad squeezes with the servo's force limit, no more
        assert 0.8 * GRIP_FORCE < n < 1.1 * GRIP_FORCE, normal


@pytest.mark.parametrize(("pad_friction", "held"), [(PAD_FRICTION, True), (0.3, False)])
def test_the_heaviest_object_is_lifted_by_friction_alone(pad_friction, held):
    """0.55 kg at up to 2 m/s^2 upwards needs 4.1 N per pad at mu 0.8: 7 N holds it. At mu 0.3 the pads' 2 x 0.3 x
    7 N = 4.2 N is less than its 5.4 N weight: it slips out (the grip's strength is what holds it)."""
    core = _core("green bottle", seed=1)
    for g in core.world.finger_geoms:
        core.world.model.geom_friction[g, 0] = pad_friction
    clock = Clock(core)
    to_offboard(core, clock)
    bottle = core.world.by_name("green bottle")
    ok = grasp(core, clock, "green bottle", 0.0)
    assert ok is held
    assert bool(bottle.center[2] > 1.1) is held
    assert core.judge(JudgeRequest(op="held")).ok is held


def test_pads_and_arms_collide_with_the_floor_furniture_and_objects():
    core = _core()
    w = core.world
    pad_bottom = w.data.geom_xpos[w.finger_geoms[0]][2] - 0.03

    def contacts_at(z: float, x: float = 0.0, y: float = 0.0) -> set[tuple[str, str]]:
        w.set_vehicle(np.array([x, y, z]), 0.0)
        mujoco.mj_forward(w.model, w.data)
        names = set()
        for i in range(w.data.ncon):
            c = w.data.contact[i]
            a, b = w.model.geom(c.geom1).name, w.model.geom(c.geom2).name
            names.add((a, b) if a < b else (b, a))
        return names

    # Landed on the gear: the pads hang 5 mm above the floor, touching nothing.
    assert pad_bottom - w.by_name("floor").top_z == pytest.approx(0.005, abs=1e-3)
    assert not any("finger" in a or "finger" in b for a, b in contacts_at(0.0))
    # 1 cm lower (the gear pressed into the floor), the pads meet it.
    low = contacts_at(-0.01)
    assert ("e" + str(w.by_name("floor").id), "finger_left") in low
    # An arm against the table's edge, a pad against the cup's side.
    table, cup = w.by_name("table"), w.by_name("red cup")
    edge_y = table.center[1] + table.size[1] / 2
    hits = contacts_at(table.top_z + 0.10, table.center[0], edge_y + 0.098)  # the right arm 2 mm into its side
    assert ("e" + str(table.id), "finger_right_arm") in hits
    hits = contacts_at(cup.center[2] + 0.215, cup.center[0], cup.center[1] + cup.size[0] / 2 + 0.100)
    assert ("e" + str(cup.id), "finger_right") in hits


def test_a_held_object_is_let_go_at_once_and_the_telemetry_follows():
    """Stopped by the cup, the servo stalls at its force limit instead of winding its target on to zero: an open
    command takes the pads off the cup within 0.2 s. The gripper's own sensing (width, both pads in contact, the
    command) is what DEBUG_VECT "GRIPPER" reports."""
    core = _core()
    clock = Clock(core)
    to_offboard(core, clock)
    w, v = core.world, core.vehicle
    assert grasp(core, clock, "red cup", 0.0)
    clock.run(2.0, (v.p.copy(), v.yaw))  # held for 2 s more: a runaway target would be 30 cm past the cup by now
    assert v.holding and v.gripper_closed and v.finger_width == pytest.approx(0.08, abs=0.005)
    assert float(w.data.ctrl[w._grip_act]) > 0.08 - 2 * GRIP_FORCE / FINGER_KP - 0.002
    v.gripper(False)
    released = None
    for i in range(100):
        clock.run(DT, (v.p.copy(), v.yaw))
        if not v.holding:
            released = (i + 1) * DT
            break
    assert released is not None and released <= 0.2, released
    assert not v.gripper_closed
