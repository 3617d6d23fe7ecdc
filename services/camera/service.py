"""The camera service: a capture thread reads the configured source, stamps each frame once (ns since the
epoch, shared by colour and depth), encodes it, and hands it to the loop, which publishes colour, depth,
tf (base_link->camera, base_link->gripper) with that stamp, calibration at 1 Hz, and health at 1 Hz."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from services.camera.settings import CameraSettings
from services.camera.sources import CameraSource, Capture, make_source
from shared.bus import Bus
from shared.errors import AermaniError, CameraError
from shared.messages import Health, now_ns
from shared.sensors import (
    BODY_FRAME,
    CAMERA_FRAME,
    GRIPPER_FRAME,
    calibration_message,
    color_message,
    depth_message,
    transforms_message,
)

log = logging.getLogger("aermani.camera")

SERVICE = "camera"
MAX_REOPEN_S = 30.0


@dataclass
class Encoded:
    """One captured frame encoded for the bus: colour, optional depth and camera transform, with its stamp."""

    stamp_ns: int
    color: bytes
    depth: bytes | None
    tf: bytes | None


class Capturer:
    """Owns the source on one daemon thread (device calls block; a hung device must not stall health)."""

    def __init__(self, source: CameraSource, settings: CameraSettings, deliver: Callable[[Encoded], None]) -> None:
        self.source, self.s, self.deliver = source, settings, deliver
        self.stop = threading.Event()
        self.opened = False
        self.open_error = ""
        self.last_error = ""
        self.failures = 0
        self.ended = ""
        self.fatal = ""
        """Set when the source cannot work at all (a file source that does not open): the service exits."""
        self.thread = threading.Thread(target=self._run, name="camera-capture", daemon=True)
        mount = settings.mount
        self.mounts = [(BODY_FRAME, CAMERA_FRAME, mount.base_to_camera()),
                       (BODY_FRAME, GRIPPER_FRAME, mount.base_to_gripper())]

    def start(self) -> None:
        self.thread.start()

    def _open(self) -> bool:
        delay = self.s.reopen_s
        while not self.stop.is_set():
            try:
                self.source.open()
                self.opened, self.open_error = True, ""
                log.info("opened %s: %s, depth %s", self.source.describe(), self.source.intrinsics,
                         "yes" if self.source.has_depth else "no (colour only)")
                return True
            except AermaniError as exc:
                self.open_error = str(exc)
            except Exception as exc:  # a driver's own exception: report it the same way
                self.open_error = f"{type(exc).__name__}: {exc}"
            if not self.source.retry_open:
                self.fatal = f"cannot open {self.source.describe()}: {self.open_error}"
                return False
            # The same words as health's message, so the log says it too.
            log.warning("camera absent: %s; retrying in %.0f s", self.open_error, delay)
            self.stop.wait(delay)
            delay = min(MAX_REOPEN_S, delay * 2)
        return False

    def encode(self, cap: Capture) -> Encoded:
        stamp = now_ns()
        color = color_message(cap.rgb, stamp, quality=self.s.jpeg_quality, jpeg=cap.jpeg)  # type: ignore[arg-type]
        depth = depth_message(cap.depth_mm, stamp) if cap.depth_mm is not None else None
        tf = transforms_message(self.mounts, stamp) if self.s.publish_tf else None
        return Encoded(stamp, color, depth, tf)

    def _run(self) -> None:
        period = 1.0 / self.s.fps
        last_sent = -1e9
        try:
            while not self.stop.is_set():
                if not self.opened and not self._open():
                    return
                t0 = time.monotonic()
                try:
                    cap = self.source.read()
                    if cap is None:
                        self.ended = self.source.ended or "the source ended"
                        log.warning("%s", self.ended)
                        return
                    self.failures = 0
                    if self.source.paced and time.monotonic() - last_sent < 0.9 * period:
                        continue  # a device faster than `fps` (UVC cameras may ignore the request): drop
                    last_sent = time.monotonic()
                    self.deliver(self.encode(cap))
                except Exception as exc:
                    self.failures += 1
                    self.last_error = str(exc) if isinstance(exc, CameraError) else f"{type(exc).__name__}: {exc}"
                    log.warning("frame from %s failed (%d in a row): %s", self.source.describe(), self.failures,
                                self.last_error)
                    if self.failures >= 3:  # the device is gone or wedged: start over
                        self._close()
                        self.stop.wait(self.s.reopen_s)
                    continue
                if not self.source.paced:
                    self.stop.wait(max(0.0, period - (time.monotonic() - t0)))
        finally:
            self._close()

    def _close(self) -> None:
        if self.opened:
            with contextlib.suppress(Exception):
                self.source.close()
        self.opened = False

    def join(self, timeout: float) -> None:
        self.stop.set()
        self.thread.join(timeout)


class CameraService:
    """Publishes a camera source's frames on the vehicle's camera keys and reports the frame rate in health."""

    def __init__(self, bus: Bus, settings: CameraSettings, source: CameraSource) -> None:
        self.bus, self.s, self.source = bus, settings, source
        self.keys = settings.keys
        self.loop = asyncio.get_running_loop()
        self.capturer = Capturer(source, settings, self._from_thread)
        self.frames = 0
        self.recent: deque[float] = deque(maxlen=1000)
        self.last_frame_mono: float | None = None
        self.last_stamp_ns = 0
        self.last_calibration = -1e9
        self.started = time.monotonic()

    def _from_thread(self, enc: Encoded) -> None:  # capture thread
        self.loop.call_soon_threadsafe(self._publish, enc)

    def _publish(self, enc: Encoded) -> None:  # loop
        now = time.monotonic()
        if self.source.intrinsics is not None and now - self.last_calibration >= 1.0:
            # With (not after) the first frame, then at 1 Hz: a consumer never holds a frame it cannot project.
            self.bus.publish(self.keys.camera_calibration, calibration_message(self.source.intrinsics, enc.stamp_ns))
            self.last_calibration = now
        self.bus.publish(self.keys.camera_color, enc.color)
        if enc.depth is not None:
            self.bus.publish(self.keys.camera_depth, enc.depth)
        if enc.tf is not None:
            self.bus.publish(self.keys.tf, enc.tf)
        self.frames += 1
        self.last_frame_mono = now
        self.recent.append(self.last_frame_mono)
        self.last_stamp_ns = enc.stamp_ns

    def health(self) -> Health:
        now = time.monotonic()
        c = self.capturer
        age = now - self.last_frame_mono if self.last_frame_mono is not None else None
        fps = sum(1 for t in self.recent if now - t <= 5.0) / min(5.0, max(now - self.started, 1e-3))
        what = self.source.describe()
        if not c.opened and c.open_error and not c.ended:
            message = f"camera absent: {c.open_error}"
        elif age is None:
            message = f"no frame from {what} yet ({now - self.started:.1f} s since start)" + (
                f"; last error: {c.last_error}" if c.last_error else "")
        elif age > self.s.stall_s:
            message = f"camera stalled: no frame from {what} for {age:.1f} s" + (
                f": {c.ended}" if c.ended else f"; last error: {c.last_error}" if c.last_error else "")
        else:
            message = ""
        ok = message == ""
        return Health(service=SERVICE, ok=ok, message=message, details={
            "source": self.s.source, "fps_5s": round(fps, 2), "frame_age_s": None if age is None else round(age, 3),
            "frames": self.frames, "depth": self.source.has_depth, "opened": c.opened,
            "width": self.source.intrinsics.width if self.source.intrinsics else None,
            "height": self.source.intrinsics.height if self.source.intrinsics else None,
            "failures": c.failures, "last_error": c.last_error, "ended": c.ended})

    async def run(self, stop: asyncio.Event) -> None:
        self.capturer.start()
        try:
            while not stop.is_set():
                if self.capturer.fatal:
                    raise CameraError(self.capturer.fatal)
                self.bus.publish(self.keys.health(SERVICE), self.health())
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), 1.0)
        finally:
            await asyncio.to_thread(self.capturer.join, 5.0)


async def idle(bus: Bus, settings: CameraSettings, stop: asyncio.Event) -> None:
    """source `none`: publish nothing but say so, so nobody mistakes the silence for a stalled camera."""
    log.info("no camera source configured (AERMANI_CAMERA_SOURCE=none): publishing nothing")
    while not stop.is_set():
        bus.publish(settings.keys.health(SERVICE), Health(
            service=SERVICE, ok=True, message="no camera source configured (AERMANI_CAMERA_SOURCE=none): this "
            "service publishes nothing; the simulator (or another publisher) owns the camera keys",
            details={"source": "none"}))
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), 1.0)


async def run(bus: Bus, settings: CameraSettings, stop: asyncio.Event) -> None:
    if settings.source == "none":
        await idle(bus, settings, stop)
        return
    try:
        source = make_source(settings)
    except CameraError as exc:
        log.error("cannot start: %s", exc)
        raise
    await CameraService(bus, settings, source).run(stop)
