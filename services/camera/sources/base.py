"""The camera source interface and its registry: a source is one file plus `@register`, picked by `source`."""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from shared.errors import CameraError
from shared.frames import DEFAULT_INTRINSICS
from shared.registry import Registry
from shared.sensors import Intrinsics

if TYPE_CHECKING:
    from services.camera.settings import CameraSettings


@dataclass
class Capture:
    """One frame from a source: colour (pixels, or JPEG bytes passed through) and depth aligned to it."""

    rgb: np.ndarray | None = None
    """HxWx3 uint8 RGB (None when `jpeg` is given)."""
    jpeg: bytes | None = None
    """Colour already JPEG-encoded (a recorded log's bytes, republished without re-encoding)."""
    depth_mm: np.ndarray | None = None
    """HxW uint16 z-depth in millimetres, registered to the colour image (0 = invalid); None without depth."""


class CameraSource(ABC):
    """A camera. `open()` connects (raises CameraError when absent), `read()` blocks for the next frame and
    returns None when a finite source (file/mcap without loop) has ended, `close()` releases it."""

    type: ClassVar[str] = ""
    paced: ClassVar[bool] = False
    """True: `read()` itself waits for the device's next frame; False: the service paces reads to `fps`."""
    retry_open: ClassVar[bool] = True
    """True for devices (unplugged now, plugged in later: keep trying); False for what plays a file
    (PlayedSource), where a failed open is a configuration error and the service exits with it."""

    def __init__(self, settings: CameraSettings) -> None:
        self.settings = settings
        self.intrinsics: Intrinsics | None = None
        """Pinhole intrinsics of the colour (and aligned depth) image, known after `open()`."""
        self.has_depth = False
        """Whether `read()` returns depth (set by `open()`)."""
        self.ended = ""
        """Why a finite source stopped ("" while it runs)."""

    sdk: ClassVar[str] = ""
    """The Python module of the device's SDK (imported on `check()` and `open()`), "" when none is needed."""
    install: ClassVar[str] = ""
    """How to install `sdk`: the CameraError's text when it cannot be imported."""

    def check(self) -> None:
        """Validate settings and dependencies without touching a device; raise CameraError saying how to fix.
        By default: the SDK imports."""
        if self.sdk:
            self.sdk_module()

    def check_calibration(self) -> None:
        """A calibration file named by AERMANI_CAMERA_CALIBRATION must exist (checked before anything opens)."""
        if self.settings.calibration and not Path(self.settings.calibration).is_file():
            raise CameraError(f"AERMANI_CAMERA_CALIBRATION {self.settings.calibration} does not exist")

    def intrinsics_from(self, cal: Path | None, native: tuple[int, int], must_match: bool) -> Intrinsics:
        """Intrinsics at the configured size of frames that arrive `native`-sized: from the calibration file
        `cal` when it exists (for `native` exactly when `must_match`), else the simulator camera's."""
        intr = load_calibration(cal) if cal is not None and cal.is_file() else default_intrinsics(*native)
        if must_match and (intr.width, intr.height) != native:
            raise CameraError(f"calibration {cal} is for {intr.width}x{intr.height} but the frames are "
                              f"{native[0]}x{native[1]}")
        return scaled(intr, self.settings.width, self.settings.height)

    def sdk_module(self) -> Any:
        """The imported `sdk` module, or a CameraError saying how to install it."""
        try:
            return importlib.import_module(self.sdk)
        except ImportError as exc:
            raise CameraError(self.install) from exc

    @abstractmethod
    def open(self) -> None:
        """Connect to the camera (raise CameraError when it is absent); set `intrinsics` and `has_depth`."""

    @abstractmethod
    def read(self) -> Capture | None:
        """The next frame (blocking), or None when the source has ended."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the device or file."""

    def describe(self) -> str:
        return self.type


class PlayedSource(CameraSource):
    """A source that plays what AERMANI_CAMERA_PATH names (a video, an image folder, a recorded log) instead of
    a device: a failed open is a configuration error, never retried."""

    retry_open = False

    def input_path(self, what: str) -> Path:
        """`path`, the thing to play: a CameraError naming AERMANI_CAMERA_PATH when unset or absent."""
        if not self.settings.path:
            raise CameraError(f"the {self.type} source needs AERMANI_CAMERA_PATH: {what}")
        p = Path(self.settings.path)
        if not p.exists():
            raise CameraError(f"AERMANI_CAMERA_PATH {p} does not exist")
        return p


SOURCES: Registry[type[CameraSource]] = Registry("camera source", "type", "AERMANI_CAMERA_SOURCE", CameraError)
register = SOURCES.register
"""Class decorator: make a source selectable by its `type` (AERMANI_CAMERA_SOURCE)."""


# --------------------------------------------------------------------------- helpers shared by sources


def scaled(intr: Intrinsics, width: int, height: int) -> Intrinsics:
    """Intrinsics of the same camera at another resolution (pixel centres kept)."""
    if (intr.width, intr.height) == (width, height):
        return intr
    sx, sy = width / intr.width, height / intr.height
    return Intrinsics(width, height, intr.fx * sx, intr.fy * sy, (intr.cx + 0.5) * sx - 0.5, (intr.cy + 0.5) * sy - 0.5)


def default_intrinsics(width: int, height: int) -> Intrinsics:
    """The simulator's camera at `width` x `height`: the assumption when nothing better is known."""
    return scaled(DEFAULT_INTRINSICS, width, height)


def load_calibration(path: str | Path) -> Intrinsics:
    """Intrinsics from YAML: either `width, height, fx, fy, cx, cy`, or a ROS camera_info file
    (`image_width`, `image_height`, `camera_matrix: {data: [9 numbers]}`)."""
    import yaml

    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text())
    except OSError as exc:
        raise CameraError(f"cannot read calibration {p}: {exc}") from exc
    except yaml.YAMLError as exc:
        raise CameraError(f"calibration {p} is not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise CameraError(f"calibration {p} must be a mapping with width, height, fx, fy, cx, cy")
    try:
        if "camera_matrix" in data:
            k = [float(v) for v in data["camera_matrix"]["data"]]
            intr = Intrinsics(int(data["image_width"]), int(data["image_height"]), k[0], k[4], k[2], k[5])
        else:
            intr = Intrinsics(int(data["width"]), int(data["height"]), float(data["fx"]), float(data["fy"]),
                              float(data["cx"]), float(data["cy"]))
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise CameraError(f"calibration {p} lacks a field or has a non-number ({exc!r}); expected width, height, "
                          "fx, fy, cx, cy (or a ROS camera_info file)") from exc
    if intr.width <= 0 or intr.height <= 0 or intr.fx <= 0 or intr.fy <= 0:
        raise CameraError(f"calibration {p}: width, height, fx and fy must be positive, got {intr}")
    return intr


def fit(cap: Capture, width: int, height: int) -> Capture:
    """Resize a capture's colour (area) and depth (nearest: never blend depth across edges) to width x height."""
    import cv2

    rgb, depth = cap.rgb, cap.depth_mm
    if rgb is not None and rgb.shape[:2] != (height, width):
        rgb = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
    if depth is not None and depth.shape[:2] != (height, width):
        depth = cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)
    return Capture(rgb, cap.jpeg, depth)
