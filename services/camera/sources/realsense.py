"""`realsense` source: an Intel RealSense D4xx through pyrealsense2, depth aligned to colour on the device's
pipeline, intrinsics read from the device. Opened only when the SDK lists a connected device ("no RealSense
connected" otherwise); streaming is untested here (no device on the build machine), the absent path runs
against the real SDK in tests/camera."""

from __future__ import annotations

from typing import Any

import numpy as np

from services.camera.sources.base import CameraSource, Capture, register
from shared.errors import CameraError
from shared.sensors import Intrinsics

INSTALL = ("the realsense source needs the `pyrealsense2` package: `pip install pyrealsense2` (or `pip install "
           "-e .[realsense]`); where no wheel exists for the platform (e.g. a Jetson), build librealsense with "
           "-DBUILD_PYTHON_BINDINGS=ON (docs/hardware.md)")


@register
class RealSenseSource(CameraSource):
    """Camera source for an Intel RealSense depth camera (colour aligned with depth) through pyrealsense2."""

    type = "realsense"
    paced = True  # wait_for_frames blocks until the device delivers
    sdk = "pyrealsense2"
    install = INSTALL

    def connected(self, rs: Any) -> list[str]:
        """Serial numbers of the RealSense devices connected now. The SDK's device list answers in a few
        milliseconds; `pipeline.start` with no device waits 15 s and holds the GIL all the while (measured with
        pyrealsense2 2.59), which stops the service's event loop, its heartbeat and health, and gets it killed
        as hung. So the service asks this first and opens only a device that is there."""
        devices = rs.context().query_devices()
        camera_info = rs.camera_info.serial_number
        return [d.get_info(camera_info) for d in devices]

    def open(self) -> None:
        rs = self.sdk_module()
        s = self.settings
        serials = self.connected(rs)
        if not serials:
            raise CameraError("no RealSense connected (the SDK lists no device: plugged into a USB 3 port? "
                              "inside a container, /dev shared with the USB device rule, see docs/hardware.md)")
        if s.device and s.device not in serials:
            raise CameraError(f"no RealSense with serial {s.device} connected (connected: {', '.join(serials)}; "
                              "AERMANI_CAMERA_DEVICE names one of them, or leave it empty for the first)")
        self.pipeline = rs.pipeline()
        cfg = rs.config()
        if s.device:
            cfg.enable_device(s.device)
        fps = int(round(s.fps))
        cfg.enable_stream(rs.stream.color, s.width, s.height, rs.format.rgb8, fps)
        cfg.enable_stream(rs.stream.depth, s.width, s.height, rs.format.z16, fps)
        try:
            profile = self.pipeline.start(cfg)
        except RuntimeError as exc:
            raise CameraError(f"no RealSense camera could stream {s.width}x{s.height} at {fps} fps"
                              f"{' (serial ' + s.device + ')' if s.device else ''}: {exc}") from exc
        # Depth units: metres per raw unit (1 mm by default on D4xx); the bus wants millimetres.
        self.depth_to_mm = profile.get_device().first_depth_sensor().get_depth_scale() * 1000.0
        self.align = rs.align(rs.stream.color)
        ci = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
        self.intrinsics = Intrinsics(ci.width, ci.height, ci.fx, ci.fy, ci.ppx, ci.ppy)
        self.has_depth = True

    def read(self) -> Capture | None:
        try:
            frames = self.pipeline.wait_for_frames(int(self.settings.read_timeout_s * 1000))
        except RuntimeError as exc:
            raise CameraError(f"RealSense delivered no frame in {self.settings.read_timeout_s} s: {exc}") from exc
        frames = self.align.process(frames)
        color, depth = frames.get_color_frame(), frames.get_depth_frame()
        if not color or not depth:
            raise CameraError("RealSense frameset without colour or depth")
        raw = np.asanyarray(depth.get_data())
        depth_mm = raw if abs(self.depth_to_mm - 1.0) < 1e-6 else np.clip(raw * self.depth_to_mm, 0, 65535)
        return Capture(rgb=np.asanyarray(color.get_data()).copy(), depth_mm=depth_mm.astype(np.uint16))

    def close(self) -> None:
        if getattr(self, "pipeline", None) is not None:
            try:
                self.pipeline.stop()
            except RuntimeError:
                pass

    def describe(self) -> str:
        return f"realsense {self.settings.device or '(first)'}"
