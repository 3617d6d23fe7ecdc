"""Issue 4's accuracy sweep: 20 random sim layouts, every object and surface, both segmenters.

The pipeline runs in-process on frames the simulator's own camera produces (MuJoCo rendering with the
realistic stereo-depth and exposure model, same JPEG as the sim process publishes), so 20 layouts take a
minute instead of twenty; test_service.py runs the real service process against the real sim process for a
sample.

Comparison with ground truth (the sim's world model):
- objects: horizontal distance of the estimated centre to the true box centre <= 4 cm, and |top_z - true
  top| <= 4 cm (realistic depth noise);
- placement: the spot lies on the asked surface (inside its footprint), no object resting there is closer
  than its footprint radius plus the held object's, and |surface_z - true top| <= 5 cm.
"In view" means: the whole bounding box projects inside the image, at least half of the thing's pixels
are unoccluded (rendered alone vs in the scene), and it is within 3 m of the camera (beyond that a table
top is seen at a grazing angle and only a thin side of an object remains). "Not in view" means no pixel
at all: the answer must then be not_visible. Partly visible things are counted, not judged."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest

from services.perception import query as q
from services.perception.pipeline import Perception
from services.perception.segmenters import make_segmenter
from services.perception.settings import PerceptionSettings
from shared.messages import LocalizeRequest, Vec3
from tests.perception.scenes import aim_at, layout, projected_corners_in_view, render_view, unoccluded_pixels

pytestmark = pytest.mark.slow

SEEDS = range(20)
COLOR_SET = ("red cup", "green bottle", "purple cup", "orange", "banana", "coke can", "tissue box")
HELD = Vec3(x=0.08, y=0.08, z=0.11)


def classify(view, e) -> str:
    px = int((view.instance == e.id).sum())
    if px == 0:
        return "absent"
    if (px >= 100 and projected_corners_in_view(e, view.frame)
            and np.linalg.norm(e.center - view.frame.world_from_camera[:3, 3]) <= 3.0
            and px >= 0.5 * unoccluded_pixels(view, e)):
        return "in_view"
    return "partial"


OBJECT_TOL = 0.04  # m: the frames carry the realistic stereo depth noise (sigma 0.004 z^2: 1.6 cm at 2 m)


def object_ok(est, e) -> bool:
    p = est.pose.position
    return (math.hypot(p.x - e.center[0], p.y - e.center[1]) <= OBJECT_TOL
            and abs(est.top_z - e.top_z) <= OBJECT_TOL)


def placement_ok(est, surface, world) -> bool:
    p = est.pose.position
    if not surface.contains_xy(p.x, p.y) or abs(est.surface_z - surface.top_z) > 0.05:
        return False
    r = math.hypot(HELD.x, HELD.y) / 2
    return all(math.hypot(p.x - o.center[0], p.y - o.center[1]) >= o.footprint_radius() + r
               for o in world.objects if o.support == surface.name)


def judge_object(c: Counter, failures: list[str], what: str, cls: str, est, e) -> None:
    """Count one object query's outcome by how the object appears (`cls`) and note what went wrong."""
    c[f"object_{cls}"] += 1
    if cls == "in_view":
        if not est.found:
            c["object_miss"] += 1
            failures.append(f"{what}: {est.reason} {est.message}")
        elif not object_ok(est, e):
            c["object_wrong"] += 1
            failures.append(f"{what}: off {est.pose.position} vs {e.center}")
        else:
            c["object_ok"] += 1
    elif cls == "absent" and est.found:
        c["object_false"] += 1
        failures.append(f"{what}: found but not in the image")
    elif cls == "absent":
        c["absent_ok"] += 1


def judge_placement(c: Counter, failures: list[str], what: str, aimed: bool, est, s, world) -> None:
    """Count one placement query's outcome (`aimed`: the camera looks at this surface, else it is out of view)."""
    if est.found and not placement_ok(est, s, world):
        c["place_wrong"] += 1
        failures.append(f"{what}: spot {est.pose.position} not free/on it")
    elif est.found:
        c["place_ok"] += 1
    elif aimed:
        c["place_miss"] += 1
        failures.append(f"{what}: {est.reason} {est.message}")
    if not aimed and est.found:
        c["place_false"] += 1


@pytest.mark.timeout(1500)
def test_twenty_layouts_sim_and_color() -> None:
    seg = {k: Perception(make_segmenter(PerceptionSettings(segmenter=k)), PerceptionSettings(segmenter=k))
           for k in ("sim", "color")}
    rng = np.random.default_rng(4)
    st = {k: Counter() for k in seg}
    failures: list[str] = []
    for seed in SEEDS:
        world = layout(seed)
        present = {e.name for e in world.objects}
        for target in world.objects:
            view = render_view(world, *aim_at(world, target.center, rng.uniform(0.8, 1.4), rng))
            for e in world.objects:
                cls = classify(view, e)
                for kind, p in seg.items():
                    if kind == "color" and e.name not in COLOR_SET:
                        continue
                    est = p.localize_object(view.frame, LocalizeRequest(query=e.name), q.parse(e.name))
                    judge_object(st[kind], failures, f"{kind} seed {seed} {e.name}", cls, est, e)
            # Names the layout does not have at all must be not_visible, never another object.
            for name in COLOR_SET:
                if name not in present:
                    for kind, p in seg.items():
                        est = p.localize_object(view.frame, LocalizeRequest(query=name), q.parse(name))
                        st[kind]["missing_queries"] += 1
                        if est.found:
                            st[kind]["object_false"] += 1
                            failures.append(f"{kind} seed {seed} {name}: found {est.label} but it is not there")
        for surface in world.surfaces:
            top = surface.center.copy()
            top[2] = surface.top_z
            view = render_view(world, *aim_at(world, top, 1.4, rng))
            for s in world.surfaces:
                # The aimed-at surface is judged fully; the others only when they are out of the image.
                if s is not surface and (view.instance == s.id).any():
                    continue
                for kind, p in seg.items():
                    est = p.localize_placement(view.frame, LocalizeRequest(query=s.name, object_size=HELD),
                                               q.parse(s.name))
                    judge_placement(st[kind], failures, f"{kind} seed {seed} {s.name}", s is surface, est, s, world)
    for kind, c in st.items():
        print(kind, dict(c))
    print("\n".join(failures[:40]))
    sim, col = st["sim"], st["color"]
    # sim segmenter: perfect masks, so every in-view object is found and every aimed-at surface is right; the
    # realistic stereo depth (noise ~ z^2, holes at edges) leaves a few centres beyond 4 cm (measured: 2 of
    # 119, a cup seen at the image border and a can at 1.4 m).
    assert sim["object_miss"] == 0 and sim["object_false"] == 0
    assert sim["object_wrong"] <= 0.03 * (sim["object_ok"] + sim["object_wrong"])
    assert sim["object_ok"] >= 100
    assert sim["place_miss"] == 0 and sim["place_wrong"] == 0 and sim["place_false"] == 0
    # color segmenter on the seven objects: recall >= 90 %, wrong-object rate <= 5 %.
    in_view = col["object_ok"] + col["object_miss"] + col["object_wrong"]
    answered = col["object_ok"] + col["object_wrong"] + col["object_false"]
    assert in_view >= 30
    assert col["object_ok"] / in_view >= 0.90
    assert (col["object_wrong"] + col["object_false"]) / max(answered, 1) <= 0.05
    assert col["place_wrong"] == 0 and col["place_false"] == 0
    # Surface tops by colour under the varying room light: measured 107/120 (a top in deep shadow or seen at a
    # grazing angle is missed, never taken for another).
    assert col["place_ok"] / max(col["place_ok"] + col["place_miss"], 1) >= 0.85
