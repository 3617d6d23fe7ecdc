"""`file` source: a video file, or a folder of images with optional 16-bit depth PNGs and a calibration YAML.

Folder layout (either):
  frames/0001.png, frames/0001_depth.png, ..., frames/calibration.yaml
  frames/color/0001.png, frames/depth/0001.png, ..., frames/calibration.yaml
Depth PNGs are 16-bit, millimetres, registered to the colour image (same size). Frames play in name order at
`fps` and loop when `loop` is on.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from services.camera.sources.base import Capture, PlayedSource, fit, register
from shared.errors import CameraError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")
CACHE_BYTES = 512 << 20  # decoded frames kept for the next loop (PNG decoding dominates the cost of a frame)
DEPTH_SUFFIX = "_depth"


def read_color(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise CameraError(f"cannot read image {path}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CameraError(f"cannot read depth image {path}")
    if img.dtype != np.uint16 or img.ndim != 2:
        raise CameraError(f"depth image {path} is {img.dtype} with shape {img.shape}; it must be a single-channel "
                          "16-bit PNG in millimetres")
    return img


def folder_frames(folder: Path) -> list[tuple[Path, Path | None]]:
    """(colour, depth or None) pairs of an image folder, in name order."""
    color_dir = folder / "color" if (folder / "color").is_dir() else folder
    depth_dir = folder / "depth" if (folder / "depth").is_dir() else None
    colors = sorted(p for p in color_dir.iterdir()
                    if p.suffix.lower() in IMAGE_SUFFIXES and not p.stem.endswith(DEPTH_SUFFIX))
    out = []
    for c in colors:
        d = depth_dir / f"{c.stem}.png" if depth_dir is not None else c.with_name(f"{c.stem}{DEPTH_SUFFIX}.png")
        out.append((c, d if d.is_file() else None))
    return out


@register
class FileSource(PlayedSource):
    """Camera source that plays a video file or a folder of images (colour only)."""

    type = "file"

    def check(self) -> None:
        p = self.input_path("a video file or a folder of images")
        self.check_calibration()
        if p.is_dir():
            frames = folder_frames(p)
            if not frames:
                raise CameraError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {p}")
            with_depth = sum(1 for _, d in frames if d is not None)
            if 0 < with_depth < len(frames):
                missing = next(c.name for c, d in frames if d is None)
                raise CameraError(f"{p}: {with_depth} of {len(frames)} frames have depth; every frame needs one "
                                  f"(none for {missing}) or none may have it")

    def open(self) -> None:
        p = Path(self.settings.path)
        self.frames: list[tuple[Path, Path | None]] = []
        self.video: cv2.VideoCapture | None = None
        self.index = 0
        self.played = 0
        self.cache: dict[int, Capture] = {}
        self.cached_bytes = 0
        if p.is_dir():
            self.frames = folder_frames(p)
            self.has_depth = self.frames[0][1] is not None
            first = read_color(self.frames[0][0])
            native = (first.shape[1], first.shape[0])
            cal = Path(self.settings.calibration) if self.settings.calibration else p / "calibration.yaml"
        else:
            self.video = cv2.VideoCapture(str(p))
            if not self.video.isOpened():
                raise CameraError(f"OpenCV cannot open the video {p}")
            native = (int(self.video.get(cv2.CAP_PROP_FRAME_WIDTH)), int(self.video.get(cv2.CAP_PROP_FRAME_HEIGHT)))
            cal = Path(self.settings.calibration) if self.settings.calibration else p.with_suffix(".yaml")
        self.intrinsics = self.intrinsics_from(cal, native, must_match=True)

    def _next_folder(self) -> Capture | None:
        if self.index >= len(self.frames):
            if not self.settings.loop:
                self.ended = f"the file source reached its end after {self.played} frames (loop off)"
                return None
            self.index = 0
        i = self.index
        self.index += 1
        if i in self.cache:
            return self.cache[i]
        c, d = self.frames[i]
        rgb = read_color(c)
        depth = read_depth(d) if d is not None else None
        if d is not None and depth is not None and depth.shape != rgb.shape[:2]:
            raise CameraError(f"{d.name} is {depth.shape[1]}x{depth.shape[0]} but {c.name} is "
                              f"{rgb.shape[1]}x{rgb.shape[0]}: depth must be aligned to colour")
        cap = fit(Capture(rgb=rgb, depth_mm=depth), self.settings.width, self.settings.height)
        size = cap.rgb.nbytes + (cap.depth_mm.nbytes if cap.depth_mm is not None else 0)  # type: ignore[union-attr]
        if self.cached_bytes + size <= CACHE_BYTES:
            self.cache[i] = cap
            self.cached_bytes += size
        return cap

    def _next_video(self) -> Capture | None:
        assert self.video is not None
        ok, bgr = self.video.read()
        if not ok and self.settings.loop and self.played:
            self.video.set(cv2.CAP_PROP_POS_FRAMES, 0)
            ok, bgr = self.video.read()
        if not ok:
            self.ended = f"the video {self.settings.path} ended after {self.played} frames" + (
                " (loop off)" if not self.settings.loop else "")
            return None
        return Capture(rgb=cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))

    def read(self) -> Capture | None:
        cap = self._next_video() if self.video is not None else self._next_folder()
        if cap is None:
            return None
        self.played += 1
        return fit(cap, self.settings.width, self.settings.height)  # a no-op for folder frames (fitted once)

    def close(self) -> None:
        video = getattr(self, "video", None)
        if video is not None:
            video.release()

    def describe(self) -> str:
        return f"file {self.settings.path}"
