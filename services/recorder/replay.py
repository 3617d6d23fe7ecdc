"""Replay: republish a recorded log on Zenoh verbatim (same key, bytes, encoding) with its original timing.

Control keys (commands and abort) are left out unless asked: republished onto a live bus, a recorded abort
would stop a flight and a recorded command could move a vehicle. Nor does a replay publish onto a vehicle that
is live now (its state and detections would pass for the vehicle's own) unless asked. `remap` moves samples to
other vehicle ids (key and the payload's top-level `vehicle_id`), so a log can be watched beside the live fleet."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from shared import keys as k
from shared.bus import Bus
from shared.errors import AermaniError
from shared.mcaplog import iter_samples, log_vehicles

# Keys (after aermani/v1/<vehicle>/) that act on a vehicle or a task when they arrive.
CONTROL_SUFFIXES = tuple(d.name for d in (
    k.SAFETY_ABORT, k.AUTOPILOT_COMMAND, k.EXECUTOR_RUN_SKILL, k.EXECUTOR_CANCEL_SKILL, k.REASONER_START_TASK,
    k.REASONER_CANCEL_TASK, k.REASONER_DECIDE_APPROVAL, k.SIM_RESET))


def is_control_key(key: str) -> bool:
    parts = str(key).split("/", 3)
    return len(parts) == 4 and f"{parts[0]}/{parts[1]}" == k.ROOT and parts[3] in CONTROL_SUFFIXES


def remap_sample(key: str, payload: bytes, encoding: str, remap: dict[str, str]) -> tuple[str, bytes]:
    """Move a sample to the vehicle id `remap` names for its own (or "*" for any)."""
    parts = str(key).split("/", 3)
    if len(parts) < 3 or f"{parts[0]}/{parts[1]}" != k.ROOT:
        return key, payload
    old = parts[2]
    new = remap.get(old, remap.get("*"))
    if new is None or new == old:
        return key, payload
    k.vehicle_prefix(new)  # validates
    parts[2] = new
    if encoding.startswith("application/json"):
        try:
            obj = json.loads(payload)
        except ValueError:
            obj = None
        if isinstance(obj, dict) and obj.get("vehicle_id") == old:
            obj["vehicle_id"] = new
            payload = json.dumps(obj, separators=(",", ":")).encode()
    return "/".join(parts), payload


@dataclass
class ReplayResult:
    """Result of replaying a log onto the bus: samples published, the log's time span and the wall time."""

    published: int
    first_log_ns: int
    last_log_ns: int
    wall_s: float
    skipped_control: dict[str, int] = field(default_factory=dict)
    """Control samples left out, per key."""


def log_bounds(path: str | Path) -> tuple[int, int]:
    """(first, last) log time of a log, ns."""
    from mcap.reader import make_reader

    try:
        with Path(path).open("rb") as f:
            summary = make_reader(f).get_summary()
            if summary is not None and summary.statistics is not None:
                return summary.statistics.message_start_time, summary.statistics.message_end_time
    except Exception:
        pass
    first = last = 0
    for s in iter_samples(path):
        first = first or s.log_time_ns
        last = s.log_time_ns
    return first, last


# A vehicle is live when the services that own its state answer: the autopilot bridge (pose, link, mode) or the
# simulator standing in for the vehicle. Ground services (gateway, recorder) alone leave a vehicle id free.
VEHICLE_OWNERS = ("autopilot_bridge", "sim")


class ReplayOntoLive(AermaniError):
    """The replay would publish onto a vehicle that is flying or could fly now."""


async def live_targets(bus: Bus, path: str | Path, remap: dict[str, str] | None) -> list[str]:
    """The vehicle ids the replay of `path` (after `remap`) would publish onto whose state owners answer."""
    targets = {(remap or {}).get(v, (remap or {}).get("*", v)) for v in log_vehicles(path)}
    owned = {vehicle for vehicle, service in map(k.parse_alive_key, await bus.alive(k.alive_pattern(), timeout=2.0))
             if service in VEHICLE_OWNERS}  # one liveliness query for the whole fleet
    return sorted(targets & owned)


async def replay(bus: Bus, path: str | Path, *, speed: float = 1.0, keys: str | None = None,
                 start_s: float | None = None, end_s: float | None = None,
                 on_sample: Callable[[int], None] | None = None, include_control: bool = False,
                 remap: dict[str, str] | None = None, onto_live: bool = False) -> ReplayResult:
    """Publish the samples of `path` in log-time order. `speed` 1 keeps the original timing, 2 is twice as
    fast, 0 (or less) as fast as possible. `start_s`/`end_s` are seconds from the start of the log.
    Abort and command keys are skipped unless `include_control`; `remap` maps old vehicle ids to new ones
    ("*" for every vehicle)."""
    for new in (remap or {}).values():
        k.vehicle_prefix(new)  # a bad id fails before anything is published
    if not onto_live and (live := await live_targets(bus, path, remap)):
        raise ReplayOntoLive(
            f"vehicle {', '.join(live)} is live (its autopilot bridge or simulator answers): the log's state, "
            "detections and camera would reach its services and its operators as if they were now. Replay beside "
            "it under another id (--vehicle replay1, or --remap OLD=NEW), or pass --onto-live on purpose")
    skipped: dict[str, int] = {}
    first, _ = log_bounds(path)
    start_ns = first + int(start_s * 1e9) if start_s is not None else None
    end_ns = first + int(end_s * 1e9) if end_s is not None else None
    t_wall0 = time.monotonic()
    t_log0: int | None = None
    n = 0
    last = 0
    for s in iter_samples(path, keys, start_ns, end_ns):
        if t_log0 is None:
            t_log0 = s.log_time_ns
        if speed > 0:
            due = t_wall0 + (s.log_time_ns - t_log0) / 1e9 / speed
            delay = due - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
        if not include_control and is_control_key(s.key):
            skipped[s.key] = skipped.get(s.key, 0) + 1
            continue
        key, payload = remap_sample(s.key, s.payload, s.encoding, remap) if remap else (s.key, s.payload)
        bus.publish_raw(key, payload, s.encoding)
        n += 1
        last = s.log_time_ns
        if on_sample is not None:
            on_sample(n)
        elif n % 200 == 0:
            await asyncio.sleep(0)  # keep the loop responsive when replaying as fast as possible
    return ReplayResult(n, t_log0 or 0, last, time.monotonic() - t_wall0, skipped)
