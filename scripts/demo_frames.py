"""Render the default demo's camera frames (colour, and depth colour-mapped with a scale) to PNG files.

Usage: .venv/bin/python scripts/demo_frames.py [--out docs/images] [--realism realistic] [--seed 0] [--unit 0]
       [--command "pick up the red cup and place it on the table"]

The scenario is the one `make demo` runs (`aermani demo` with its defaults: layout seed 0, the command's target
and destination, realism `realistic`, camera unit 0). Two views, through the level's camera model
(services/sim/render.py):
- `ground`: the vehicle landed at its start pose (gear on the floor, the camera 0.2 m above it);
- `near`: at the flight altitude (1.5 m), 1 m from the target horizontally on the side it comes from, facing it.
Writes `demo_<view>_color.png` and `demo_<view>_depth.png` (turbo colour map from 0.2 m to 4 m with its scale,
black = no depth) under `--out`, colour quantized to an adaptive 256-colour palette so each file stays small.
Regenerate after the scene, the look or the camera model changes.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import services.sim  # noqa: E402, F401  (picks the headless OpenGL platform before MuJoCo loads)
from aermani.demo import scenario_for  # noqa: E402
from services.sim.layout import ROOM_HALF  # noqa: E402
from services.sim.physics import look_for  # noqa: E402
from services.sim.render import MIN_DEPTH_M, Renderer, snapshot_at  # noqa: E402
from services.sim.scenarios import generate  # noqa: E402

COMMAND = "pick up the red cup and place it on the table"
FAR_M = 4.0  # depth colour map range end
NEAR_DISTANCE_M = 1.0  # the `near` view: horizontal distance to the target
FLIGHT_ALTITUDE_M = 1.5  # the executor's flight_altitude (body origin above the floor's ground)


def depth_image(depth_mm: np.ndarray) -> np.ndarray:
    """Depth as a BGR image for viewing: turbo from MIN_DEPTH_M (blue) to FAR_M (red), no depth black, with a
    labelled scale bar on the right."""
    import cv2

    z = depth_mm.astype(np.float32) / 1000.0
    scaled = np.clip((z - MIN_DEPTH_M) / (FAR_M - MIN_DEPTH_M) * 255.0, 0, 255).astype(np.uint8)
    img = cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)
    img[depth_mm == 0] = 0
    h = img.shape[0]
    bar = np.full((h, 110, 3), 255, np.uint8)
    top, bottom = 30, h - 60
    ramp = np.linspace(255, 0, bottom - top).astype(np.uint8)[:, None]
    bar[top:bottom, 10:40] = cv2.applyColorMap(np.repeat(ramp, 30, axis=1), cv2.COLORMAP_TURBO)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for metres in (0.2, 1.0, 2.0, 3.0, 4.0):
        v = int(round(bottom - (metres - MIN_DEPTH_M) / (FAR_M - MIN_DEPTH_M) * (bottom - top)))
        v = min(max(v, top), bottom - 1)
        cv2.line(bar, (40, v), (46, v), (0, 0, 0), 1)
        cv2.putText(bar, f"{metres:.1f} m", (49, v + 5), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(bar, "depth", (10, 20), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.rectangle(bar, (10, h - 45), (40, h - 25), (0, 0, 0), -1)
    cv2.putText(bar, "none", (49, h - 30), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([img, bar], axis=1)


def near_pose(world, target: np.ndarray, start: np.ndarray) -> tuple[np.ndarray, float]:
    """A body pose NEAR_DISTANCE_M from `target` horizontally, on the side of `start` (turned until it is inside
    the room and clear of furniture), at the flight altitude, facing the target."""
    base = math.atan2(start[1] - target[1], start[0] - target[0])
    for k in (0, 1, -1, 2, -2, 3, -3, 4, -4, 5, -5, 6):
        ang = base + k * math.radians(30.0)
        x, y = target[0] + NEAR_DISTANCE_M * math.cos(ang), target[1] + NEAR_DISTANCE_M * math.sin(ang)
        inside = abs(x) < ROOM_HALF - 0.4 and abs(y) < ROOM_HALF - 0.4
        clear = all(not e.contains_xy(x, y, margin=-0.3) for e in world.entities if e.category == "furniture"
                    or e.category == "surface")
        if inside and clear:
            return np.array([x, y, FLIGHT_ALTITUDE_M]), math.atan2(target[1] - y, target[0] - x)
    raise SystemExit("no free viewpoint near the target")


def write_png(path: Path, rgb: np.ndarray) -> int:
    """An RGB image as a palette PNG (adaptive 256 colours: the camera's read noise makes true-colour PNGs of
    several hundred kB); returns the file's size."""
    from PIL import Image

    Image.fromarray(rgb).quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(
        path, optimize=True)
    return path.stat().st_size


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("docs/images"))
    ap.add_argument("--realism", default="realistic")
    ap.add_argument("--seed", type=int, default=0, help="layout seed (aermani demo's default 0)")
    ap.add_argument("--unit", type=int, default=0, help="camera unit (AERMANI_SIM_CAMERA_UNIT's default 0)")
    ap.add_argument("--command", default=COMMAND)
    a = ap.parse_args()
    import cv2

    scenario, _ = scenario_for(a.command, None, None, a.seed)
    world, filled, start = generate(scenario, light_variation=a.realism != "ideal", look=look_for(a.realism))
    target = world.by_name(filled.target_object or "")
    if target is None:
        raise SystemExit(f"layout {a.seed} has no target object")
    home = np.array([start.position.x, start.position.y, 0.0])
    near, near_yaw = near_pose(world, target.center, home)
    views = {"ground": (home, start.yaw), "near": (near, near_yaw)}
    a.out.mkdir(parents=True, exist_ok=True)
    camera = Renderer(realism=a.realism, seed=a.seed, unit=a.unit)
    try:
        for view, (position, heading) in views.items():
            f = camera.render(snapshot_at(world, position, heading))
            color = write_png(a.out / f"demo_{view}_color.png", f.rgb)
            depth = write_png(a.out / f"demo_{view}_depth.png", cv2.cvtColor(depth_image(f.depth_mm),
                                                                               cv2.COLOR_BGR2RGB))
            lower = f.depth_mm[f.depth_mm.shape[0] // 2:]
            print(f"{view}: body at ({position[0]:.2f}, {position[1]:.2f}, {position[2]:.2f}) yaw "
                  f"{math.degrees(heading):.0f} deg; {(f.depth_mm == 0).mean() * 100:.1f} % of pixels without depth "
                  f"({(lower == 0).mean() * 100:.1f} % of the lower half); PNGs {color // 1000} + {depth // 1000} kB")
    finally:
        camera.close()
    print(f"layout {a.seed}, {a.realism}, unit {a.unit}, target {target.name} at "
          f"({target.center[0]:.2f}, {target.center[1]:.2f}, {target.center[2]:.2f}): PNGs in {a.out}")


if __name__ == "__main__":
    main()
