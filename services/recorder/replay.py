"""Replay: republish a recorded log on Zenoh verbatim (same key, bytes, encoding) with its original timing."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from services.recorder.mcaplog import iter_samples
from shared.bus import Bus


@dataclass
class ReplayResult:
    published: int
    first_log_ns: int
    last_log_ns: int
    wall_s: float


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


async def replay(bus: Bus, path: str | Path, *, speed: float = 1.0, keys: str | None = None,
                 start_s: float | None = None, end_s: float | None = None,
                 on_sample: Callable[[int], None] | None = None) -> ReplayResult:
    """Publish the samples of `path` in log-time order. `speed` 1 keeps the original timing, 2 is twice as
    fast, 0 (or less) as fast as possible. `start_s`/`end_s` are seconds from the start of the log."""
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
        bus.publish_raw(s.key, s.payload, s.encoding)
        n += 1
        last = s.log_time_ns
        if on_sample is not None:
            on_sample(n)
        elif n % 200 == 0:
            await asyncio.sleep(0)  # keep the loop responsive when replaying as fast as possible
    return ReplayResult(n, t_log0 or 0, last, time.monotonic() - t_wall0)
