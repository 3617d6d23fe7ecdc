"""obj_localization / placement_localization on sim-rendered frames, in-process (MuJoCo's camera with the
realistic stereo-depth noise, real Open3D, real JPEG): accuracy, reasons for not finding, size words and
ambiguity, bad depth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.perception import query as q
from services.perception.pipeline import Perception
from services.perception.segmenters import make_segmenter
from services.perception.settings import PerceptionSettings
from services.sim.render import Renderer
from shared.messages import LocalizeRequest, Vec3
from tests.perception.scenes import furniture, layout, manual_world, render_view, thing

TABLE = furniture("table", 2.0, 0.0)  # 1.2 x 0.8, top at 0.75
OBJS = [
    thing("red cup", 1.75, 0.2, TABLE), thing("purple cup", 1.8, -0.2, TABLE),
    thing("tissue box", 2.05, 0.05, TABLE, yaw=0.4), thing("cardboard box", 2.35, -0.15, TABLE, yaw=0.785),
    thing("orange", 1.85, 0.0, TABLE), thing("banana", 2.1, 0.28, TABLE, yaw=-0.3),
]
WORLD = manual_world(TABLE, *OBJS)
POSE = (0.95, 0.0, 1.55, 0.0)  # 1 m in front of the table edge, looking at it


@pytest.fixture(scope="module")
def view():
    return render_view(WORLD, *POSE)


def perception(kind: str = "sim", **kw) -> Perception:
    s = PerceptionSettings(segmenter=kind, **kw)
    return Perception(make_segmenter(s), s)


@pytest.fixture(scope="module")
def sim() -> Perception:
    return perception("sim")


@pytest.fixture(scope="module")
def color() -> Perception:
    return perception("color")


def obj(p: Perception, frame, text: str):
    return p.localize_object(frame, LocalizeRequest(query=text), q.parse(text))


def place(p: Perception, frame, text: str, size: Vec3 | None = None):
    return p.localize_placement(frame, LocalizeRequest(query=text, object_size=size), q.parse(text))


@pytest.mark.parametrize("kind", ["sim", "color"])
@pytest.mark.parametrize("e", OBJS, ids=lambda e: e.name)
def test_object_within_3cm(kind: str, e, view, sim, color) -> None:
    p = sim if kind == "sim" else color
    est = obj(p, view.frame, e.name)
    assert est.found, est.message
    assert est.label == e.name
    pos = est.pose.position
    assert math.hypot(pos.x - e.center[0], pos.y - e.center[1]) <= 0.03
    assert abs(est.top_z - e.top_z) <= 0.03
    assert abs(pos.z - e.center[2]) <= 0.03
    assert abs(est.support_z - TABLE.top_z) <= 0.02
    assert est.n_points > 30 and 0 < est.confidence <= 1
    assert est.bbox is not None and est.frame_stamp_ns == view.frame.stamp_ns
    # the class's catalogued extent standing (long, short, height): the grasp tells lying from standing by it
    long_, short = max(e.size[0], e.size[1]), min(e.size[0], e.size[1])
    assert est.catalog_size == Vec3(x=long_, y=short, z=e.size[2]), est.catalog_size


def test_box_yaw_and_size_are_not_pca_diagonals(view, sim) -> None:
    est = obj(sim, view.frame, "tissue box")  # 24 x 12 cm, yawed 0.4 rad: yaw along the long side (mod pi)
    assert est.size.x == pytest.approx(0.24, abs=0.02) and est.size.y == pytest.approx(0.12, abs=0.02)
    d = (est.pose.yaw - 0.4) % math.pi
    assert min(d, math.pi - d) < math.radians(6)
    est = obj(sim, view.frame, "banana")  # elongated: yaw along its long side (mod pi)
    d = (est.pose.yaw + 0.3) % math.pi
    assert min(d, math.pi - d) < math.radians(6)
    assert est.size.x == pytest.approx(0.19, abs=0.02)


@pytest.mark.parametrize("kind", ["sim", "color"])
def test_size_words_and_ambiguity(kind: str, view, sim, color) -> None:
    p = sim if kind == "sim" else color
    # Two real boxes of different measured sizes (no object is named after the answer).
    assert obj(p, view.frame, "the larger box").label == "cardboard box"
    assert obj(p, view.frame, "the smaller box").label == "tissue box"
    cup = obj(p, view.frame, "cup")
    assert not cup.found and cup.reason == "ambiguous"
    assert obj(p, view.frame, "the red one").label == "red cup"
    missing = obj(p, view.frame, "green bottle")
    assert not missing.found and missing.reason == "not_visible"
    assert obj(p, view.frame, "snack").reason == "ambiguous"  # orange and banana


def test_out_of_view_is_not_visible(sim, color) -> None:
    away = render_view(WORLD, 0.95, 0.0, 1.55, math.pi)  # looking at the empty half of the room
    for p in (sim, color):
        est = obj(p, away.frame, "red cup")
        assert not est.found and est.reason == "not_visible", est.message
        assert place(p, away.frame, "table").reason == "not_visible"


def test_depth_invalid_and_too_few_points(view, sim) -> None:
    f = render_view(WORLD, *POSE).frame
    red = OBJS[0]
    mask = f.segmentation == red.id
    orig = f.depth_mm.copy()
    f.depth_mm = f.depth_mm.copy()
    f.depth_mm[mask] = 0
    assert obj(sim, f, "red cup").reason == "depth_invalid"
    keep = np.flatnonzero((mask & (orig > 0)).ravel())[:10]  # ten pixels that had depth (stereo leaves holes)
    f.depth_mm.ravel()[keep] = orig.ravel()[keep]
    est = obj(sim, f, "red cup")
    assert est.reason == "too_few_points" and est.n_points == 10


@pytest.mark.parametrize("kind", ["sim", "color"])
def test_placement_on_table_is_free_and_on_surface(kind: str, view, sim, color) -> None:
    p = sim if kind == "sim" else color
    size = Vec3(x=0.08, y=0.08, z=0.11)
    est = place(p, view.frame, "the table", size)
    assert est.found, est.message
    assert est.label == "table"
    pos = est.pose.position
    assert abs(est.surface_z - TABLE.top_z) <= 0.01
    assert pos.z == pytest.approx(est.surface_z + est.vertical_offset)
    assert TABLE.contains_xy(pos.x, pos.y, margin=0.04)
    for o in OBJS:
        gap = math.hypot(pos.x - o.center[0], pos.y - o.center[1]) - o.footprint_radius()
        assert gap >= 0.04, f"spot {pos} is {gap:.3f} m from the {o.name}"
    assert est.clearance >= 0.04 + 0.03
    assert est.plane is not None and est.plane[2] > 0.98


def test_cluttered_surface_has_no_free_spot(sim) -> None:
    shelf = furniture("shelf", 2.0, 0.0)  # 1.0 x 0.5
    clutter = [thing(n, x, y, shelf) for n, x, y in (
        ("cardboard box", 1.68, 0.0), ("tissue box", 2.0, 0.08), ("green bottle", 2.0, -0.15),
        ("cracker box", 2.35, -0.1), ("coke can", 2.38, 0.15))]
    v = render_view(manual_world(shelf, *clutter), *POSE)
    est = place(sim, v.frame, "shelf", Vec3(x=0.3, y=0.3, z=0.2))
    assert not est.found and est.reason == "no_free_spot", est.message
    assert est.surface_z == pytest.approx(0.9, abs=0.01)


def test_detections_list_objects_and_surfaces(view, sim, color) -> None:
    for p in (sim, color):
        dets = p.detections(view.frame)
        labels = {d.label: d for d in dets.items}
        for o in OBJS:
            assert o.name in labels, (p.segmenter.type, sorted(labels))
            c = labels[o.name].centroid
            assert math.hypot(c.x - o.center[0], c.y - o.center[1]) < 0.05
            standing = Vec3(x=max(o.size[0], o.size[1]), y=min(o.size[0], o.size[1]), z=o.size[2])
            assert labels[o.name].catalog_size == standing, (p.segmenter.type, o.name)
        assert labels["table"].category == "surface" and labels["table"].catalog_size is None
        assert dets.segmenter == p.segmenter.type and dets.frame_stamp_ns == view.frame.stamp_ns
        assert "floor" not in labels


def test_color_sink_and_catalog_file(tmp_path) -> None:
    sink = furniture("sink", 2.0, 0.0)
    v = render_view(manual_world(sink, thing("red cup", 1.8, 0.2, sink)), *POSE)
    p = perception("color")
    est = place(p, v.frame, "sink", Vec3(x=0.08, y=0.08, z=0.11))
    assert est.found and sink.contains_xy(est.pose.position.x, est.pose.position.y), est
    assert abs(est.surface_z - sink.top_z) < 0.01
    # A catalogue file replaces the built-in classes: with only a green bottle known, the red cup is unknown.
    cat = tmp_path / "catalog.json"
    cat.write_text('{"objects": [{"name": "green bottle", "color": "green", "hsv": [66, 221, 150], '
                   '"dims": [0.07, 0.07, 0.25]}], "surfaces": [{"name": "sink", "color": "blue steel", '
                   '"rgb": [140, 165, 200], "more_rgb": [[105, 115, 125]]}]}')
    p2 = perception("color", color_catalog=str(cat))
    assert p2.segmenter.known_names(None) == ["green bottle", "sink"]
    assert obj(p2, v.frame, "red cup").reason == "not_visible"
    assert place(p2, v.frame, "sink").found


def test_color_segment_keys_are_unique_when_a_split_blob_is_merged() -> None:
    """Dev clutter/000: localizing "cardboard box" answered "matched cardboard box" with the cracker box's pose,
    label and size. A class split in two blobs was merged under its larger blob's key, and the next class's first
    blob was numbered from the count of segments so far: the same key, and find() returned the first segment with
    it. Seen in 3 of 258 aimed views of dev layouts 100-129 (all a cracker box, whose print the colour classes
    also read as a cardboard box in part: a false detection, issue 33); this is one."""
    world = layout(103, look="textured")
    camera = Renderer(realism="realistic", seed=1)  # its first frame: a fresh camera's noise, the same every run
    try:
        view = render_view(world, -3.552, 1.634, 1.871, -0.694, camera=camera)
    finally:
        camera.close()
    p = perception("color")
    segs = p.segmenter.detect_objects(view.frame)
    assert len(segs) >= 3 and len({s.key for s in segs}) == len(segs), [(s.key, s.label) for s in segs]
    for name in {s.label for s in segs}:
        est = obj(p, view.frame, name)
        assert est.found and est.label == name, (name, est.label, est.message)
    est, truth = obj(p, view.frame, "cracker box"), world.by_name("cracker box")
    assert math.hypot(est.pose.position.x - truth.center[0], est.pose.position.y - truth.center[1]) < 0.1
