"""Per-class detection recall of the `color` segmenter at 1-2 m, on the primitive and on the textured look.

Usage: .venv/bin/python benchmarks/detection_recall.py [--seeds 100-119] [--looks primitive,textured] [--json PATH]

Layouts are generated (`services.sim.scenarios.generate`, dev seeds 100-119 by default: never the evaluation
suites' test split). For every object of a layout the camera is aimed at it from a random bearing 1-2 m away
(horizontally), and the frame is rendered with the realistic camera (stereo depth noise, exposure, JPEG as on the
bus). An object counts when it is in view: its whole bounding box projects inside the image and at least half of
its pixels are unoccluded. It is detected when `localize_object` with its name answers within 5 cm (horizontal
centre) of the truth. The same seeds, bearings and distances are used for every look, so the looks compare
object for object. Prints figures only; never fails on them.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks._figures import add_json_option, write_json  # noqa: E402
from services.perception import query as q  # noqa: E402
from services.perception.pipeline import Perception  # noqa: E402
from services.perception.segmenters import make_segmenter  # noqa: E402
from services.perception.settings import PerceptionSettings  # noqa: E402
from services.sim.layout import OBJECTS  # noqa: E402
from shared.messages import LocalizeRequest  # noqa: E402
from tests.perception.scenes import aim_at, layout, projected_corners_in_view, render_view, unoccluded_pixels  # noqa: E402

TOLERANCE = 0.05  # m, horizontal centre error of a detection


def _seeds(text: str) -> list[int]:
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(s) for s in text.split(",")]


def measure(look: str, seeds: list[int], segmenter: str = "color",
            misses: list[str] | None = None) -> dict[str, dict[str, int]]:
    """Per class: views in view, detected (right place), found elsewhere, not found (each noted in `misses`)."""
    settings = PerceptionSettings(segmenter=segmenter)
    perception = Perception(make_segmenter(settings), settings)
    out: dict[str, dict[str, int]] = defaultdict(lambda: {"in_view": 0, "detected": 0, "wrong_place": 0, "missed": 0})
    for seed in seeds:
        rng = np.random.default_rng(seed)  # the same bearings and distances for every look
        world = layout(seed, look)
        for target in world.objects:
            view = render_view(world, *aim_at(world, target.center, float(rng.uniform(1.0, 2.0)), rng))
            px = int((view.instance == target.id).sum())
            if px < 50 or not projected_corners_in_view(target, view.frame) or px < 0.5 * unoccluded_pixels(view,
                                                                                                          target):
                continue
            c = out[target.name]
            c["in_view"] += 1
            est = perception.localize_object(view.frame, LocalizeRequest(query=target.name), q.parse(target.name))
            err = math.hypot(est.pose.position.x - target.center[0],
                             est.pose.position.y - target.center[1]) if est.found and est.pose else math.inf
            if est.found and err <= TOLERANCE:
                c["detected"] += 1
                continue
            c["missed" if not est.found else "wrong_place"] += 1
            if misses is not None:
                misses.append(f"{look} seed {seed} {target.name} on the {target.support} ({px} px): "
                              + (f"{est.reason} {est.message}" if not est.found else f"{err:.3f} m off"))
    return dict(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="100-119", help="layout seeds: a range a-b or a comma list (dev seeds)")
    ap.add_argument("--looks", default="primitive,textured", help="looks to compare (services.sim.physics.LOOKS)")
    ap.add_argument("--show-misses", action="store_true", help="print every miss with the segmenter's reason")
    add_json_option(ap)
    args = ap.parse_args()
    seeds = _seeds(args.seeds)
    figures: dict[str, dict] = {}
    misses: list[str] = []
    for look in args.looks.split(","):
        per = measure(look, seeds, misses=misses)
        figures[look] = {name: {**c, "recall": c["detected"] / c["in_view"] if c["in_view"] else None}
                         for name, c in sorted(per.items())}
        tot = {k: sum(c[k] for c in per.values()) for k in ("in_view", "detected", "wrong_place", "missed")}
        figures[look]["all"] = {**tot, "recall": tot["detected"] / max(tot["in_view"], 1)}
    looks = list(figures)
    print(f"color segmenter, realistic camera, seeds {args.seeds}, 1-2 m: recall = detected within "
          f"{TOLERANCE * 100:.0f} cm / in view")
    print(f"{'class':15s}" + "".join(f"{look:>22s}" for look in looks))
    for name in [*OBJECTS, "all"]:
        cells = []
        for look in looks:
            c = figures[look].get(name)
            cells.append("-" if not c or not c["in_view"] else f"{c['detected']}/{c['in_view']} = {c['recall']:.2f}")
        print(f"{name:15s}" + "".join(f"{cell:>22s}" for cell in cells))
    if args.show_misses:
        print("\n".join(misses))
    write_json(args.json, "detection_recall", figures, args)


if __name__ == "__main__":
    main()
