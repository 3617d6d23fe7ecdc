"""Recorder throughput: a real recorder process records camera frames published at a multiple of the demo
rate (demo: 15 fps colour + depth + segmentation at 640x480) plus vehicle state; prints sustained write
throughput (messages/s, MB/s) and drops. Target: zero drops at 3x.

    .venv/bin/python benchmarks/recorder.py [--seconds 10] [--rate-mult 3] [--chunk-kib 1024]
"""

from __future__ import annotations

import argparse
import asyncio
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from aermani.launcher import Stack  # noqa: E402
from benchmarks._figures import add_json_option, write_json  # noqa: E402
from shared.bus import Bus  # noqa: E402
from shared.keys import Keys  # noqa: E402
from shared.messages import VehicleState  # noqa: E402
from shared.sensors import color_message, depth_message, encode_depth_png, encode_jpeg, raw16_message  # noqa: E402

DEMO_FPS = 15.0


def scene(n: int, w: int, h: int) -> list[tuple[bytes, np.ndarray, np.ndarray]]:
    """n distinct frames that compress like real ones: smooth depth with noise, blocky segmentation."""
    rng = np.random.default_rng(0)
    out = []
    yy, xx = np.mgrid[0:h, 0:w]
    for i in range(n):
        rgb = np.stack([(xx + i * 7) % 256, (yy + i * 3) % 256, (xx + yy) % 256], axis=-1).astype(np.uint8)
        rgb = np.clip(rgb.astype(np.int16) + rng.integers(-8, 8, rgb.shape), 0, 255).astype(np.uint8)
        depth = (1500 + 2 * yy + rng.integers(-5, 5, (h, w)) + i).astype(np.uint16)
        seg = np.zeros((h, w), np.uint16)
        seg[h // 3: h // 2, w // 3: w // 2] = 1
        seg[2 * h // 3:, :] = 2
        out.append((encode_jpeg(rgb), encode_depth_png(depth), seg))
    return out


async def publish(bus: Bus, keys: Keys, seconds: float, fps: float, frames) -> tuple[dict[str, int], int, float]:
    """Messages published per key, bytes of frames, seconds."""
    per_key: dict[str, int] = {}
    nbytes = 0
    t0 = time.monotonic()
    n = 0
    while time.monotonic() - t0 < seconds:
        jpeg, depth, seg = frames[n % len(frames)]
        stamp = time.time_ns()
        for key, data in (
            (keys.camera_color, color_message(None, stamp, jpeg=jpeg)),  # type: ignore[arg-type]
            (keys.camera_depth, depth_message(None, stamp, png=depth)),
            (keys.camera_segmentation, raw16_message(seg, stamp)),
        ):
            bus.publish(key, data)
            per_key[key.key] = per_key.get(key.key, 0) + 1
            nbytes += len(data)
        if n % 3 == 0:  # vehicle state beside the frames (~15 Hz at 3x)
            data = VehicleState(stamp_ns=stamp)
            bus.publish(keys.autopilot_state, data)
            per_key[keys.autopilot_state.key] = per_key.get(keys.autopilot_state.key, 0) + 1
        n += 1
        await asyncio.sleep(max(0.0, t0 + n / fps - time.monotonic()))
    return per_key, nbytes, time.monotonic() - t0


def recorded(files: list[Path], keys: Keys) -> dict[str, int]:
    """Messages of each of the benchmark's keys in the recording (the recorder's own health is left out)."""
    from mcap.reader import make_reader

    wanted = {keys.camera_color.key, keys.camera_depth.key, keys.camera_segmentation.key, keys.autopilot_state.key}
    n = dict.fromkeys(sorted(wanted), 0)
    for f in files:
        with f.open("rb") as fh:
            summary = make_reader(fh).get_summary()
        counts = summary.statistics.channel_message_counts
        for cid, ch in summary.channels.items():
            if ch.topic in wanted:
                n[ch.topic] += counts.get(cid, 0)
    return n


async def main_async(args: argparse.Namespace) -> None:
    keys = Keys("am1")
    out = Path(args.out or tempfile.mkdtemp(prefix="aermani-bench-"))
    env = {"AERMANI_RECORDER_OUT_DIR": str(out), "AERMANI_RECORDER_CHUNK_SIZE": str(args.chunk_kib * 1024),
           "AERMANI_RECORDER_HEALTH_PERIOD_S": "0.5", "AERMANI_LOG_LEVEL": "WARNING",
           # every frame and the oracle's masks too: the heaviest recording there is
           "AERMANI_RECORDER_SEGMENTATION": "1", "AERMANI_RECORDER_FRAME_MAX_HZ": "0"}
    frames = scene(8, args.width, args.height)
    stack = Stack(["recorder"], env=env, log_dir=out / "logs", supervise=False)
    stack.start(wait=True)
    try:
        bus = await Bus.open(connect=[stack.endpoint])
        health = bus.subscribe(keys.health("recorder"), maxsize=100)
        await health.recv(timeout=60)
        fps = DEMO_FPS * args.rate_mult
        print(f"publishing {args.width}x{args.height} colour+depth+segmentation at {fps:.0f} fps "
              f"({args.rate_mult:g}x demo) + state for {args.seconds:.0f} s into {out}")
        sent_by_key, nbytes, pub_s = await publish(bus, keys, args.seconds, fps, frames)
        sent = sum(sent_by_key.values())
        t_pub_end = time.monotonic()
        # Drained when the writer has caught up with everything the recorder received. What it received counts
        # its own health messages too, so the counts can match while a frame is still on its way: the stop waits
        # for two more drained health reports (a second) before it ends the recording.
        settled, drain_s = 0, 0.0
        while settled < 3:
            d = (await health.recv(timeout=60)).details
            drained = d["received"] >= sent and d["written"] + d["lost_on_error"] >= d["received"]
            settled = settled + 1 if drained and not d["backlog_bytes"] else 0
            if settled == 1:
                drain_s = time.monotonic() - t_pub_end
        max_backlog = d["backlog_bytes"]
        await bus.close()
    finally:
        stack.stop(timeout=60)
    files = sorted(out.glob("*.mcap"))
    written_by_key = recorded(files, keys)
    written = sum(written_by_key.values())
    missing_by_key = {k.split("/", 3)[3]: sent_by_key.get(k, 0) - n for k, n in written_by_key.items()}
    not_written = d["received"] - d["written"] - d["lost_on_error"]
    total_s = pub_s + drain_s
    file_mb = sum(f.stat().st_size for f in files) / 1e6
    dropped = d["dropped"]
    print(f"published     {sent} messages, {nbytes / 1e6:.1f} MB of frames in {pub_s:.1f} s "
          f"({sent / pub_s:.0f} msg/s, {nbytes / 1e6 / pub_s:.1f} MB/s offered)")
    print(f"recorded      {written} messages: {written / total_s:.0f} msg/s, {nbytes / 1e6 / total_s:.1f} MB/s "
          f"sustained (writer drained {drain_s:.1f} s after the publishers stopped; backlog then {max_backlog} B)")
    print(f"dropped       {dropped} (bus queue {d.get('bus_dropped', 0)}, writer backlog "
          f"{dropped - d.get('bus_dropped', 0)}), lost to write errors {d['lost_on_error']}, "
          f"missing {sent - written} of {sent} (" + ", ".join(f"{k} {v}" for k, v in missing_by_key.items())
          + f"); received by the recorder but not written {not_written}")
    compression = nbytes / 1e6 / max(file_mb, 1e-9)
    print(f"file size     {file_mb:.1f} MB in {len(files)} file(s), compression {compression:.1f}x")
    print(f"target zero drops at {args.rate_mult:g}x:", "MET" if dropped == 0 and sent == written else "NOT MET")
    write_json(args.json, "recorder", {
        "offered_fps": fps, "sent": sent, "written": written, "dropped": dropped,
        "missing": sent - written, "missing_by_key": missing_by_key,
        "not_written_of_received": not_written,
        "lost_on_error": d["lost_on_error"], "msg_per_s": written / total_s, "mb_per_s": nbytes / 1e6 / total_s,
        "drain_s": drain_s, "file_mb": file_mb, "compression": compression}, args)
    if args.out is None:
        shutil.rmtree(out, ignore_errors=True)  # a temp recording of ~100 MB is not worth keeping


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--rate-mult", type=float, default=3.0, help="multiple of the 15 fps demo rate")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--chunk-kib", type=int, default=1024)
    p.add_argument("--out", default=None, help="keep the recording in this directory (default: a temp dir, deleted)")
    add_json_option(p)
    asyncio.run(main_async(p.parse_args()))


if __name__ == "__main__":
    main()
