"""`uvc` source: any V4L2/UVC camera through OpenCV. Colour only: perception can list what it sees in 2D but
needs depth (realsense, zed, or a file source with depth) to localize anything in 3D."""

from __future__ import annotations

from pathlib import Path

import cv2

from services.camera.sources.base import CameraSource, Capture, fit, register
from shared.errors import CameraError


@register
class UvcSource(CameraSource):
    """Camera source for a USB (UVC) webcam through OpenCV's VideoCapture; colour only, no depth."""

    type = "uvc"
    paced = True  # VideoCapture.read waits for the device's next frame

    def _device(self) -> int | str:
        dev = self.settings.device or "0"
        return int(dev) if dev.isdigit() else dev

    def check(self) -> None:
        self.check_calibration()

    def open(self) -> None:
        dev = self._device()
        if isinstance(dev, str) and not Path(dev).exists():
            raise CameraError(f"no camera at {dev} (is it plugged in? `v4l2-ctl --list-devices` lists them)")
        self.cap = cv2.VideoCapture(dev, cv2.CAP_V4L2)
        if not self.cap.isOpened():
            raise CameraError(f"OpenCV cannot open the UVC camera {dev!r} (busy, absent, or no permission: add the "
                              "user to the `video` group)")
        s = self.settings
        self.cap.set(cv2.CAP_PROP_FRAME_WIDTH, s.width)
        self.cap.set(cv2.CAP_PROP_FRAME_HEIGHT, s.height)
        self.cap.set(cv2.CAP_PROP_FPS, s.fps)
        self.has_depth = False
        native = (int(self.cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(self.cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        cal = Path(s.calibration) if s.calibration else None
        self.intrinsics = self.intrinsics_from(cal, native, must_match=False)

    def read(self) -> Capture | None:
        ok, bgr = self.cap.read()
        if not ok:
            raise CameraError(f"the UVC camera {self._device()!r} returned no frame (unplugged?)")
        return fit(Capture(rgb=cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)), self.settings.width, self.settings.height)

    def close(self) -> None:
        if getattr(self, "cap", None) is not None:
            self.cap.release()

    def describe(self) -> str:
        return f"uvc {self._device()}"
