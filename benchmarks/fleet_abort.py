"""Fleet-wide abort benchmark: one publication on `aermani/v1/fleet/safety/abort` while three simulated
vehicles translate; how long until every vehicle holds. Target: all holding within 100 ms p95.

Real processes: for each of three vehicle ids a simulator, an autopilot bridge and an executor, on one
in-process router (MAVLink over UDP on loopback, like the evaluation's parallel vehicles). Each trial starts
a left/right translation on every vehicle, waits until all move, publishes ONE fleet abort, and measures per
vehicle (a) abort -> the executor's AbortAck (hold commanded and accepted by the bridge) and (b) abort -> the
first state with speed below --still m/s. A trial's figure is the slowest vehicle's. Printed, never asserted.

    .venv/bin/python benchmarks/fleet_abort.py [--trials 15] [--vehicles 3]
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from aermani.launcher import Stack, free_udp_port  # noqa: E402
from benchmarks._figures import add_json_option, write_json  # noqa: E402
from shared.action import skill_client  # noqa: E402
from shared.bus import Bus, Subscription  # noqa: E402
from shared.keys import FLEET_ABORT, Keys  # noqa: E402
from shared.messages import Abort, AbortAck, SkillRequest, SkillState, VehicleState  # noqa: E402


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.array(values), q)) if values else float("nan")


def speed(s: VehicleState) -> float:
    return math.sqrt(s.velocity.x ** 2 + s.velocity.y ** 2 + s.velocity.z ** 2)


def vehicle_env() -> dict[str, str]:
    api = free_udp_port()
    return {"AERMANI_SIM_API_PORT": str(api), "AERMANI_SIM_API_LOCAL_PORT": str(free_udp_port()),
            "AERMANI_SIM_GCS_PORT": str(free_udp_port()), "AERMANI_SIM_GCS_LOCAL_PORT": str(free_udp_port()),
            "AERMANI_AUTOPILOT_BRIDGE_CONNECTION": f"udpin:127.0.0.1:{api}",
            "AERMANI_EXECUTOR_TRANSLATION_SPEED": "0.3"}  # slow steps leave time to abort mid-motion


async def takeoff(bus: Bus, vid: str) -> None:
    async with skill_client(bus, vid) as skills:
        why = ""
        for _ in range(60):  # the bridge needs a moment to see the simulator's heartbeats
            goal = await skills.send_goal(SkillRequest(skill="takeoff"), ready_timeout=30)
            st = await goal.result(120) if goal.accepted else None
            if st is not None and st.state is SkillState.SUCCEEDED:
                return
            why = st.message if st is not None else goal.reason
            await asyncio.sleep(1.0)
        raise RuntimeError(f"{vid}: takeoff failed: {why}")


async def first(sub: Subscription, pred, t0: int, timeout: float = 10.0) -> float:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        rec = await sub.recv_sample(timeout=max(0.01, deadline - time.monotonic()))
        if pred(rec.value):
            return (rec.receive_ns - t0) / 1e6
    raise RuntimeError("no answer within 10 s")


async def bench(endpoint: str, vehicles: list[str], trials: int, still: float) -> dict[str, float]:
    bus = await Bus.open(connect=[endpoint])
    states = {v: bus.subscribe(Keys(v).autopilot_state, maxsize=1000) for v in vehicles}
    acks = {v: bus.subscribe(Keys(v).abort_ack, maxsize=100) for v in vehicles}
    clients = {v: skill_client(bus, v) for v in vehicles}
    try:
        await asyncio.gather(*(takeoff(bus, v) for v in vehicles))
        print(f"{len(vehicles)} vehicles airborne")
        ack_ms: list[float] = []
        still_ms: list[float] = []
        for i in range(trials):
            skill = "left" if i % 2 == 0 else "right"
            goals = [await clients[v].send_goal(SkillRequest(skill=skill)) for v in vehicles]
            if not all(g.accepted for g in goals):
                raise RuntimeError(f"{skill} rejected: {[g.reason for g in goals]}")
            for v in vehicles:
                while speed(await states[v].recv(timeout=10)) < 0.15:
                    pass
                states[v].latest_nowait()
            abort = Abort(reason="fleet benchmark", source="benchmark")
            t0 = time.time_ns()
            bus.publish(FLEET_ABORT, abort)
            stamp = abort.stamp_ns

            def acked(a: object, stamp: int = stamp) -> bool:
                return isinstance(a, AbortAck) and a.abort_stamp_ns == stamp

            per_ack = await asyncio.gather(*(first(acks[v], acked, t0) for v in vehicles))
            per_still = await asyncio.gather(*(first(states[v], lambda s: speed(s) < still, t0) for v in vehicles))
            ack_ms.append(max(per_ack))
            still_ms.append(max(per_still))
            for g in goals:
                await g.result(10)
                g.close()
            print(f"trial {i + 1:2d}: all acknowledged {max(per_ack):6.1f} ms (per vehicle "
                  f"{', '.join(f'{x:.0f}' for x in per_ack)}), all below {still} m/s {max(per_still):6.1f} ms")
        print()
        print(f"fleet abort -> every AbortAck    p50 {pct(ack_ms, 50):6.1f} ms  p95 {pct(ack_ms, 95):6.1f} ms  "
              f"max {max(ack_ms):6.1f} ms  (target p95 <= 100 ms; {len(vehicles)} vehicles, {trials} trials)")
        print(f"fleet abort -> every speed<{still} p50 {pct(still_ms, 50):6.1f} ms  p95 {pct(still_ms, 95):6.1f} ms  "
              f"max {max(still_ms):6.1f} ms  (includes braking from 0.3 m/s)")
        return {"ack_p50_ms": pct(ack_ms, 50), "ack_p95_ms": pct(ack_ms, 95), "ack_max_ms": max(ack_ms),
                "still_p50_ms": pct(still_ms, 50), "still_p95_ms": pct(still_ms, 95), "still_max_ms": max(still_ms),
                "trials": trials, "vehicles": len(vehicles)}
    finally:
        for c in clients.values():
            await c.close()
        await bus.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=15)
    ap.add_argument("--vehicles", type=int, default=3)
    ap.add_argument("--still", type=float, default=0.05, help="speed counted as stopped, m/s")
    add_json_option(ap)
    args = ap.parse_args()
    vehicles = [f"fa{i + 1}" for i in range(args.vehicles)]
    services = ["sim", "autopilot_bridge", "executor"]
    with tempfile.TemporaryDirectory() as tmp:
        stack = Stack(services, vehicle_id=vehicles[0], env=vehicle_env(), log_dir=Path(tmp) / "logs",
                      supervise=False)
        for v in vehicles[1:]:
            stack.add_vehicle(v, services, vehicle_env())
        stack.start(wait=True, timeout=180)
        try:
            figures = asyncio.run(bench(stack.endpoint, vehicles, args.trials, args.still))
        finally:
            stack.stop()
    write_json(args.json, "fleet_abort", figures, args)


if __name__ == "__main__":
    main()
