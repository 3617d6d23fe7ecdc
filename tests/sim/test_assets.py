"""The textured look: generated meshes and textures, objects that rest and grasp like the primitives, segmentation
ids on every geom of an object, and the `ideal` look left as it was."""

from __future__ import annotations

import filecmp
import math
from pathlib import Path

import numpy as np
import pytest

from services.sim import assets
from services.sim.core import SimCore
from services.sim.layout import OBJECTS
from services.sim.physics import World, build_xml, entity_geoms, look_for
from services.sim.render import Renderer, snapshot_at
from services.sim.scenarios import _structure, generate
from shared.messages import Pose, Scenario, Vec3
from tests.perception.scenes import furniture, thing
from tests.sim.flight import Clock, grasp, make_core, to_offboard

START = Pose(position=Vec3(x=0.0, y=0.0), yaw=0.0)


def _read_obj(path: Path) -> np.ndarray:
    return np.array([[float(x) for x in line.split()[1:4]] for line in path.read_text().splitlines()
                     if line.startswith("v ")])


def test_generation_is_deterministic(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assets.generate_all(a)
    assets.generate_all(b)
    names = sorted(p.name for p in a.iterdir())
    assert names == sorted(p.name for p in b.iterdir())
    assert any(n.endswith(".obj") for n in names) and any(n.endswith(".png") for n in names)
    _, mismatch, errors = filecmp.cmpfiles(a, b, names, shallow=False)
    assert mismatch == [] and errors == []


def test_every_mesh_is_small_and_inside_its_objects_box():
    root = assets.asset_dir()
    for name, model in assets.OBJECT_MODELS.items():
        half = np.array(OBJECTS[name].size) / 2
        verts = np.vstack([_read_obj(root / f"{p.mesh}.obj") for p in model.parts])
        assert (np.abs(verts) <= half + 0.002).all(), f"{name} mesh leaves its catalogue box {OBJECTS[name].size}"
        # Fills it too: a mesh much smaller than the box would make the judge's size a lie (a mug's body is
        # narrower than its box across the handle, a banana's curve thinner than its box).
        assert (verts.max(0) - verts.min(0) >= 0.75 * 2 * half).all(), f"{name} mesh is smaller than its box"
        n_tri = sum(len(assets_faces(root / f"{p.mesh}.obj")) for p in model.parts)
        assert 12 <= n_tri <= 3000, f"{name}: {n_tri} triangles"
    assert set(assets.OBJECT_MODELS) == set(OBJECTS)


def assets_faces(path: Path) -> list[str]:
    return [line for line in path.read_text().splitlines() if line.startswith("f ")]


def _on_table(name: str, look: str, yaw: float = 0.4) -> World:
    table = furniture("table", 0.0, 0.0)
    return World(entities=_structure() + [table, thing(name, 0.05, -0.03, table, yaw)], look=look, settle_s=0.0)


@pytest.mark.parametrize("name", list(OBJECTS))
def test_object_rests_on_a_table_upright_and_still(name):
    world = _on_table(name, "textured")
    e = world.by_name(name)
    start = e.center.copy()
    world.step(2.0)
    assert e.support == "table", f"{name} rests on {e.support}"
    assert e.tilt < math.radians(3), f"{name} tilted {math.degrees(e.tilt):.1f} deg"
    assert world.object_speed(name) < 1e-3
    assert np.linalg.norm(e.center[:2] - start[:2]) < 0.005, f"{name} slid {e.center - start}"
    assert abs(e.bottom_z - world.by_name("table").top_z) < 0.005


def test_every_geom_of_an_object_carries_its_instance_id():
    import mujoco  # after services.sim, which picks the headless GL backend before mujoco loads

    world, _, _ = generate(Scenario(seed=3, distractors=(), extra_objects=tuple(n for n in OBJECTS if n != "red cup"),
                                    target_object="red cup"), look="textured")
    m = world.model
    for e in world.objects:
        body = m.body("obj " + e.name).id
        geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] == body]
        assert sorted(geoms) == sorted(entity_geoms(m, e))
        meshes = [g for g in geoms if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH]
        assert meshes, f"{e.name} has no mesh"
        assert all(world.geom_instance[g] == e.id for g in geoms), e.name
        assert all(world.geom_entity[g] is e for g in geoms)


def test_segmentation_of_the_textured_look_covers_the_mesh():
    world = _on_table("purple cup", "textured")
    e = world.by_name("purple cup")
    r = Renderer(realism="ideal")
    try:
        pos = e.center + np.array([-0.9, 0.0, 0.45])
        f = r.render(snapshot_at(world, pos, 0.0))
    finally:
        r.close()
    mask = f.instance == e.id
    assert mask.sum() > 300
    # The mug's pixels (its purple) are the instance's: no purple pixel outside the mask, none unlabelled.
    rgb = f.rgb.astype(int)
    purple = (rgb[..., 2] > rgb[..., 1] + 60) & (rgb[..., 0] > rgb[..., 1] + 20)
    assert purple.sum() > 200
    assert (purple & ~mask).sum() <= 0.02 * purple.sum()


# Width between the pads when held at the box centre: the party cup's 8 cm (as the primitive), the mug's 6.4 cm
# body, the banana's 3.4 cm middle, the hammer's 2.5 cm handle (the primitives' boxes were 4.5 and 10 cm wide).
HELD_WIDTH = {"red cup": 0.08, "purple cup": 0.064, "banana": 0.034, "hammer": 0.025}


@pytest.mark.parametrize("name", list(HELD_WIDTH))
def test_textured_objects_are_grasped_by_their_colliders(name):
    core = make_core(Scenario(seed=1, target_object=name, distractors=(), start=START), "realistic")
    assert core.world.look == "textured"
    clock = Clock(core)
    to_offboard(core, clock)
    obj = core.world.by_name(name)
    assert grasp(core, clock, name, obj.yaw)  # the pads close across the short side
    assert obj.center[2] > 1.2  # lifted with the vehicle
    assert abs(core.vehicle.finger_width - HELD_WIDTH[name]) < 0.006, core.vehicle.finger_width


def test_the_ideal_look_builds_the_primitives():
    import mujoco

    world, _, _ = generate(Scenario(seed=2), look=look_for("ideal"))
    assert world.look == "primitive"
    assert "<mesh" not in world.xml and "file=" not in world.xml
    m = world.model
    kinds = {"box": mujoco.mjtGeom.mjGEOM_BOX, "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
             "sphere": mujoco.mjtGeom.mjGEOM_SPHERE}
    for e in world.objects:
        geoms = entity_geoms(m, e)
        assert len(geoms) == 1 and m.geom_type[geoms[0]] == kinds[e.shape]
    # The same layout under the textured look differs only in how things look: same entities, same places.
    textured, _, _ = generate(Scenario(seed=2), look="textured")
    assert [e.name for e in world.entities] == [e.name for e in textured.entities]
    for a, b in zip(world.entities, textured.entities, strict=True):
        assert np.linalg.norm(a.center[:2] - b.center[:2]) < (0.01 if a.category == "object" else 1e-9), a.name
    assert build_xml(world.entities, 2, True) == build_xml(world.entities, 2, True, "primitive")


def test_simcore_picks_the_look_from_its_realism():
    assert SimCore(Scenario(seed=1), realism="ideal").world.look == "primitive"
    assert SimCore(Scenario(seed=1), realism="realistic").world.look == "textured"
