"""Soak: back-to-back tasks on the whole stack for a set duration (issue 18). Reports tasks completed, failures
by cause, unsafe endings, memory growth per service (RSS after the first task to the end) and messages
dropped (every service's bus counters from its health, and the recorder's).

Real processes: simulator (realistic), autopilot bridge, perception (colour segmenter), executor, reasoner
(`rules` backend: a non-VLM baseline; swap in a model with AERMANI_REASONER_* variables) and recorder, on
one in-process router. Each task: the simulator resets to a fresh seeded layout, the vehicle lands if
needed, a pick-and-place command runs to its terminal status; an ending is unsafe when the task did not
succeed and the vehicle is neither landed nor holding still inside the geofence. Printed, never asserted.

    .venv/bin/python benchmarks/soak.py [--minutes 30] [--out runs/soak] [--json PATH]

The figures are also written as JSON to --json (default OUT/soak.json), which `benchmarks/run_all.py
--soak-json PATH` reads into docs/performance.md.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from aermani.launcher import Stack, free_udp_port  # noqa: E402
from benchmarks._figures import add_json_option, write_json  # noqa: E402
from services.executor.settings import ExecutorSettings  # noqa: E402
from shared.bus import Bus  # noqa: E402
from shared.keys import HEALTH_TOPIC, HEARTBEAT_TOPIC, Keys  # noqa: E402
from shared.messages import Health, Heartbeat, Scenario, TaskRequest, VehicleState  # noqa: E402
from shared.tasks import follow_task  # noqa: E402

SERVICES = ["sim", "autopilot_bridge", "perception", "executor", "reasoner", "recorder"]
COMMANDS = [("red cup", "table"), ("coke can", "shelf"), ("tissue box", "counter"), ("apple", "table")]


def rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def safe(st: VehicleState | None, fence: ExecutorSettings) -> bool:
    if st is None:
        return False
    if st.landed_state.value == "on_ground" and not st.armed:
        return True
    p, v = st.position, st.velocity
    inside = all(lo <= x <= hi for x, lo, hi in zip((p.x, p.y, p.z), fence.geofence_min, fence.geofence_max,
                                                     strict=True))
    return inside and math.sqrt(v.x ** 2 + v.y ** 2 + v.z ** 2) < 0.15


async def soak(stack: Stack, minutes: float) -> dict[str, object]:
    keys = Keys("am1")
    fence = ExecutorSettings()
    bus = await Bus.open(connect=[stack.endpoint])
    health = bus.subscribe(HEALTH_TOPIC.bind("am1", service="*"), maxsize=1000)
    beats = bus.subscribe(HEARTBEAT_TOPIC.bind("am1", service="*"), maxsize=2000)
    state = bus.subscribe(keys.autopilot_state, maxsize=5)
    drops: dict[str, int] = collections.defaultdict(int)
    causes: collections.Counter[str] = collections.Counter()
    done = unsafe = 0
    base: dict[str, float] = {}
    end_at = time.monotonic() + minutes * 60
    seed = 1000
    try:
        while time.monotonic() < end_at:
            seed += 1
            obj, dest = COMMANDS[seed % len(COMMANDS)]
            res = await bus.query(keys.sim_reset, Scenario(seed=seed, target_object=obj, destination=dest), timeout=60)
            if not res.ok:
                causes[f"reset refused: {res.message[:60]}"] += 1
                continue
            await asyncio.sleep(2.0)
            req = TaskRequest(command=f"Pick up the {obj} and place it on the {dest}.", takeoff=True, t_max_s=300)
            followed = await follow_task(bus, keys, req, timeout=400, ready_timeout=60, retry_rejected_s=30)
            final = followed.final
            last = state.latest_nowait()
            if final is None:
                causes["no terminal status: " + (followed.error or "timeout")[:60]] += 1
            elif final.state.value == "succeeded":
                done += 1
            else:
                causes[f"{final.state.value}: {final.message[:70]}"] += 1
            if final is None or final.state.value != "succeeded":
                await asyncio.sleep(3.0)
                if not safe(state.latest_nowait() or last, fence):
                    unsafe += 1
            while (h := health.recv_nowait()) is not None:
                _note_drops(h, drops)
            while (b := beats.recv_nowait()) is not None:
                _note_beat(b, drops)
            if not base:
                base = {p.label: rss_mb(p.proc.pid) for p in stack.procs if p.proc}
            left = (end_at - time.monotonic()) / 60
            print(f"  tasks {done + sum(causes.values())}: {done} succeeded, {sum(causes.values())} not, "
                  f"{unsafe} unsafe; {max(0.0, left):.1f} min left", flush=True)
    finally:
        end = {p.label: rss_mb(p.proc.pid) for p in stack.procs if p.proc}
        await bus.close()
    total = done + sum(causes.values())
    print(f"\nsoak: {minutes:.0f} min, {total} tasks, {done} succeeded, unsafe endings {unsafe}")
    for cause, n in causes.most_common():
        print(f"  {n:3d} x {cause}")
    print("memory growth per service (RSS after the first task -> end, MB):")
    for label, mb in end.items():
        print(f"  {label:28s} {base.get(label, float('nan')):7.1f} -> {mb:7.1f}  ({mb - base.get(label, mb):+.1f})")
    dropped = ", ".join(f"{k} {v}" for k, v in sorted(drops.items())) or "none"
    print(f"messages dropped (bus counters from every heartbeat and health, recorder): {dropped}")
    growth = {label: mb - base.get(label, mb) for label, mb in end.items()}
    return {"minutes": minutes, "tasks": total, "succeeded": done, "unsafe": unsafe, "causes": dict(causes),
            "memory_growth_mb": growth, "memory_growth_max_mb": max(growth.values(), default=0.0),
            "dropped": dict(drops), "dropped_total": sum(drops.values())}


def _note_beat(b: Heartbeat, drops: dict[str, int]) -> None:
    """Every service's heartbeat carries its bus's drop counter (services without a health topic too)."""
    drops[b.service] = max(drops.get(b.service, 0), b.bus_dropped)


def _note_drops(h: Health, drops: dict[str, int]) -> None:
    bus = h.details.get("bus") or {}
    n = int(bus.get("dropped", 0)) + int(h.details.get("dropped", 0) if h.service == "recorder" else 0)
    drops[h.service] = max(drops.get(h.service, 0), n)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--out", default="runs/soak")
    add_json_option(ap)
    args = ap.parse_args()
    api = free_udp_port()
    env = {"AERMANI_SIM_API_PORT": str(api), "AERMANI_SIM_API_LOCAL_PORT": str(free_udp_port()),
           "AERMANI_SIM_GCS_PORT": str(free_udp_port()), "AERMANI_SIM_GCS_LOCAL_PORT": str(free_udp_port()),
           "AERMANI_AUTOPILOT_BRIDGE_CONNECTION": f"udpin:127.0.0.1:{api}", "AERMANI_REASONER_BACKEND": "rules",
           "AERMANI_RECORDER_OUT_DIR": f"{args.out}/recordings", "AERMANI_SIM_SPEED_FACTOR": "4"}
    print(f"soak for {args.minutes:.0f} min: {', '.join(SERVICES)} (backend rules: a non-VLM baseline)")
    with Stack(SERVICES, env=env, log_dir=Path(args.out) / "logs") as stack:
        figures = asyncio.run(soak(stack, args.minutes))
    write_json(args.json or Path(args.out) / "soak.json", "soak", figures, args)


if __name__ == "__main__":
    main()
