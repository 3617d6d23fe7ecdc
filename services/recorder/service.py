"""The recorder service: subscribe the key space, hand every raw sample to the writer thread, report health."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import re
import socket
import time
from collections import OrderedDict
from collections.abc import Callable
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from services.recorder.settings import RecorderSettings
from services.recorder.throttle import FrameThrottle
from services.recorder.writer import RecordWriter
from shared.bus import Bus, Subscription
from shared.keys import CAMERA_SEGMENTATION, REASONER_STEP, REASONER_TASK_STATUS
from shared.messages import Health, TaskState
from shared.service import announce

log = logging.getLogger("aermani.recorder")

# Names like api_key, gateway_token, tls_key_password; `key_expr` is not a secret.
_SECRET = re.compile(r"(^|_)(key|token|secret|password|passwd|credentials?|auth)(_|$)")


def aermani_version() -> str:
    try:
        return version("aermani")
    except PackageNotFoundError:
        return "unknown"


def public_settings(settings: RecorderSettings) -> dict[str, str]:
    """Settings for the metadata record, without anything that looks like a secret."""
    out = {}
    for name, value in settings.model_dump().items():
        if _SECRET.search(name.lower()) and name != "key_expr":
            continue
        out[f"setting.{name}"] = str(value)
    return out


def static_metadata(settings: RecorderSettings) -> dict[str, str]:
    return {"aermani_version": aermani_version(), "host": socket.gethostname(), "key_expr": settings.key_expr,
            "started_ns": str(time.time_ns()), **public_settings(settings)}


class TaskLedger:
    """What the recorder has taken of each recent task: its steps and whether its end came (`health/recorder`
    details `tasks`: the highest step number taken and the terminal state), so whoever stops a stack after a task
    can first wait until its log holds the task's end and its last step (`shared.tasks.recorded_end`) instead of
    losing them to a stop a few milliseconds too early."""

    KEEP = 16

    def __init__(self) -> None:
        self.tasks: OrderedDict[str, dict[str, Any]] = OrderedDict()

    def note(self, key: str, payload: bytes) -> bool:
        """Count a sample; True when it was a task's terminal status, or a step of an ended task (worth saying at
        once)."""
        status = key.endswith("/" + REASONER_TASK_STATUS.name)
        if not status and not key.endswith("/" + REASONER_STEP.name):
            return False
        try:
            doc = json.loads(payload)
            task_id = str(doc["task_id"])
            entry = self.tasks.setdefault(task_id, {"steps": 0, "ended": None})
            self.tasks.move_to_end(task_id)
            while len(self.tasks) > self.KEEP:
                self.tasks.popitem(last=False)
            if not status:
                entry["steps"] = max(entry["steps"], int(doc["step"]))
                return entry["ended"] is not None  # a step after the end (Zenoh orders nothing across keys)
            state = TaskState(doc["state"])
        except (ValueError, KeyError, TypeError):
            return False  # recorded as it came; only not counted
        if state.terminal:
            entry["ended"] = state.value
        return state.terminal


async def _drain(sub: Subscription[Any], submit: Callable[[str, bytes, str, int], None]) -> None:
    """Whatever the bus already delivered belongs in the file too; then the subscription closes."""
    while sub.qsize():
        try:
            rec = await sub.recv_sample(timeout=1.0)
        except (TimeoutError, asyncio.CancelledError):
            break
        submit(rec.key, rec.payload, rec.encoding, rec.receive_ns)
    sub.close()


async def run(bus: Bus, settings: RecorderSettings, stop: asyncio.Event) -> None:
    writer = RecordWriter(settings, static_metadata(settings))
    writer.start()
    sub = bus.subscribe(settings.key_expr, maxsize=settings.queue_size, overflow="drop_newest")
    subs = [sub]
    if settings.segmentation:
        subs.append(bus.subscribe(CAMERA_SEGMENTATION.fleet().key, maxsize=settings.queue_size,
                                  overflow="drop_newest"))
    announce(bus, settings, "recorder")
    health_key = settings.keys.health("recorder")

    throttle = FrameThrottle(settings.frame_max_hz)
    ledger = TaskLedger()

    def health() -> Health:
        bus_dropped = sum(s.dropped for s in subs)
        details = {**writer.stats(), "bus_dropped": bus_dropped, "frames_skipped": throttle.skipped,
                   "tasks": {k: dict(v) for k, v in ledger.tasks.items()}}
        details["dropped"] = writer.dropped_backlog + bus_dropped
        ok = writer.ok
        message = writer.error if not ok else ""
        if ok and details["dropped"]:
            message = f"{details['dropped']} samples dropped (writer too slow)"
        return Health(service="recorder", ok=ok, message=message, details=details)

    async def report() -> None:
        while True:
            with contextlib.suppress(Exception):
                bus.publish(health_key, health())
            await asyncio.sleep(settings.health_period_s)

    def submit(key: str, payload: bytes, encoding: str, receive_ns: int) -> None:
        for sample in throttle.admit(key, payload, encoding, receive_ns):
            writer.submit(*sample)
        if ledger.note(key, payload):
            with contextlib.suppress(Exception):
                bus.publish(health_key, health())  # a task's end is in the log: say so now, not within a second

    async def take(one: Subscription[Any]) -> None:
        while True:
            rec = await one.recv_sample()
            submit(rec.key, rec.payload, rec.encoding, rec.receive_ns)

    reporter = asyncio.create_task(report(), name="recorder.health")
    takers = [asyncio.create_task(take(one), name=f"recorder.take{i}") for i, one in enumerate(subs)]
    stopper = asyncio.create_task(stop.wait(), name="recorder.stop")
    try:
        await asyncio.wait([stopper, *takers], return_when=asyncio.FIRST_COMPLETED)
        for t in takers:
            if t.done():
                t.result()  # a taker only ends by an error: raise it, as the one loop before it did
    finally:
        reporter.cancel()
        stopper.cancel()
        for t in takers:
            t.cancel()
        await asyncio.gather(*takers, return_exceptions=True)
        for one in subs:
            await _drain(one, submit)
        # The writer thread finishes the file; never cancelled, so a SIGTERM always leaves a valid MCAP.
        await asyncio.shield(asyncio.to_thread(writer.stop, settings.stop_drain_s, settings.stop_drain_s + 15.0))
        log.info("recording finished: %s", writer.stats())
