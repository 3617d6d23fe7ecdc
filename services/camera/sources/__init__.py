"""Built-in camera sources; importing this package registers them."""

from services.camera.sources import file, mcap, realsense, uvc, zed  # noqa: F401
from services.camera.sources.base import SOURCES, CameraSource, Capture, PlayedSource, make_source, register

__all__ = ["SOURCES", "CameraSource", "Capture", "PlayedSource", "make_source", "register"]
