"""`zed` source: a Stereolabs ZED (the paper's camera) through the ZED SDK's `pyzed`, depth registered to the
left colour image, intrinsics from the SDK (untested here: needs the SDK, CUDA and a ZED)."""

from __future__ import annotations

import numpy as np

from services.camera.sources.base import CameraSource, Capture, register
from shared.errors import CameraError
from shared.sensors import Intrinsics

INSTALL = ("the zed source needs the ZED SDK and its Python API `pyzed` (not on PyPI): install the ZED SDK for "
           "your JetPack/CUDA from stereolabs.com/developers, then run its `get_python_api.py` in this venv "
           "(docs/hardware.md)")

RESOLUTIONS = {(672, 376): "VGA", (1280, 720): "HD720", (1920, 1080): "HD1080", (2208, 1242): "HD2K"}


@register
class ZedSource(CameraSource):
    """Camera source for a Stereolabs ZED stereo camera (colour and depth) through the ZED SDK."""

    type = "zed"
    paced = True  # grab() waits for the next frame
    sdk = "pyzed.sl"
    install = INSTALL

    def open(self) -> None:
        sl = self.sdk_module()
        s = self.settings
        init = sl.InitParameters()
        # The SDK has fixed modes: take the one matching width x height, else the smallest, resized below.
        init.camera_resolution = getattr(sl.RESOLUTION, RESOLUTIONS.get((s.width, s.height), "VGA"))
        init.camera_fps = int(round(s.fps))
        init.depth_mode = sl.DEPTH_MODE.NEURAL if hasattr(sl.DEPTH_MODE, "NEURAL") else sl.DEPTH_MODE.ULTRA
        init.coordinate_units = sl.UNIT.MILLIMETER
        if s.device:
            init.set_from_serial_number(int(s.device))
        self.cam = sl.Camera()
        err = self.cam.open(init)
        if err != sl.ERROR_CODE.SUCCESS:
            raise CameraError(f"the ZED camera did not open: {err}")
        cal = self.cam.get_camera_information().camera_configuration.calibration_parameters.left_cam
        res = self.cam.get_camera_information().camera_configuration.resolution
        self.intrinsics = Intrinsics(res.width, res.height, cal.fx, cal.fy, cal.cx, cal.cy)
        self.has_depth = True
        self.runtime = sl.RuntimeParameters()
        self.left, self.depth = sl.Mat(), sl.Mat()
        self.sl = sl

    def read(self) -> Capture | None:
        sl = self.sl
        err = self.cam.grab(self.runtime)
        if err != sl.ERROR_CODE.SUCCESS:
            raise CameraError(f"ZED grab failed: {err}")
        self.cam.retrieve_image(self.left, sl.VIEW.LEFT)
        self.cam.retrieve_measure(self.depth, sl.MEASURE.DEPTH)
        bgra = self.left.get_data()
        rgb = np.ascontiguousarray(bgra[:, :, 2::-1])
        d = self.depth.get_data()
        depth_mm = np.where(np.isfinite(d), np.clip(d, 0, 65535), 0).astype(np.uint16)
        return Capture(rgb=rgb, depth_mm=depth_mm)

    def close(self) -> None:
        if getattr(self, "cam", None) is not None:
            self.cam.close()

    def describe(self) -> str:
        return f"zed {self.settings.device or '(first)'}"
