"""Camera service throughput: a real camera process (file source, 640x480 colour + 16-bit depth PNGs) at a
requested frame rate; prints the rate that reaches a subscriber as colour/depth pairs with one stamp, the
stamp-to-receive latency (p50/p99, same machine clock) and what the service's health says.

    .venv/bin/python benchmarks/camera.py [--fps 30] [--seconds 8] [--width 640] [--height 480]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from aermani.launcher import Stack  # noqa: E402
from benchmarks._figures import add_json_option, write_json  # noqa: E402
from shared.bus import Bus  # noqa: E402
from shared.keys import Keys  # noqa: E402
from shared.sensors import CompressedImage, decode_proto, parse_depth, stamp_to_ns  # noqa: E402


def write_frames(folder: Path, n: int, w: int, h: int) -> None:
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:h, 0:w]
    for i in range(n):
        rgb = np.stack([(xx + i * 7) % 256, (yy + i * 3) % 256, (xx + yy) % 256], axis=-1).astype(np.uint8)
        rgb = np.clip(rgb.astype(np.int16) + rng.integers(-8, 8, rgb.shape), 0, 255).astype(np.uint8)
        depth = (1500 + 2 * yy + rng.integers(-5, 5, (h, w)) + i).astype(np.uint16)
        cv2.imwrite(str(folder / f"{i:04d}.png"), rgb)
        cv2.imwrite(str(folder / f"{i:04d}_depth.png"), depth)


async def measure(endpoint: str, seconds: float) -> dict:
    bus = await Bus.open(connect=[endpoint])
    k = Keys("am1")
    try:
        color, depth = bus.subscribe(k.camera_color, maxsize=1000), bus.subscribe(k.camera_depth, maxsize=1000)
        health = bus.subscribe(k.health("camera"))
        await color.recv(timeout=20)  # running
        colors: dict[int, int] = {}
        depths: set[int] = set()
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            with contextlib.suppress(TimeoutError):
                c = await color.recv(timeout=0.2)
                colors[stamp_to_ns(decode_proto(CompressedImage, c).timestamp)] = time.time_ns()
            while (d := depth.recv_nowait()) is not None:
                depths.add(parse_depth(d)[0])
        elapsed = time.monotonic() - t0
        paired = [s for s in colors if s in depths]
        lat = sorted((colors[s] - s) / 1e6 for s in colors)
        h = health.latest_nowait() or await health.recv(timeout=5)
        return {"pairs_per_s": len(paired) / elapsed, "colour_per_s": len(colors) / elapsed,
                "latency_ms_p50": lat[len(lat) // 2], "latency_ms_p99": lat[int(len(lat) * 0.99)],
                "health_ok": h.ok, "health_fps_5s": h.details.get("fps_5s"), "health_message": h.message}
    finally:
        await bus.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    add_json_option(ap)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "frames"
        folder.mkdir()
        write_frames(folder, 10, args.width, args.height)
        env = {"AERMANI_CAMERA_SOURCE": "file", "AERMANI_CAMERA_PATH": str(folder), "AERMANI_CAMERA_FPS": str(args.fps),
               "AERMANI_CAMERA_WIDTH": str(args.width), "AERMANI_CAMERA_HEIGHT": str(args.height)}
        stack = Stack(["camera"], env=env, log_dir=Path(tmp) / "logs", supervise=False)
        try:
            stack.start(wait=True, timeout=60)
            r = asyncio.run(measure(stack.endpoint, args.seconds))
        finally:
            stack.stop()
    print(f"camera service, file source {args.width}x{args.height} colour + depth, requested {args.fps:g} fps, "
          f"{args.seconds:g} s:")
    for key, value in r.items():
        print(f"  {key}: {value:.2f}" if isinstance(value, float) else f"  {key}: {value}")
    write_json(args.json, "camera", {**r, "requested_fps": args.fps}, args)


if __name__ == "__main__":
    main()
