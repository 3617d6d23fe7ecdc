"""Issue 4's accuracy sweep: 20 random sim layouts, every object and surface, both segmenters.

The pipeline runs in-process on frames the simulator's own camera produces (MuJoCo rendering with the
realistic stereo camera: noise, scale bias, occlusion bands, flying pixels, dropouts, misregistration; exposure
model; same JPEG as the sim process publishes), so 20 layouts take a few minutes instead of twenty;
test_service.py runs the real service process against the real sim process for a sample.

Comparison with ground truth (the sim's world model):
- objects: the error, the larger of the horizontal distance of the estimated centre to the true box centre and
  |top_z - true top|, against the sensor's error model at the object's distance from the camera: the 95th and
  99th percentiles of that error measured by `benchmarks/depth_error.py --views sweep --write-model` on dev
  layouts (seeds >= 100; these are 0-19) with the same camera, look and kind of views, per 3-D distance bin
  (`benchmarks/data/depth_error_model.json`). A correct pipeline puts about 5 % of the objects beyond the p95 and
  1 % beyond the p99, so each count may reach what a binomial reaches with probability 1 % (`allowed_beyond`):
  a wrong calibration shows in the first, rare gross errors (flying pixels, a misregistered rim) in the second;
- placement: the spot lies on the asked surface (inside its footprint), no object resting there is closer
  than its footprint radius plus the held object's, and |surface_z - true top| <= 5 cm.
"In view" means: the whole bounding box projects inside the image, at least half of the thing's pixels
are unoccluded (rendered alone vs in the scene), and it is within 3 m of the camera (beyond that a table
top is seen at a grazing angle and only a thin side of an object remains). "Not in view" means no pixel
at all: the answer must then be not_visible. Partly visible things are counted, not judged."""

from __future__ import annotations

import json
import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from services.perception import query as q
from services.perception.pipeline import Perception
from services.perception.segmenters import make_segmenter
from services.perception.settings import PerceptionSettings
from services.sim.render import Renderer
from shared.messages import LocalizeRequest, Vec3
from tests.perception.scenes import aim_at, classify, layout, render_view

pytestmark = pytest.mark.slow

SEEDS = range(20)
COLOR_SET = ("red cup", "green bottle", "purple cup", "orange", "banana", "coke can", "tissue box")
HELD = Vec3(x=0.08, y=0.08, z=0.11)


MODEL = Path(__file__).resolve().parents[2] / "benchmarks" / "data" / "depth_error_model.json"
ALPHA = 0.01  # chance that a correct pipeline fails one of the two counts on these layouts (the test is
# deterministic: the chance is over which layouts seeds 0-19 happen to draw)


def error_bound(range_m: float, quantile: str = "p95") -> float:
    """The sensor's object error (m) at `range_m` from the camera that a fraction of objects exceeds: the measured
    model's `quantile` (p95, p99) in its distance bin (beyond the last bin, the last)."""
    bins = json.loads(MODEL.read_text())["figures"]["bins"]
    row = next((b for b in bins if b["lo_m"] <= range_m < b["hi_m"]), bins[-1])
    return float(row[f"{quantile}_cm"]) / 100


def allowed_beyond(n: int, p: float, alpha: float = ALPHA) -> int:
    """The largest count of n objects beyond a (1 - p)-quantile bound that a correct pipeline reaches with
    probability >= alpha: the smallest k with P(Binomial(n, p) > k) <= alpha."""
    tail, k = 1.0, 0
    while True:
        tail -= math.comb(n, k) * p ** k * (1 - p) ** (n - k)
        if tail <= alpha:
            return k
        k += 1


def object_error(est, e) -> float:
    p = est.pose.position
    return max(math.hypot(p.x - e.center[0], p.y - e.center[1]), abs(est.top_z - e.top_z))


def object_range(e, view) -> float:
    return float(np.linalg.norm(e.center - view.frame.world_from_camera[:3, 3]))


def placement_ok(est, surface, world) -> bool:
    p = est.pose.position
    if not surface.contains_xy(p.x, p.y) or abs(est.surface_z - surface.top_z) > 0.05:
        return False
    r = math.hypot(HELD.x, HELD.y) / 2
    return all(math.hypot(p.x - o.center[0], p.y - o.center[1]) >= o.footprint_radius() + r
               for o in world.objects if o.support == surface.name)


def judge_object(c: Counter, failures: list[str], what: str, cls: str, est, e, view) -> None:
    """Count one object query's outcome by how the object appears (`cls`) and note what went wrong."""
    c[f"object_{cls}"] += 1
    if cls == "in_view":
        if not est.found:
            c["object_miss"] += 1
            failures.append(f"{what}: {est.reason} {est.message}")
        else:
            err, bound = object_error(est, e), error_bound(object_range(e, view))
            c["object_ok" if err <= bound else "object_wrong"] += 1
            if err > error_bound(object_range(e, view), "p99"):
                c["object_beyond_p99"] += 1
            if err > bound:
                failures.append(f"{what}: off by {100 * err:.1f} cm at {object_range(e, view):.2f} m, p95 bound "
                                f"{100 * bound:.1f} cm")
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


def sweep_layout(seed: int, seg: dict, rng: np.random.Generator, st: dict, failures: list[str]) -> None:
    """Every object and surface of layout `seed`, through camera unit `seed` (the error model pooled units of
    either bias sign: one unit for the whole sweep would shift every far object the same way)."""
    world = layout(seed)
    camera = Renderer(realism="realistic", seed=seed, unit=seed)
    try:
        present = {e.name for e in world.objects}
        for target in world.objects:
            view = render_view(world, *aim_at(world, target.center, rng.uniform(0.8, 1.4), rng), camera=camera)
            for e in world.objects:
                cls = classify(view, e)
                for kind, p in seg.items():
                    if kind == "color" and e.name not in COLOR_SET:
                        continue
                    est = p.localize_object(view.frame, LocalizeRequest(query=e.name), q.parse(e.name))
                    judge_object(st[kind], failures, f"{kind} seed {seed} {e.name}", cls, est, e, view)
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
            view = render_view(world, *aim_at(world, top, 1.4, rng), camera=camera)
            for s in world.surfaces:
                # The aimed-at surface is judged fully; the others only when they are out of the image.
                if s is not surface and (view.instance == s.id).any():
                    continue
                for kind, p in seg.items():
                    est = p.localize_placement(view.frame, LocalizeRequest(query=s.name, object_size=HELD),
                                               q.parse(s.name))
                    judge_placement(st[kind], failures, f"{kind} seed {seed} {s.name}", s is surface, est, s, world)
    finally:
        camera.close()


@pytest.mark.timeout(1500)
def test_twenty_layouts_sim_and_color() -> None:
    seg = {k: Perception(make_segmenter(PerceptionSettings(segmenter=k)), PerceptionSettings(segmenter=k))
           for k in ("sim", "color")}
    rng = np.random.default_rng(4)
    st = {k: Counter() for k in seg}
    failures: list[str] = []
    for seed in SEEDS:
        sweep_layout(seed, seg, rng, st, failures)
    for kind, c in st.items():
        print(kind, dict(c))
    print("\n".join(failures[:40]))
    sim, col = st["sim"], st["color"]
    # sim segmenter: perfect masks, so every in-view object is found and every aimed-at surface is right. The
    # sensor's error model (dev layouts) says how many objects may lie beyond its p95 and its p99: a broad
    # degradation (a wrong calibration) shows in the first count, rare gross errors (flying pixels) in the second.
    judged = sim["object_ok"] + sim["object_wrong"]
    assert sim["object_miss"] == 0 and sim["object_false"] == 0
    assert sim["object_ok"] >= 100
    assert sim["object_wrong"] <= allowed_beyond(judged, 0.05), (sim["object_wrong"], judged)
    assert sim["object_beyond_p99"] <= allowed_beyond(judged, 0.01), (sim["object_beyond_p99"], judged)
    assert sim["place_miss"] == 0 and sim["place_wrong"] == 0 and sim["place_false"] == 0
    # color segmenter on the seven objects: recall >= 90 %; of what it finds, no more beyond the sensor's
    # bounds than chance allows (its masks as good as the oracle's); false finds <= 5 % of the answers.
    in_view = col["object_ok"] + col["object_miss"] + col["object_wrong"]
    found = col["object_ok"] + col["object_wrong"]
    answered = found + col["object_false"]
    assert in_view >= 30
    assert found / in_view >= 0.90
    assert col["object_wrong"] <= allowed_beyond(found, 0.05), (col["object_wrong"], found)
    assert col["object_beyond_p99"] <= allowed_beyond(found, 0.01), (col["object_beyond_p99"], found)
    assert col["object_false"] / max(answered, 1) <= 0.05
    assert col["place_wrong"] == 0 and col["place_false"] == 0
    # Surface tops by colour under the varying room light: measured 107/120 (a top in deep shadow or seen at a
    # grazing angle is missed, never taken for another).
    assert col["place_ok"] / max(col["place_ok"] + col["place_miss"], 1) >= 0.85
