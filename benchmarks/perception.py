"""Perception latency: per-request p50/p95 of localize_object and localize_placement at 640x480, for the
`sim` and `color` segmenters, in-process on one core and through the real service over Zenoh.

Usage: .venv/bin/python benchmarks/perception.py [--requests 60] [--no-bus] [--cpu 0]

Frames are the simulator's own renders (seeded layouts, camera aimed at objects and surfaces). In-process,
every request gets a fresh Frame, so JPEG decoding and segmentation are paid each time (the service caches
per frame; this is the worst case). Targets from issue 4: object p95 <= 60 ms, placement p95 <= 120 ms on
one core. Prints figures only; never fails on them. On a shared, loaded machine the figures are inflated:
the script prints the load average next to them.
"""

from __future__ import annotations

import argparse
import asyncio
import copy
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from aermani.launcher import free_port  # noqa: E402
from benchmarks._figures import add_json_option, pin_all_threads, write_json  # noqa: E402
from services.perception import query as q  # noqa: E402
from services.perception.pipeline import Perception  # noqa: E402
from services.perception.segmenters import make_segmenter  # noqa: E402
from services.perception.settings import PerceptionSettings  # noqa: E402
from shared.bus import Bus  # noqa: E402
from shared.errors import NoResponder  # noqa: E402
from shared.frames import base_to_camera  # noqa: E402
from shared.keys import Keys  # noqa: E402
from shared.messages import LocalizeRequest, Vec3  # noqa: E402
from shared.sensors import depth_message, raw16_message, transforms_message  # noqa: E402
from tests.perception.scenes import aim_at, layout, render_view  # noqa: E402

OBJECT_NAMES = ("red cup", "green bottle", "purple cup", "orange", "banana", "coke can", "tissue box")
HELD = Vec3(x=0.08, y=0.08, z=0.11)


def views(n: int, seed: int = 0):
    """(view, object query, surface query) triples: the camera aimed at an object, its surface in view."""
    rng = np.random.default_rng(seed)
    out = []
    s = seed
    while len(out) < n:
        world = layout(s)
        s += 1
        for e in world.objects:
            v = render_view(world, *aim_at(world, e.center, 1.1, rng))
            out.append((v, e.name, e.support))
    return out[:n]


def pct(xs: list[float], cpu: list[float] | None = None) -> str:
    a = np.array(xs) * 1000
    text = f"p50 {np.percentile(a, 50):6.1f} ms  p95 {np.percentile(a, 95):6.1f} ms"
    if cpu:
        c = np.array(cpu) * 1000
        text += f"  | CPU p50 {np.percentile(c, 50):6.1f} ms  p95 {np.percentile(c, 95):6.1f} ms"
    return text + f"  (n={len(a)})"


def p95s(prefix: str, wall: list[float], cpu: list[float] | None = None) -> dict[str, float]:
    """Figures of one series for --json: wall p50/p95 (and CPU p50/p95) in ms."""
    out = {f"{prefix}_p50_ms": float(np.percentile(wall, 50)) * 1e3,
           f"{prefix}_p95_ms": float(np.percentile(wall, 95)) * 1e3}
    if cpu:
        out |= {f"{prefix}_cpu_p50_ms": float(np.percentile(cpu, 50)) * 1e3,
                f"{prefix}_cpu_p95_ms": float(np.percentile(cpu, 95)) * 1e3}
    return out


def in_process(requests: int) -> dict[str, float]:
    figures: dict[str, float] = {}
    vs = views(min(requests, 24))
    for kind in ("sim", "color"):
        s = PerceptionSettings(segmenter=kind)
        p = Perception(make_segmenter(s), s)
        obj_t, place_t, obj_c, place_c = [], [], [], []
        for i in range(requests):
            v, name, surface = vs[i % len(vs)]
            if kind == "color" and name not in OBJECT_NAMES:
                name = "red cup"
            f = copy.copy(v.frame)  # new Frame: colour decoded again, segmenter cache missed
            f._rgb = None
            t, c = time.perf_counter(), time.process_time()
            p.localize_object(f, LocalizeRequest(query=name), q.parse(name))
            obj_t.append(time.perf_counter() - t)
            obj_c.append(time.process_time() - c)
            f = copy.copy(v.frame)
            f._rgb = None
            t, c = time.perf_counter(), time.process_time()
            p.localize_placement(f, LocalizeRequest(query=surface, object_size=HELD), q.parse(surface))
            place_t.append(time.perf_counter() - t)
            place_c.append(time.process_time() - c)
        print(f"in-process {kind:5s} localize_object    {pct(obj_t, obj_c)}")
        print(f"in-process {kind:5s} localize_placement {pct(place_t, place_c)}")
        figures |= p95s(f"inproc_{kind}_object", obj_t, obj_c) | p95s(f"inproc_{kind}_placement", place_t, place_c)
    return figures


async def over_bus(requests: int, cpu: int | None) -> dict[str, float]:
    figures: dict[str, float] = {}
    vs = views(6)
    keys = Keys("am1")
    for kind in ("sim", "color"):
        port = free_port()
        router = await Bus.open(mode="router", listen=[f"tcp/127.0.0.1:{port}"], connect=[])
        env = {**os.environ, "AERMANI_ZENOH_CONNECT": f"tcp/127.0.0.1:{port}", "AERMANI_PERCEPTION_SEGMENTER": kind,
               "AERMANI_PERCEPTION_DETECTIONS_HZ": "5", "AERMANI_LOG_LEVEL": "WARNING", "OMP_NUM_THREADS": "1"}
        pre = (lambda: os.sched_setaffinity(0, {cpu})) if cpu is not None else None
        proc = subprocess.Popen([sys.executable, "-m", "services.perception"], env=env, preexec_fn=pre,
                                cwd=Path(__file__).resolve().parent.parent)
        bus = await Bus.open(connect=[f"tcp/127.0.0.1:{port}"])
        stop = asyncio.Event()

        async def camera(bus: Bus = bus, stop: asyncio.Event = stop) -> None:
            # 5 Hz, like a slow camera: every frame gets a fresh stamp.
            i = 0
            while not stop.is_set():
                v = vs[(i // 10) % len(vs)][0].frame
                stamp = time.time_ns()
                from shared.sensors import CompressedImage, decode_proto, ns_to_stamp

                msg = decode_proto(CompressedImage, v.color_payload)
                msg.timestamp.CopyFrom(ns_to_stamp(stamp))
                bus.publish(keys.sim_labels, v.labels)
                bus.publish(keys.tf, transforms_message([("world", "base_link", v.world_from_camera
                                                          @ np.linalg.inv(base_to_camera())),
                                                         ("base_link", "camera", base_to_camera())], stamp))
                bus.publish(keys.camera_segmentation, raw16_message(v.segmentation, stamp))
                bus.publish(keys.camera_depth, depth_message(v.depth_mm, stamp))
                bus.publish(keys.camera_color, msg.SerializeToString())
                i += 1
                await asyncio.sleep(0.2)

        cam = asyncio.create_task(camera())
        cam.add_done_callback(lambda t: t.cancelled() or t.exception() is None or print(f"camera: {t.exception()!r}"))
        try:
            deadline = time.monotonic() + 120
            est = None
            while True:
                try:
                    est = await bus.query(keys.localize_object, LocalizeRequest(query="red cup"),
                                          timeout=10)
                    if est.reason not in ("no_frame",):
                        break
                except NoResponder:
                    pass
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise SystemExit(f"perception did not come up (exit code {proc.poll()}, last answer {est})")
                await asyncio.sleep(0.3)
            obj_t, place_t = [], []
            for i in range(requests):
                _, name, surface = vs[(i // 10) % len(vs)]
                if kind == "color" and name not in OBJECT_NAMES:
                    name = "red cup"
                t = time.perf_counter()
                await bus.query(keys.localize_object, LocalizeRequest(query=name), timeout=10)
                obj_t.append(time.perf_counter() - t)
                t = time.perf_counter()
                await bus.query(keys.localize_placement, LocalizeRequest(query=surface, object_size=HELD), timeout=10)
                place_t.append(time.perf_counter() - t)
                await asyncio.sleep(0.05)
            where = f"pinned to cpu {cpu}" if cpu is not None else "unpinned"
            print(f"zenoh {kind:5s} localize_object    {pct(obj_t)}  [service {where}, detections at 5 Hz]")
            print(f"zenoh {kind:5s} localize_placement {pct(place_t)}")
            figures |= p95s(f"zenoh_{kind}_object", obj_t) | p95s(f"zenoh_{kind}_placement", place_t)
        finally:
            stop.set()
            cam.cancel()
            proc.terminate()
            proc.wait(20)
            await bus.close()
            await router.close()
    return figures


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--requests", type=int, default=60)
    ap.add_argument("--no-process", action="store_true", help="only the figures through the service")
    ap.add_argument("--no-bus", action="store_true", help="only the in-process figures")
    ap.add_argument("--cpu", type=int, default=0, help="core to pin to (-1: no pinning)")
    add_json_option(ap)
    args = ap.parse_args()
    cpu = None if args.cpu < 0 else args.cpu
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; targets: object p95 <= 60 ms, "
          "placement p95 <= 120 ms on one core")
    figures: dict[str, float] = {}
    if cpu is not None:
        figures["pinned_threads"] = pin_all_threads(cpu)
        print(f"pinned {figures['pinned_threads']:.0f} threads of this process to cpu {cpu}")
    if not args.no_process:
        figures |= in_process(args.requests)
    if not args.no_bus:
        figures |= asyncio.run(over_bus(args.requests, cpu))
    write_json(args.json, "perception", figures, args)


if __name__ == "__main__":
    main()
