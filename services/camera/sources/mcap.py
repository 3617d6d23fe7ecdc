"""`mcap` source: the colour/depth frames of a recorded aermani MCAP log, replayed as a live camera.

Colour and depth are paired by their recorded stamp; the JPEG bytes go out verbatim (no re-encoding) with a
new stamp (the bus convention: now, shared by colour and depth). The log's resolution is kept; the recorded
calibration is used.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from services.camera.sources.base import Capture, PlayedSource, register
from shared.errors import CameraError, DecodeError
from shared.keys import CAMERA_CALIBRATION, CAMERA_COLOR, CAMERA_DEPTH
from shared.sensors import CompressedImage, decode_proto, parse_calibration, parse_depth, stamp_to_ns


def _vehicles_with_color(path: Path) -> list[str]:
    from shared.mcaplog import iter_samples, vehicle_of

    seen: list[str] = []
    for s in iter_samples(path, CAMERA_COLOR.fleet().key):
        v = vehicle_of(s.key)
        if v and v not in seen:
            seen.append(v)
            break  # the first is enough unless a vehicle is named
    return seen


@register
class McapSource(PlayedSource):
    """Camera source that replays the camera frames recorded in an aermani MCAP log."""

    type = "mcap"

    def check(self) -> None:
        if not self.input_path("an aermani MCAP log").is_file():
            raise CameraError(f"AERMANI_CAMERA_PATH {self.settings.path} is not a file")

    def open(self) -> None:
        from shared.mcaplog import iter_samples

        path = Path(self.settings.path)
        vehicle = self.settings.mcap_vehicle or next(iter(_vehicles_with_color(path)), "")
        if not vehicle:
            raise CameraError(f"{path} has no camera/color samples to replay")
        self.vehicle = vehicle
        self.color_key = CAMERA_COLOR.bind(vehicle).key
        self.depth_key = CAMERA_DEPTH.bind(vehicle).key
        cal_key = CAMERA_CALIBRATION.bind(vehicle).key
        self.has_depth = any(True for _ in _take(iter_samples(path, self.depth_key), 1))
        for s in iter_samples(path, cal_key):
            try:
                self.intrinsics = parse_calibration(s.payload)
                break
            except DecodeError:
                continue
        if not any(True for _ in _take(iter_samples(path, self.color_key), 1)):
            raise CameraError(f"{path} has no camera/color samples of vehicle {vehicle!r}")
        self.frames_iter = self._pairs()
        self.played = 0

    def _pairs(self) -> Iterator[Capture]:
        """Colour (and depth with the same stamp) in log order, once through the log."""
        from shared.mcaplog import iter_samples

        pending_color: dict[int, bytes] = {}
        pending_depth: dict[int, object] = {}
        for s in iter_samples(self.settings.path, f"aermani/v1/{self.vehicle}/camera/*"):
            try:
                if s.key == self.color_key:
                    stamp = stamp_to_ns(decode_proto(CompressedImage, s.payload).timestamp)
                    jpeg = bytes(decode_proto(CompressedImage, s.payload).data)
                    if not self.has_depth:
                        yield Capture(jpeg=jpeg)
                    elif stamp in pending_depth:
                        yield Capture(jpeg=jpeg, depth_mm=pending_depth.pop(stamp))  # type: ignore[arg-type]
                    else:
                        pending_color[stamp] = jpeg
                elif s.key == self.depth_key:
                    stamp, depth = parse_depth(s.payload)  # PNG, or RawImage in older logs
                    if stamp in pending_color:
                        yield Capture(jpeg=pending_color.pop(stamp), depth_mm=depth)
                    else:
                        pending_depth[stamp] = depth
            except DecodeError:
                continue  # a malformed recorded sample is skipped, like the recorder's readers do
            # Unpaired halves older than a few frames will never be paired (dropped in flight when recorded).
            for pending in (pending_color, pending_depth):
                while len(pending) > 8:
                    pending.pop(min(pending))

    def read(self) -> Capture | None:
        for _ in range(2):
            cap = next(self.frames_iter, None)
            if cap is not None:
                self.played += 1
                return cap
            if not self.settings.loop or not self.played:
                break
            self.frames_iter = self._pairs()
        self.ended = f"the mcap log reached its end after {self.played} frames" + (
            " (loop off)" if self.settings.loop is False else " (no colour/depth pair with the same stamp)")
        return None

    def describe(self) -> str:
        return f"mcap {self.settings.path} (vehicle {getattr(self, 'vehicle', '?')})"


def _take(it: Iterator[object], n: int) -> Iterator[object]:
    for i, x in enumerate(it):
        if i >= n:
            return
        yield x
