"""Bus benchmark: latency (p50/p99) and throughput through shared.bus vs raw zenoh-python, same run.

Two client sessions through an in-process router on loopback, like the services. Payloads: a 1 KiB JSON
message, and a 640x480 colour (JPEG) + depth (16UC1) frame pair in Foxglove protobuf. Latency is a
ping: publish, wait until the subscriber has it, repeat. Throughput: a burst, until all arrived.

    .venv/bin/python benchmarks/bus.py [--n 300]
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from aermani.launcher import free_port, open_router  # noqa: E402
from benchmarks._figures import add_json_option, write_json  # noqa: E402
from shared.bus import Bus, zenoh_config  # noqa: E402
from shared.keys import Protobuf, Topic  # noqa: E402
from shared.messages import Health  # noqa: E402
from shared.sensors import color_message, raw16_message  # noqa: E402


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.array(values), q))


def make_frames() -> tuple[bytes, bytes]:
    rng = np.random.default_rng(0)
    # A plausible rendered scene: smooth gradients + noise compress like a real camera image.
    yy, xx = np.mgrid[0:480, 0:640]
    rgb = np.stack([(xx / 640 * 255), (yy / 480 * 255), ((xx + yy) / 1120 * 255)], -1)
    rgb = (rgb + rng.normal(0, 6, rgb.shape)).clip(0, 255).astype(np.uint8)
    depth = (1500 + 400 * np.sin(xx / 50) + rng.normal(0, 5, xx.shape)).astype(np.uint16)
    now = time.time_ns()
    return color_message(rgb, now), raw16_message(depth, now)


def json_payload() -> Health:
    return Health(service="bench", ok=True, message="x" * 880, details={"seq": 0})


# ------------------------------------------------------------------ raw zenoh


def raw_bench(endpoint: str, payloads: list[tuple[str, bytes]], n: int) -> tuple[list[float], float]:
    """Latency samples (s) and burst throughput (sets/s) for a set of payloads published together."""
    pub_s = zenoh.open(zenoh_config(mode="client", connect=[endpoint]))
    sub_s = zenoh.open(zenoh_config(mode="client", connect=[endpoint]))
    count = 0
    cond = threading.Condition()

    def on_sample(sample: zenoh.Sample) -> None:
        nonlocal count
        sample.payload.to_bytes()
        with cond:
            count += 1
            cond.notify_all()

    subs = [sub_s.declare_subscriber(key, on_sample) for key, _ in payloads]
    pubs = [pub_s.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK) for key, _ in payloads]
    time.sleep(0.5)
    lat = []
    for _ in range(n):
        with cond:
            target = count + len(payloads)
        t0 = time.perf_counter()
        for pub, (_, data) in zip(pubs, payloads, strict=True):
            pub.put(data)
        with cond:
            cond.wait_for(lambda t=target: count >= t, timeout=5)
        lat.append(time.perf_counter() - t0)
    with cond:
        target = count + n * len(payloads)
    t0 = time.perf_counter()
    for _ in range(n):
        for pub, (_, data) in zip(pubs, payloads, strict=True):
            pub.put(data)
    with cond:
        cond.wait_for(lambda: count >= target, timeout=60)
    rate = n / (time.perf_counter() - t0)
    for x in (*subs, *pubs):
        x.undeclare()
    pub_s.close()
    sub_s.close()
    return lat, rate


# ------------------------------------------------------------------ wrapper


async def wrapper_bench(endpoint: str, payloads: list[tuple[str, object, object]], n: int
                        ) -> tuple[list[float], float]:
    """Through the typed bus as services use it: declared topics, decoded to their declared type."""
    a = await Bus.open(connect=[endpoint])
    b = await Bus.open(connect=[endpoint])
    topics = [Topic(name, t, "benchmark", "benchmark").bind("bench") for name, _obj, t in payloads]
    subs = [b.subscribe(topic, maxsize=4 * n) for topic in topics]
    payloads = [(topic, obj, None) for topic, (_name, obj, _t) in zip(topics, payloads, strict=True)]
    await asyncio.sleep(0.5)
    lat = []
    for _ in range(n):
        t0 = time.perf_counter()
        for topic, obj, _ in payloads:
            a.publish(topic, obj)
        for s in subs:
            await s.recv(timeout=5)
        lat.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    for _ in range(n):
        for topic, obj, _ in payloads:
            a.publish(topic, obj)
    for s in subs:
        for _ in range(n):
            await s.recv(timeout=30)
    rate = n / (time.perf_counter() - t0)
    dropped = sum(s.dropped for s in subs)
    await a.close()
    await b.close()
    if dropped:
        print(f"  (wrapper dropped {dropped} samples)")
    return lat, rate


def report(name: str, raw: tuple[list[float], float], wrapped: tuple[list[float], float], unit: str
           ) -> dict[str, float]:
    rl, rr = raw
    wl, wr = wrapped
    print(f"{name}")
    print(f"  raw zenoh : p50 {pct(rl, 50) * 1e3:7.3f} ms  p99 {pct(rl, 99) * 1e3:7.3f} ms  "
          f"throughput {rr:9.1f} {unit}/s")
    print(f"  aermani   : p50 {pct(wl, 50) * 1e3:7.3f} ms  p99 {pct(wl, 99) * 1e3:7.3f} ms  "
          f"throughput {wr:9.1f} {unit}/s")
    print(f"  ratio wrapper/raw: latency p50 {pct(wl, 50) / pct(rl, 50):.2f}  p99 {pct(wl, 99) / pct(rl, 99):.2f}  "
          f"throughput {rr / wr:.2f} (raw/wrapper time per item)")
    return {"raw_p50_ms": pct(rl, 50) * 1e3, "raw_p99_ms": pct(rl, 99) * 1e3, "p50_ms": pct(wl, 50) * 1e3,
            "p99_ms": pct(wl, 99) * 1e3, "raw_rate": rr, "rate": wr}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=300, help="messages per measurement")
    add_json_option(ap)
    args = ap.parse_args()
    port = free_port()
    router = open_router(port)
    endpoint = f"tcp/127.0.0.1:{port}"
    try:
        msg = json_payload()
        data = msg.model_dump_json().encode()
        print(f"JSON message: {len(data)} B; ", end="")
        color, depth = make_frames()
        print(f"frame pair: colour JPEG {len(color) / 1024:.0f} KiB + depth {len(depth) / 1024:.0f} KiB; n={args.n}")
        raw_j = raw_bench(endpoint, [("bench/raw/json", data)], args.n)
        wr_j = asyncio.run(wrapper_bench(endpoint, [("wr/json", msg, Health)], args.n))
        figures = {"json": report("1 KiB JSON message", raw_j, wr_j, "msg")}
        raw_f = raw_bench(endpoint, [("bench/raw/color", color), ("bench/raw/depth", depth)], args.n)
        wr_f = asyncio.run(wrapper_bench(endpoint, [("wr/color", color, Protobuf("foxglove.CompressedImage")),
                                                    ("wr/depth", depth, Protobuf("foxglove.RawImage"))], args.n))
        figures["frame"] = report("640x480 colour+depth frame pair", raw_f, wr_f, "pairs")
        frame_ratio = statistics.median(wr_f[0]) / statistics.median(raw_f[0])
        print(f"targets (issue 12): wrapper/raw latency p50 <= 1.2 and throughput <= 1.5 for both payloads (frame p50 "
              f"ratio {frame_ratio:.2f}); issue 2: p99 frame latency <= 5 ms (got {pct(wr_f[0], 99) * 1e3:.2f} ms)")
        write_json(args.json, "bus", figures, args, json_bytes=len(data), color_bytes=len(color),
                   depth_bytes=len(depth))
    finally:
        router.close()


if __name__ == "__main__":
    main()
