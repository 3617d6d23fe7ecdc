"""World generation: seeded layouts that respect spacing, support and visibility rules."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from services.sim.layout import OBJECTS, ROOM_HALF, SURFACES
from services.sim.render import Renderer, preview, snapshot_at
from services.sim.scenarios import (
    EDGE_MARGIN,
    FURNITURE_GAP,
    START_CLEAR,
    ScenarioError,
    generate,
)
from shared.messages import Pose, Scenario, Vec3

SEEDS = range(25)


@pytest.mark.parametrize("seed", SEEDS)
def test_layout_rules(seed):
    world, scen, start = generate(Scenario(seed=seed))
    assert scen.target_object in OBJECTS and scen.destination in SURFACES
    objs = world.objects
    names = [o.name for o in objs]
    assert scen.target_object in names and set(scen.distractors) <= set(names)
    target = world.by_name(scen.target_object)
    assert target.support != scen.destination
    for o in objs:
        surf = world.by_name(o.support)
        assert surf.category == "surface"
        assert abs(o.bottom_z - surf.top_z) < 0.002  # settled by the physics (contact penetration)
        assert o.tilt < 0.01
        assert surf.contains_xy(o.center[0], o.center[1], EDGE_MARGIN - 1e-9)
    for i, a in enumerate(objs):
        for b in objs[i + 1:]:
            gap = math.hypot(a.center[0] - b.center[0], a.center[1] - b.center[1])
            assert gap >= a.footprint_radius() + b.footprint_radius(), (a.name, b.name)
    furniture = world.obstacles
    for f in furniture:
        assert f.top_z <= 1.1
        assert abs(f.center[0]) + f.size[0] / 2 <= ROOM_HALF - FURNITURE_GAP + 1e-9
        assert abs(f.center[1]) + f.size[1] / 2 <= ROOM_HALF - FURNITURE_GAP + 1e-9
        qx = max(abs(start.position.x - f.center[0]) - f.size[0] / 2, 0)
        qy = max(abs(start.position.y - f.center[1]) - f.size[1] / 2, 0)
        assert math.hypot(qx, qy) >= START_CLEAR
    for i, a in enumerate(furniture):
        for b in furniture[i + 1:]:
            assert (abs(a.center[0] - b.center[0]) >= (a.size[0] + b.size[0]) / 2 + FURNITURE_GAP - 1e-9
                    or abs(a.center[1] - b.center[1]) >= (a.size[1] + b.size[1]) / 2 + FURNITURE_GAP - 1e-9)
    assert {"table", "round table", "wooden table", "shelf", "sink", "counter", "coffee machine"} == {
        f.name for f in furniture}


def test_same_seed_same_layout_and_choices_respected():
    a, sa, _ = generate(Scenario(seed=3))
    b, sb, _ = generate(Scenario(seed=3))
    assert sa == sb
    assert [tuple(e.center) for e in a.entities] == [tuple(e.center) for e in b.entities]
    w, s, start = generate(Scenario(seed=4, target_object="Purple  Cup", destination="round table",
                                    distractors=("red cup",), extra_objects=("orange", "banana"),
                                    start=Pose(position=Vec3(x=0.1, y=0.2), yaw=1.0)))
    assert s.target_object == "purple cup" and s.destination == "round table"
    assert {o.name for o in w.objects} == {"purple cup", "red cup", "orange", "banana"}
    assert w.by_name("purple cup").support != "round table"
    assert start.position.x == 0.1 and start.yaw == 1.0
    with pytest.raises(ScenarioError, match="unicorn"):
        generate(Scenario(target_object="unicorn"))
    with pytest.raises(ScenarioError, match="coffee machine"):
        generate(Scenario(destination="coffee machine"))


def _rendered_ids(world, start: Pose, altitude: float) -> set[int]:
    frame = preview(world, np.array([start.position.x, start.position.y, altitude]), start.yaw, "ideal")
    return set(np.unique(frame.instance).tolist())


@pytest.mark.parametrize("seed", range(6))
def test_target_out_of_view_is_outside_the_frustum(seed):
    world, scen, start = generate(Scenario(seed=seed, target_out_of_view=True))
    target = world.by_name(scen.target_object)
    for alt in (0.0, 1.0, 1.5):
        ids = _rendered_ids(world, start, alt)
        assert target.id not in ids, f"seed {seed}: {target.name} visible at {alt} m"
        assert len(ids) > 2  # the camera does see the room


def test_target_in_view_by_default():
    visible = 0
    for seed in range(6):
        world, scen, start = generate(Scenario(seed=seed))
        target = world.by_name(scen.target_object)
        visible += any(target.id in _rendered_ids(world, start, alt) for alt in (0.0, 1.5))
    assert visible >= 5


def test_coarse_rendering_keeps_calibration():
    """render_scale 2 renders a half-size image whose pixel centres fall on the centres of 2x2 blocks of
    full-resolution pixels. On a plane 1/z is affine in the pixel coordinates, so the coarse inverse depth
    equals the block mean."""
    from services.sim.render_worker import coarse_intrinsics

    world, _, start = generate(Scenario(seed=1))
    snap = snapshot_at(world, np.array([start.position.x, start.position.y, 1.5]), start.yaw)
    full = Renderer(realism="ideal").render(snap)
    coarse = Renderer(coarse_intrinsics(2), realism="ideal").render(snap)
    blocks = full.instance.reshape(240, 2, 320, 2)
    floor = (blocks == 1).all(axis=(1, 3)) & (coarse.instance == 1)
    inv = (1.0 / np.maximum(full.depth_mm, 1).astype(float)).reshape(240, 2, 320, 2).mean(axis=(1, 3))
    expect = 1.0 / inv
    err = np.abs(coarse.depth_mm.astype(float) - expect)[floor]
    assert floor.sum() > 10_000
    assert np.percentile(err, 95) < 1.0  # millimetres: only the depth rounding
    # A one-pixel shift would be far off: the floor depth changes by several mm per row here.
    shifted = np.abs(coarse.depth_mm[1:].astype(float) - expect[:-1])[floor[1:] & floor[:-1]]
    assert np.median(shifted) > 5 * np.median(err) + 1.0


@pytest.mark.parametrize("seed", range(4))
def test_placements_put_objects_on_the_named_surface(seed):
    scen = Scenario(seed=seed, target_object="orange", extra_objects=("banana",), distractors=("red cup",),
                    placements={"Orange": "counter", "red cup": "shelf"})
    world, filled, start = generate(scen)
    assert world.by_name("orange").support == "counter"
    assert world.by_name("red cup").support == "shelf"
    assert filled.placements == {"orange": "counter", "red cup": "shelf"}
    # The target's surface is the one faced at the start, so "approach the counter" starts looking at it.
    counter = world.by_name("counter")
    bearing = math.atan2(counter.center[1] - start.position.y, counter.center[0] - start.position.x) - start.yaw
    assert abs(math.atan2(math.sin(bearing), math.cos(bearing))) < 1e-6
    with pytest.raises(ScenarioError, match="coffee machine"):
        generate(Scenario(seed=seed, target_object="orange", placements={"orange": "coffee machine"}))
    with pytest.raises(ScenarioError, match="destination"):
        generate(Scenario(seed=seed, target_object="orange", destination="counter", placements={"orange": "counter"}))


_RENDER_TWICE = """
{first}
import numpy as np
from services.sim.render import preview
from services.sim.scenarios import generate
from shared.messages import Scenario

world, _, start = generate(Scenario(seed=0))
for attempt in (1, 2):  # a second renderer after a failed context is what aborted the process
    try:
        frame = preview(world, np.array([start.position.x, start.position.y, 1.5]), start.yaw, "ideal")
        print("rendered", int(frame.rgb.max()))
    except RuntimeError as exc:
        print("refused:", exc)
"""


@pytest.mark.parametrize("first", ["import mujoco", "import services.sim"])
def test_mujoco_imported_before_the_simulator_is_refused_with_the_cause_not_an_abort(first):
    """MuJoCo picks its OpenGL platform (MUJOCO_GL) when first imported; `services.sim` sets the headless default
    on import. A process that imports mujoco first got GLFW, which has no context without a display: MjrContext
    raised and the next renderer aborted Python. Now each render is refused with the cause; with the simulator
    imported first it renders."""
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM", "DISPLAY")}
    root = Path(__file__).resolve().parents[2]
    env["PYTHONPATH"] = str(root)
    p = subprocess.run([sys.executable, "-c", _RENDER_TWICE.format(first=first)], env=env, cwd=root,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, (p.returncode, p.stdout, p.stderr[-2000:])
    lines = p.stdout.splitlines()
    if first == "import mujoco":
        assert len(lines) == 2 and all("mujoco was imported before services.sim" in x for x in lines), lines
    else:
        assert len(lines) == 2 and all(x.startswith("rendered ") and int(x.split()[1]) > 0 for x in lines), lines
