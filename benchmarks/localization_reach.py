"""Localization error against distance under the realistic camera: the curve behind the executor's `reach`.

Usage: .venv/bin/python benchmarks/localization_reach.py [--seeds 6] [--segmenter color]

For every object of a few seeded layouts and every distance, a body pose is chosen that aims the camera at the
object from that horizontal distance (as the executor's standoff does); the frame is rendered by MuJoCo with
the realistic stereo-depth and exposure model and the object is localized in-process by the segmenter +
point-cloud pipeline. Prints, per distance, the share found and the horizontal error of the centre (median,
p90) against the simulator's truth. Grasping needs the error well inside the gripper's tolerance (about 3 cm
off the axis across the pads).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks._figures import add_json_option, write_json  # noqa: E402
from services.perception import query as q  # noqa: E402
from services.perception.pipeline import Perception  # noqa: E402
from services.perception.segmenters import make_segmenter  # noqa: E402
from services.perception.segmenters.color import DEFAULT_OBJECTS  # noqa: E402
from services.perception.settings import PerceptionSettings  # noqa: E402
from shared.messages import LocalizeRequest  # noqa: E402
from tests.perception.scenes import aim_at, layout, render_view  # noqa: E402

DISTANCES = (0.75, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--segmenter", default="color")
    add_json_option(ap)
    a = ap.parse_args()
    s = PerceptionSettings(segmenter=a.segmenter)
    p = Perception(make_segmenter(s), s)
    known = {c.name for c in DEFAULT_OBJECTS} if a.segmenter == "color" else None
    rng = np.random.default_rng(11)
    errs: dict[float, list[float]] = {d: [] for d in DISTANCES}
    tries: dict[float, int] = dict.fromkeys(DISTANCES, 0)
    for seed in range(a.seeds):
        world = layout(seed)
        for e in world.objects:
            if known is not None and e.name not in known:
                continue
            for d in DISTANCES:
                view = render_view(world, *aim_at(world, e.center, d, rng))
                if (view.instance == e.id).sum() < 30:
                    continue  # occluded or out of the frame from this side: not a localization question
                tries[d] += 1
                est = p.localize_object(view.frame, LocalizeRequest(query=e.name), q.parse(e.name))
                if est.found and est.label == e.name:
                    pos = est.pose.position
                    errs[d].append(math.hypot(pos.x - e.center[0], pos.y - e.center[1]))
    print(f"segmenter {a.segmenter}, realistic camera, {a.seeds} layouts")
    print("distance_m  tries  found_%  err_median_cm  err_p90_cm")
    rows = {}
    for d in DISTANCES:
        e = np.array(errs[d])
        found = 100.0 * len(e) / tries[d] if tries[d] else float("nan")
        med = 100 * np.median(e) if len(e) else float("nan")
        p90 = 100 * np.percentile(e, 90) if len(e) else float("nan")
        print(f"{d:10.2f}  {tries[d]:5d}  {found:7.1f}  {med:13.1f}  {p90:10.1f}")
        rows[f"{d:.2f}"] = {"tries": tries[d], "found_pct": found, "err_median_cm": med, "err_p90_cm": p90}
    write_json(a.json, "localization_reach", {"by_distance_m": rows}, a)


if __name__ == "__main__":
    main()
