"""Built-in camera sources; importing this package registers them."""

from __future__ import annotations

from typing import TYPE_CHECKING

from services.camera.sources import file, mcap, realsense, uvc, zed  # noqa: F401
from services.camera.sources.base import SOURCES, CameraSource, Capture, PlayedSource, register

__all__ = ["SOURCES", "CameraSource", "Capture", "PlayedSource", "make_source", "register"]

if TYPE_CHECKING:
    from services.camera.settings import CameraSettings


def make_source(settings: CameraSettings) -> CameraSource:
    """Build the configured source and check it (raises CameraError naming the fix; opens nothing)."""
    src = SOURCES.lookup(settings.source)(settings)
    src.check()
    return src
