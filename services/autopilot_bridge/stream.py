"""The offboard setpoint stream: a drift-free fixed-rate sender thread, ramped targets, interval statistics."""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from services.autopilot_bridge.px4 import SetpointNED

log = logging.getLogger("aermani.autopilot_bridge.stream")


@dataclass(frozen=True)
class Target:
    """Where the vehicle should be (ENU). With `speed`, the setpoint moves from `start` to the goal at that
    speed, starting at `t0` (monotonic seconds); without, it jumps to the goal."""

    x: float
    y: float
    z: float
    yaw: float
    start: tuple[float, float, float] | None = None
    speed: float | None = None
    t0: float = 0.0

    def at(self, now: float) -> tuple[float, float, float, float]:
        """Setpoint (x, y, z, yaw) ENU at monotonic time `now`."""
        if self.start is None or not self.speed:
            return (self.x, self.y, self.z, self.yaw)
        sx, sy, sz = self.start
        dx, dy, dz = self.x - sx, self.y - sy, self.z - sz
        dist = math.sqrt(dx * dx + dy * dy + dz * dz)
        travelled = self.speed * max(0.0, now - self.t0)
        if dist < 1e-9 or travelled >= dist:
            return (self.x, self.y, self.z, self.yaw)
        f = travelled / dist
        return (sx + f * dx, sy + f * dy, sz + f * dz, self.yaw)

    def ramp_done(self, now: float) -> bool:
        return self.at(now)[:3] == (self.x, self.y, self.z)


def percentile(values: list[float], q: float) -> float:
    """Nearest-rank percentile (q in 0..100) of a non-empty list."""
    s = sorted(values)
    k = max(0, min(len(s) - 1, math.ceil(q / 100.0 * len(s)) - 1))
    return s[k]


class SetpointStream:
    """Sends the current target at a fixed rate from its own thread.

    Deadlines are computed as t_start + n * period from a monotonic clock, so a late wake-up never shifts
    the following ones (no accumulated drift); if the thread falls more than a period behind (a stall), it
    skips the missed slots instead of bursting. A thread rather than an asyncio task keeps the stream's
    timing independent of whatever the event loop is busy with."""

    def __init__(self, send: Callable[[SetpointNED], bool], rate_hz: float, window: int = 2000,
                 realtime_priority: int = 0) -> None:
        self._send = send
        self.realtime_priority = realtime_priority
        self.scheduling = "normal"
        self.period = 1.0 / rate_hz
        self.target: Target | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.started_at: float | None = None  # monotonic time of the first send of the current run
        self.last_sent_at: float = 0.0
        self.sent = 0
        self.skipped = 0
        self._intervals: deque[float] = deque(maxlen=window)
        self._lock = threading.Lock()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def running_for(self) -> float:
        """Seconds the stream has been sending in its current run (0 when stopped)."""
        if not self.running or self.started_at is None:
            return 0.0
        return time.monotonic() - self.started_at

    def set_target(self, target: Target) -> None:
        self.target = target  # one reference swap: the thread sees the old or the new target, never a mix

    def start(self, target: Target) -> None:
        self.set_target(target)
        if self.running:
            return
        self._stop = threading.Event()
        self.started_at = None
        self._thread = threading.Thread(target=self._run, args=(self._stop,), name="setpoint-stream", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._thread = None
        self.started_at = None

    def _raise_priority(self) -> None:
        """SCHED_FIFO for this thread when allowed: on a loaded machine the OS scheduler, not our code, decides
        the wake-up latency. It sleeps 99% of the time, so it cannot starve anyone."""
        if self.realtime_priority <= 0 or not hasattr(os, "sched_setscheduler"):
            return
        try:
            os.sched_setscheduler(threading.get_native_id(), os.SCHED_FIFO, os.sched_param(self.realtime_priority))
            self.scheduling = f"SCHED_FIFO {self.realtime_priority}"
        except (OSError, PermissionError) as exc:
            if self.scheduling == "normal":
                log.info("setpoint stream keeps normal scheduling (SCHED_FIFO not permitted: %s)", exc)
            self.scheduling = "normal (SCHED_FIFO not permitted)"

    def _run(self, stop: threading.Event) -> None:
        self._raise_priority()
        period = self.period
        t_start = time.monotonic()
        n = 0
        prev: float | None = None
        while not stop.is_set():
            target = self.target
            if target is not None:
                now = time.monotonic()
                x, y, z, yaw = target.at(now)
                if self._send(SetpointNED.from_enu(x, y, z, yaw)):
                    if self.started_at is None:
                        self.started_at = now
                    self.sent += 1
                    self.last_sent_at = now
                    if prev is not None:
                        with self._lock:
                            self._intervals.append(now - prev)
                    prev = now
            n += 1
            deadline = t_start + n * period
            now = time.monotonic()
            if now > deadline + period:  # stalled: skip the missed slots, keep the phase
                missed = int((now - deadline) / period)
                self.skipped += missed
                n += missed
                deadline = t_start + n * period
            # Sleep most of the way, then spin the last half millisecond: sleep wake-ups are late by up to
            # a scheduler tick, the spin is cheap at 20 Hz.
            remaining = deadline - time.monotonic()
            if remaining > 0.001:
                stop.wait(remaining - 0.0005)
            while time.monotonic() < deadline and not stop.is_set():
                pass

    def stats(self) -> dict[str, float | int | str]:
        """Interval and jitter figures of the recent window, in milliseconds."""
        with self._lock:
            iv = list(self._intervals)
        out: dict[str, float | int | str] = {"stream_rate_hz": round(1.0 / self.period, 2),
                                             "setpoints_sent": self.sent, "stream_skipped_slots": self.skipped,
                                             "stream_samples": len(iv), "stream_scheduling": self.scheduling}
        if iv:
            jit = [abs(v - self.period) for v in iv]
            out.update(
                interval_p50_ms=round(percentile(iv, 50) * 1e3, 3), interval_p99_ms=round(percentile(iv, 99) * 1e3, 3),
                jitter_p50_ms=round(percentile(jit, 50) * 1e3, 3), jitter_p99_ms=round(percentile(jit, 99) * 1e3, 3),
                jitter_max_ms=round(max(jit) * 1e3, 3),
            )
        return out

    def reset_stats(self) -> None:
        with self._lock:
            self._intervals.clear()
