"""Contact sheet of the catalogue's objects, each on a table seen by the vehicle's camera from 1 m (docs/images).

Usage: .venv/bin/python scripts/object_sheet.py [--look textured] [--distance 1.0] [--out docs/images/objects.png]

Each tile is a 240 x 180 crop (shown at 1.5x) of the 640 x 480 frame the realistic camera renders, centred on the
object, with its name under it; the object stands alone on a table (white and wooden alternately).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from services.sim.layout import OBJECTS  # noqa: E402
from services.sim.physics import World  # noqa: E402
from services.sim.render import Renderer, snapshot_at  # noqa: E402
from services.sim.scenarios import _structure  # noqa: E402
from shared.frames import CAMERA_PITCH_DOWN, DEFAULT_INTRINSICS  # noqa: E402
from tests.perception.scenes import furniture, thing  # noqa: E402


def tile(renderer: Renderer, name: str, look: str, distance: float, i: int) -> np.ndarray:
    table = furniture("wooden table" if i % 2 else "table", 0.0, 0.0)
    world = World(entities=_structure() + [table, thing(name, 0.0, 0.0, table, yaw=0.5)], look=look,
                  version=10_000 + i)
    obj = world.by_name(name)
    bearing = 1.9 if name == "purple cup" else 2.6  # the mug shows its handle
    x, y = distance * math.cos(bearing), distance * math.sin(bearing)
    z = obj.center[2] + (distance - 0.12) * math.tan(CAMERA_PITCH_DOWN) + 0.05
    f = renderer.render(snapshot_at(world, np.array([x, y, z]), math.atan2(-y, -x)))
    cam = np.linalg.inv(f.camera_to_world)
    pc = cam[:3, :3] @ obj.center + cam[:3, 3]
    k = DEFAULT_INTRINSICS
    u, v = k.fx * pc[0] / pc[2] + k.cx, k.fy * pc[1] / pc[2] + k.cy
    u0, v0 = int(np.clip(u - 120, 0, k.width - 240)), int(np.clip(v - 90, 0, k.height - 180))
    img = cv2.cvtColor(f.rgb[v0:v0 + 180, u0:u0 + 240], cv2.COLOR_RGB2BGR)
    img = cv2.resize(img, (360, 270), interpolation=cv2.INTER_LINEAR)
    band = np.full((30, 360, 3), 30, np.uint8)
    cv2.putText(band, name, (10, 21), cv2.FONT_HERSHEY_SIMPLEX, 0.65, (240, 240, 240), 1, cv2.LINE_AA)
    return np.vstack([img, band])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--look", default="textured")
    ap.add_argument("--distance", type=float, default=1.0)
    ap.add_argument("--out", type=Path, default=Path("docs/images/objects.png"))
    args = ap.parse_args()
    renderer = Renderer(realism="realistic", seed=1)
    try:
        tiles = [tile(renderer, n, args.look, args.distance, i) for i, n in enumerate(OBJECTS)]
    finally:
        renderer.close()
    cols = 5
    while len(tiles) % cols:
        tiles.append(np.full_like(tiles[0], 30))
    sheet = np.vstack([np.hstack(tiles[i:i + cols]) for i in range(0, len(tiles), cols)])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), sheet)
    print(f"wrote {args.out} ({args.look} look, {args.distance} m)")


if __name__ == "__main__":
    main()
