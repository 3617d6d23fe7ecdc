"""Executor benchmark: abort-to-hold time during translations, p50/p95 (target p95 <= 200 ms for the ack).

Real processes: simulator, autopilot bridge and executor on an in-process router (MAVLink over UDP on
loopback). The vehicle takes off once; each trial starts a left/right translation, waits until the vehicle
moves, publishes `safety/abort`, and measures (a) Abort published -> AbortAck received and (b) Abort
published -> first vehicle state with speed below --still m/s. Figures are printed, never asserted.

    .venv/bin/python benchmarks/executor.py [--trials 20] [--speed-factor 1]
"""

from __future__ import annotations

import argparse
import asyncio
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from aermani.launcher import Stack, free_udp_port  # noqa: E402
from benchmarks._figures import add_json_option, write_json  # noqa: E402
from shared.bus import Bus  # noqa: E402
from shared.keys import Keys  # noqa: E402
from shared.messages import (  # noqa: E402
    Abort,
    SkillRequest,
    SkillState,
    SkillStatus,
    VehicleState,
)

KEYS = Keys("am1")


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.array(values), q)) if values else float("nan")


def speed(s: VehicleState) -> float:
    return math.sqrt(s.velocity.x ** 2 + s.velocity.y ** 2 + s.velocity.z ** 2)


async def run_skill(bus: Bus, statuses, skill: str, timeout: float = 90.0) -> SkillStatus:
    acc = await bus.query(KEYS.run_skill, SkillRequest(skill=skill), timeout=10)
    if not acc.accepted:
        raise RuntimeError(f"{skill} rejected: {acc.reason}")
    while True:
        st = await statuses.recv(timeout=timeout)
        if st.goal_id == acc.goal_id and st.state.terminal:
            return st


async def take_off(bus: Bus, statuses) -> None:
    """Run the takeoff skill until it succeeds; the bridge needs a moment to see the sim's heartbeats."""
    why = ""
    for _ in range(60):
        try:
            st = await run_skill(bus, statuses, "takeoff")
            if st.state == SkillState.SUCCEEDED:
                return
            why = st.message
        except RuntimeError as exc:
            why = str(exc)
        await asyncio.sleep(1.0)
    raise RuntimeError(f"takeoff failed: {why}")


async def abort_once(bus: Bus, acks, states, still: float) -> tuple[float, float]:
    """Publish an abort; -> (ms to its AbortAck, ms until the vehicle is slower than `still` m/s)."""
    abort = Abort(reason="benchmark", source="benchmark")
    t0 = time.time_ns()
    bus.publish(KEYS.abort, abort)
    got_ack = got_still = None
    while got_ack is None or got_still is None:
        if got_ack is None:
            try:
                rec = await acks.recv_sample(timeout=0.005)
                if rec.value.abort_stamp_ns == abort.stamp_ns:
                    got_ack = (rec.receive_ns - t0) / 1e6
            except TimeoutError:
                pass
        if got_still is None:
            try:
                rec = await states.recv_sample(timeout=0.005)
                if speed(rec.value) < still:
                    got_still = (rec.receive_ns - t0) / 1e6
            except TimeoutError:
                pass
        if (time.time_ns() - t0) > 10e9:
            raise RuntimeError("no ack or no stop within 10 s")
    return got_ack, got_still


async def bench(endpoint: str, trials: int, still: float) -> dict[str, float]:
    bus = await Bus.open(connect=[endpoint])
    statuses = bus.subscribe(KEYS.skill_status, maxsize=1000)
    states = bus.subscribe(KEYS.autopilot_state, maxsize=1000)
    acks = bus.subscribe(KEYS.abort_ack, maxsize=100)
    try:
        await take_off(bus, statuses)
        ack_ms: list[float] = []
        still_ms: list[float] = []
        for i in range(trials):
            skill = "left" if i % 2 == 0 else "right"
            acc = await bus.query(KEYS.run_skill, SkillRequest(skill=skill), timeout=10)
            if not acc.accepted:
                raise RuntimeError(f"{skill} rejected: {acc.reason}")
            while speed(await states.recv(timeout=10)) < 0.15:
                pass
            states.latest_nowait()
            got_ack, got_still = await abort_once(bus, acks, states, still)
            ack_ms.append(got_ack)
            still_ms.append(got_still)
            # drain the aborted status before the next trial
            while True:
                st = await statuses.recv(timeout=10)
                if st.goal_id == acc.goal_id and st.state.terminal:
                    break
            print(f"trial {i + 1:2d} {skill:5s}: ack {got_ack:7.1f} ms, speed<{still} m/s {got_still:7.1f} ms")
        print()
        print(f"abort -> AbortAck      p50 {pct(ack_ms, 50):7.1f} ms  p95 {pct(ack_ms, 95):7.1f} ms  "
              f"max {max(ack_ms):7.1f} ms  (target p95 <= 200 ms)")
        print(f"abort -> speed < {still} p50 {pct(still_ms, 50):7.1f} ms  p95 {pct(still_ms, 95):7.1f} ms  "
              f"max {max(still_ms):7.1f} ms  (mean {statistics.mean(still_ms):.1f} ms)")
        await run_skill(bus, statuses, "land")
        return {"ack_p50_ms": pct(ack_ms, 50), "ack_p95_ms": pct(ack_ms, 95), "ack_max_ms": max(ack_ms),
                "still_p50_ms": pct(still_ms, 50), "still_p95_ms": pct(still_ms, 95), "still_max_ms": max(still_ms),
                "trials": trials}
    finally:
        await bus.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--still", type=float, default=0.05, help="speed counted as stopped, m/s")
    ap.add_argument("--speed-factor", type=float, default=1.0, help="AERMANI_SIM_SPEED_FACTOR")
    add_json_option(ap)
    args = ap.parse_args()
    api = free_udp_port()
    env = {
        "AERMANI_SIM_API_PORT": str(api), "AERMANI_SIM_API_LOCAL_PORT": str(free_udp_port()),
        "AERMANI_SIM_GCS_PORT": str(free_udp_port()), "AERMANI_SIM_GCS_LOCAL_PORT": str(free_udp_port()),
        "AERMANI_AUTOPILOT_BRIDGE_CONNECTION": f"udpin:127.0.0.1:{api}",
        "AERMANI_SIM_SPEED_FACTOR": str(args.speed_factor),
        "AERMANI_EXECUTOR_TRANSLATION_SPEED": "0.3",  # slow steps leave time to abort mid-motion
    }
    with tempfile.TemporaryDirectory() as tmp:
        stack = Stack(["sim", "autopilot_bridge", "executor"], env=env, log_dir=Path(tmp) / "logs", supervise=False)
        stack.start(wait=True, timeout=120)
        try:
            figures = asyncio.run(bench(stack.endpoint, args.trials, args.still))
        finally:
            stack.stop()
    write_json(args.json, "executor", figures, args)


if __name__ == "__main__":
    main()
