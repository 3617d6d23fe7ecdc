"""Link and log budget (issue 31): what crosses the drone-to-ground link and what the log grows by, at default
settings, with a task loop running.

Real processes at default settings (simulator at real time, `realistic`, its 15 fps camera; autopilot bridge,
perception with the colour segmenter, executor, reasoner with the `rules` baseline, recorder), deployed as in
the field: a ground and a drone router linked by mutual TLS (`aermani up --secure`, the compose routers'
templates in shared/routers/), the vehicle's services on the drone router, reasoner and recorder on the
ground's. Back-to-back pick-and-place tasks run for --minutes while a client on the ground router subscribed
to `aermani/**` counts every sample's bytes by key. The ground's recorder subscribes `aermani/**` too, so
every sample a drone-side service publishes crosses the link once (Zenoh sends one copy per link, however
many subscribers the far side has), as the drone router's rules let it (depth at 1 Hz): the count is the
link's payload rate (ground-side messages, a few kB/s, are in it; Zenoh's framing and TLS, a few bytes per
sample, are not). The log rate is the recorder's MCAP bytes over the same window (zstd chunks), extrapolated
to one hour. A second client on the drone router counts depth as the vehicle gets it, for what raw 16UC1
depth (and unthinned PNG depth) would have cost the link.

    .venv/bin/python benchmarks/link_budget.py [--minutes 3] [--out runs/bench/link] [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from aermani.launcher import Stack, loopback_mavlink_env  # noqa: E402
from benchmarks._figures import add_json_option, write_json  # noqa: E402
from benchmarks.soak import COMMANDS, SERVICES  # noqa: E402
from shared.bus import Bus  # noqa: E402
from shared.errors import DecodeError  # noqa: E402
from shared.keys import Keys  # noqa: E402
from shared.messages import Scenario, TaskRequest  # noqa: E402
from shared.security import init_certs  # noqa: E402
from shared.sensors import parse_depth  # noqa: E402
from shared.tasks import follow_task  # noqa: E402

MB = 1e6


def key_group(key: str) -> str:
    """`aermani/v1/am1/camera/depth` -> `camera/depth`; health and heartbeats of every service as one row."""
    rest = key.split("/", 3)[3] if key.count("/") >= 3 else key
    for group in ("health/", "heartbeat/", "alive/"):
        if rest.startswith(group):
            return group + "*"
    return rest


def log_bytes(out: Path) -> int:
    return sum(f.stat().st_size for f in (out / "recordings").glob("*.mcap"))


async def tasks(bus: Bus, keys: Keys, until: float) -> tuple[int, int]:
    done = run = 0
    seed = 2000
    while time.monotonic() < until:
        seed += 1
        obj, dest = COMMANDS[seed % len(COMMANDS)]
        res = await bus.query(keys.sim_reset, Scenario(seed=seed, target_object=obj, destination=dest), timeout=60)
        if not res.ok:
            continue
        await asyncio.sleep(2.0)
        req = TaskRequest(command=f"Pick up the {obj} and place it on the {dest}.", takeoff=True, t_max_s=300)
        left = max(30.0, until - time.monotonic() + 60)
        try:
            followed = await follow_task(bus, keys, req, timeout=left, ready_timeout=60, retry_rejected_s=30)
        except TimeoutError:
            break
        run += 1
        done += int(followed.final is not None and followed.final.state.value == "succeeded")
        print(f"  task {run}: {followed.final.state.value if followed.final else 'no end'}", flush=True)
    return done, run


async def measure(stack: Stack, out: Path, minutes: float, warmup_s: float, certs: Path) -> dict[str, object]:
    keys = Keys("am1")
    # the routers are mutual-TLS (the deployed default): this benchmark joins as a client of the deployment
    bus = await Bus.open(connect=[stack.endpoint], certs=str(certs), identity="client")  # the ground router
    sub = bus.subscribe("aermani/**", maxsize=5000, overflow="drop_oldest")
    # the vehicle's side, every depth frame
    onboard = await Bus.open(connect=[stack.drone_endpoint], certs=str(certs), identity="client")
    onboard_depth = onboard.subscribe(keys.camera_depth, maxsize=100, overflow="drop_oldest")
    depth_onboard = {"png": 0, "raw": 0}
    by_key: collections.Counter[str] = collections.Counter()
    count: collections.Counter[str] = collections.Counter()
    counting = False

    async def tally() -> None:
        while True:
            rec = await sub.recv_sample()
            if not counting:
                continue
            g = key_group(rec.key)
            by_key[g] += len(rec.payload)
            count[g] += 1

    async def tally_onboard() -> None:
        while True:
            rec = await onboard_depth.recv_sample()
            if not counting:
                continue
            depth_onboard["png"] += len(rec.payload)
            with contextlib.suppress(DecodeError):
                depth_onboard["raw"] += parse_depth(rec.payload)[1].nbytes + 40  # + RawImage's header fields

    counter = asyncio.create_task(tally())
    counter_onboard = asyncio.create_task(tally_onboard())
    end = time.monotonic() + warmup_s + minutes * 60
    runner = asyncio.create_task(tasks(bus, keys, end))
    try:
        await asyncio.sleep(warmup_s)  # the first take-off's start-up is not the steady state
        counting, t0, log0 = True, time.monotonic(), log_bytes(out)
        print(f"counting for {minutes:.1f} min ...", flush=True)
        while time.monotonic() < end:
            await asyncio.sleep(min(10.0, max(0.0, end - time.monotonic())))
            el = time.monotonic() - t0
            print(f"  {el:5.0f} s: link {sum(by_key.values()) / el / MB:.2f} MB/s, "
                  f"log {(log_bytes(out) - log0) / el / MB:.2f} MB/s", flush=True)
        counting = False
        elapsed = time.monotonic() - t0
        log_growth = log_bytes(out) - log0
        runner.cancel()
        done_run = await asyncio.gather(runner, return_exceptions=True)
    finally:
        counter.cancel()
        counter_onboard.cancel()
        await bus.close()
        await onboard.close()
    done, run = done_run[0] if isinstance(done_run[0], tuple) else (0, 0)
    total = sum(by_key.values())
    rows = {g: {"mb_per_s": n / elapsed / MB, "samples_per_s": count[g] / elapsed,
                "bytes_per_sample": n / max(1, count[g])} for g, n in by_key.most_common()}
    unthinned = total - by_key["camera/depth"] + depth_onboard["png"]
    raw_total = total - by_key["camera/depth"] + depth_onboard["raw"]
    figures = {
        "minutes": elapsed / 60, "tasks_run": run, "tasks_succeeded": done,
        "link_mb_per_s": total / elapsed / MB,
        "link_mb_per_s_every_depth_frame": unthinned / elapsed / MB,
        "link_mb_per_s_with_raw_depth": raw_total / elapsed / MB,
        "depth_mb_per_s": by_key["camera/depth"] / elapsed / MB,
        "depth_onboard_mb_per_s": depth_onboard["png"] / elapsed / MB,
        "depth_raw_mb_per_s": depth_onboard["raw"] / elapsed / MB,
        "depth_ratio": depth_onboard["raw"] / depth_onboard["png"] if depth_onboard["png"] else None,
        "log_mb_per_s": log_growth / elapsed / MB,
        "log_gb_per_hour": log_growth / elapsed * 3600 / 1e9,
        "by_key": rows,
    }
    print(f"\nover {elapsed:.0f} s with {run} tasks ({done} succeeded), default settings, no segmentation recorded:")
    print(f"{'key':32s} {'MB/s':>8s} {'samples/s':>10s} {'bytes/sample':>13s}")
    for g, r in list(rows.items())[:14]:
        print(f"{g:32s} {r['mb_per_s']:8.3f} {r['samples_per_s']:10.1f} {r['bytes_per_sample']:13.0f}")
    print(f"link (every sample on aermani/** at the ground router): {figures['link_mb_per_s']:.2f} MB/s (limit "
          f"2 MB/s); with every depth frame it would be {figures['link_mb_per_s_every_depth_frame']:.2f} MB/s, with "
          f"raw 16UC1 depth {figures['link_mb_per_s_with_raw_depth']:.2f} MB/s (depth PNG "
          f"{figures['depth_ratio'] or 0:.1f}x smaller than raw)")
    print(f"log: {figures['log_mb_per_s']:.2f} MB/s = {figures['log_gb_per_hour']:.2f} GB per hour (limit 2 GB)")
    return figures


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=3.0, help="counting window (after the warm-up)")
    ap.add_argument("--warmup", type=float, default=20.0, help="seconds before counting starts")
    ap.add_argument("--out", default="runs/bench/link")
    add_json_option(ap)
    args = ap.parse_args()
    out = Path(args.out)
    # Only what the processes need to find each other on this machine; everything else at its default.
    env = loopback_mavlink_env({"AERMANI_REASONER_BACKEND": "rules",
                                "AERMANI_RECORDER_OUT_DIR": str(out / "recordings")})
    print(f"link and log budget: {', '.join(SERVICES)} at default settings (backend rules: a non-VLM baseline)")
    certs = out / "certs"
    if not (certs / "ca.pem").exists():
        init_certs(certs)
    with Stack(SERVICES, env=env, log_dir=out / "logs", secure=certs) as stack:
        figures = asyncio.run(measure(stack, out, args.minutes, args.warmup, certs))
    write_json(args.json or out / "link.json", "link_budget", figures, args)


if __name__ == "__main__":
    main()
