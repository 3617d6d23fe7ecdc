"""The perception service: ingest camera + tf, serve localize_object / localize_placement, publish detections."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from pydantic import ValidationError

from services.perception import query as q
from services.perception.frames import Frame, FrameStore
from services.perception.pipeline import Perception
from services.perception.segmenters import make_segmenter
from services.perception.settings import PerceptionSettings
from shared.bus import Bus
from shared.errors import AermaniError, DecodeError
from shared.messages import Health, LocalizeRequest, ObjectEstimate, PlacementEstimate, SimLabels
from shared.sensors import parse_calibration
from shared.service import announce

log = logging.getLogger("aermani.perception")

Estimate = ObjectEstimate | PlacementEstimate


def parse_request(data: bytes | None) -> tuple[LocalizeRequest | None, str, str]:
    """Raw query payload -> (request, echoed query, error). Never raises: anything malformed becomes a
    bad_query answer the caller can read, instead of a transport error."""
    if not data:
        return None, "", "empty request: send a JSON LocalizeRequest such as {\"query\": \"red cup\"}"
    try:
        obj = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        return None, "", f"request is not JSON ({exc}); send {{\"query\": \"red cup\"}}"
    if not isinstance(obj, dict):
        return None, "", "request must be a JSON object with a `query` field"
    raw_query = obj.get("query")
    echo = q.clean(raw_query) if isinstance(raw_query, str) else ""
    if isinstance(raw_query, str) and len(raw_query) > q.MAX_QUERY_CHARS:
        return None, echo, f"the query is {len(raw_query)} characters long; at most {q.MAX_QUERY_CHARS} are accepted"
    obj.setdefault("kind", "localize_request")
    try:
        return LocalizeRequest.model_validate(obj), echo, ""
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first.get("loc", ())) or "request"
        return None, echo, f"invalid request at {where}: {first.get('msg')}"


class PerceptionService:
    """Serves perception over the bus: keeps the newest frames and answers localization queries and detections."""

    def __init__(self, bus: Bus, settings: PerceptionSettings, perception: Perception) -> None:
        self.bus = bus
        self.settings = settings
        self.perception = perception
        self.store = FrameStore(need_segmentation=perception.segmenter.needs_segmentation)
        self.new_frame = asyncio.Event()
        self.skill_end_ns = 0  # when the newest skill ended (its status received): the next observation's start
        self.skill_ended = asyncio.Event()
        self.pool = ThreadPoolExecutor(max_workers=settings.workers, thread_name_prefix="perception")
        self.served = {"object": 0, "placement": 0, "errors": 0, "detections": 0, "after_skill_end": 0}
        self.latency_ms: list[float] = []

    # ---- ingest

    async def _ingest(self, key: str, handle: Callable[[Any], None], model: Any = None) -> None:
        sub = self.bus.subscribe(key, maxsize=4)
        while True:
            rec = await sub.recv_sample()
            try:
                before = self.store.revision
                handle(rec.value) if model is not None else handle(rec.payload)
                if self.store.revision != before:
                    self.new_frame.set()
            except (DecodeError, ValueError) as exc:
                self.store.counts["bad"] += 1
                log.warning("dropped bad sample on %s: %s", key, exc)

    async def _wait_for_frame(self, good: Callable[[Frame], bool], timeout: float) -> tuple[Frame | None, bool]:
        """The newest complete frame, and whether `good` holds for it, waiting up to `timeout` for one that does."""
        deadline = time.monotonic() + timeout
        while True:
            frame = self.store.latest()
            if frame is not None and good(frame):
                return frame, True
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return frame, False
            self.new_frame.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.new_frame.wait(), remaining)

    async def frame(self, max_age_s: float) -> tuple[Frame | None, str, str]:
        """Newest frame no older than `max_age_s` (waiting up to frame_wait_s for one) or why not."""
        frame, fresh = await self._wait_for_frame(lambda f: f.age_s() <= max_age_s, self.settings.frame_wait_s)
        if fresh:
            return frame, "ok", ""
        if frame is None:
            if self.store.counts["color"] and not self.store.counts["depth"]:
                return None, "no_frame", ("colour frames arrive but no depth: 3D localization needs a depth image "
                                          "aligned to colour (camera source realsense, zed, or file with depth "
                                          "PNGs); a colour-only camera (uvc, a plain video) cannot localize in 3D")
            return None, "no_frame", f"no camera frame yet (missing: {self.store.missing() or 'nothing'}); is the " \
                                     "camera (or the sim) running?"
        return None, "stale_frame", f"newest frame is {frame.age_s():.2f} s old (max_frame_age_s {max_age_s}); " \
                                    "the camera stream has stopped or lags"

    # ---- queryables

    async def _answer(self, data: bytes | None, cls: type[Estimate]) -> Estimate:
        t0 = time.perf_counter()
        try:
            req, echo, error = parse_request(data)
            if req is None:
                return cls(query=echo, found=False, reason="bad_query", message=error)
            try:
                parsed = q.parse(req.query)
            except q.BadQuery as exc:
                return cls(query=q.clean(req.query), found=False, reason="bad_query", message=str(exc))
            max_age = req.max_frame_age_s if req.max_frame_age_s > 0 else 1.0
            frame, reason, message = await self.frame(max_age)
            if frame is None:
                return cls(query=parsed.text, found=False, reason=reason, message=message)  # type: ignore[arg-type]
            fn = self.perception.localize_object if cls is ObjectEstimate else self.perception.localize_placement
            return await asyncio.get_running_loop().run_in_executor(self.pool, fn, frame, req, parsed)
        except Exception as exc:  # a bug must answer, not kill the queryable
            self.served["errors"] += 1
            log.exception("localization failed")
            return cls(query="", found=False, reason="error", message=f"{type(exc).__name__}: {exc}")
        finally:
            self.served["object" if cls is ObjectEstimate else "placement"] += 1
            self.latency_ms = [*self.latency_ms[-199:], (time.perf_counter() - t0) * 1000]

    async def localize_object(self, data: bytes | None) -> ObjectEstimate:
        return await self._answer(data, ObjectEstimate)  # type: ignore[return-value]

    async def localize_placement(self, data: bytes | None) -> PlacementEstimate:
        return await self._answer(data, PlacementEstimate)  # type: ignore[return-value]

    # ---- publications

    async def _skill_ends(self) -> None:
        """Follow the executor's skill statuses: a skill's end is when the reasoner's next observation starts."""
        sub = self.bus.subscribe(self.settings.keys.skill_status, maxsize=50)
        while True:
            try:
                st = await sub.recv()
            except DecodeError as exc:
                log.warning("dropped a bad skill status: %s", exc)
                continue
            if st.state.terminal:
                self.skill_end_ns = time.time_ns()
                self.skill_ended.set()

    async def _frame_received_after(self, ns: int, timeout: float) -> Frame | None:
        """The newest complete frame received after `ns` (this host's clock), waiting up to `timeout` for it."""
        frame, after = await self._wait_for_frame(lambda f: f.receive_ns > ns, timeout)
        return frame if after else None

    async def _detections(self, stop: asyncio.Event) -> None:
        """Detections at `detections_hz`, and at once for the first frame received after a skill's end: that is
        the observation the reasoner waits for before its next step, so it never waits for the next tick."""
        if self.settings.detections_hz <= 0:
            return
        period = 1.0 / self.settings.detections_hz
        last = 0
        loop = asyncio.get_running_loop()
        frame = self.store.latest()
        while not stop.is_set():
            t0 = time.monotonic()
            if frame is not None and frame.stamp_ns != last:
                last = frame.stamp_ns
                try:
                    dets = await loop.run_in_executor(self.pool, self.perception.detections, frame)
                    self.bus.publish(self.settings.keys.detections, dets)
                    self.served["detections"] += 1
                except Exception:
                    log.exception("detections failed")
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.skill_ended.wait(), max(0.0, period - (time.monotonic() - t0)))
            if self.skill_ended.is_set():
                self.skill_ended.clear()
                frame = await self._frame_received_after(self.skill_end_ns, timeout=max(period, 1.0))
                self.served["after_skill_end"] += frame is not None
            else:
                frame = self.store.latest()

    def _no_frame_reason(self) -> str:
        if self.store.counts["color"] and not self.store.counts["depth"]:
            return "colour only, no depth: 3D localization needs a depth camera"
        return f"no frame ({self.store.missing()})"

    async def _health(self, stop: asyncio.Event) -> None:
        while not stop.is_set():
            frame = self.store.latest()
            age = frame.age_s() if frame else None
            lat = sorted(self.latency_ms)
            ok = frame is not None and age is not None and age < 2.0
            self.bus.publish(self.settings.keys.health("perception"), Health(
                service="perception", ok=ok,
                message="" if ok else (self._no_frame_reason() if frame is None else f"frame {age:.1f} s old"),
                details={"segmenter": self.perception.segmenter.type, "frame_age_s": age, **self.store.counts,
                         **self.served, "latency_p50_ms": lat[len(lat) // 2] if lat else None}))
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), 2.0)


async def run(bus: Bus, settings: PerceptionSettings, stop: asyncio.Event) -> None:
    try:
        segmenter = await asyncio.to_thread(make_segmenter, settings)
    except AermaniError as exc:
        log.error("cannot start: %s", exc)
        raise
    svc = PerceptionService(bus, settings, Perception(segmenter, settings))
    k = settings.keys
    st = svc.store
    tasks = [asyncio.create_task(svc._ingest(k.camera_color, st.add_color)),
             asyncio.create_task(svc._ingest(k.camera_depth, st.add_depth)),
             asyncio.create_task(svc._ingest(k.camera_calibration, lambda p: st.add_calibration(parse_calibration(p)))),
             asyncio.create_task(svc._ingest(k.tf, st.add_tf))]
    if segmenter.needs_segmentation:
        tasks.append(asyncio.create_task(svc._ingest(k.camera_segmentation, st.add_segmentation)))
        tasks.append(asyncio.create_task(svc._ingest(k.sim_labels, st.add_labels, SimLabels)))
    bus.serve(k.localize_object, svc.localize_object, raw=True)
    bus.serve(k.localize_placement, svc.localize_placement, raw=True)
    announce(bus, settings, "perception")  # alive once it answers
    tasks += [asyncio.create_task(svc._detections(stop)), asyncio.create_task(svc._health(stop)),
              asyncio.create_task(svc._skill_ends())]
    log.info("perception ready: segmenter %s, serving %s and %s", segmenter.type, k.localize_object,
             k.localize_placement)
    try:
        await stop.wait()
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        svc.pool.shutdown(wait=False, cancel_futures=True)
