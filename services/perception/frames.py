"""Pairs colour, depth (and sim segmentation) by timestamp and attaches the camera pose from `tf`."""

from __future__ import annotations

import bisect
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from functools import cached_property
from typing import cast

import numpy as np

from shared.frames import DEFAULT_INTRINSICS
from shared.sensors import Intrinsics, parse_color, parse_depth, parse_raw16, parse_transforms

WORLD, BASE, CAMERA = "world", "base_link", "camera"
TF_EXACT_NS = 5_000_000  # a world->base_link sample this close to a frame's stamp is that frame's pose
TF_BRACKET_NS = 250_000_000  # interpolate between two samples only across a gap this short


@dataclass
class Frame:
    """One RGB-D frame with everything needed to lift pixels into the world. Colour decodes lazily: the
    `sim` segmenter and the geometry never need it."""

    stamp_ns: int
    depth_mm: np.ndarray  # HxW uint16, 0 = invalid
    intr: Intrinsics
    world_from_camera: np.ndarray  # 4x4, optical frame -> world ENU
    receive_ns: int = 0
    color_payload: bytes | None = None
    segmentation: np.ndarray | None = None  # HxW uint16 instance ids (sim only)
    labels: object | None = None  # SimLabels in force when the frame was paired (sim only)
    _rgb: np.ndarray | None = field(default=None, repr=False)

    @property
    def rgb(self) -> np.ndarray:
        if self._rgb is None:
            if self.color_payload is None:
                raise ValueError("frame has no colour image")
            self._rgb = parse_color(self.color_payload)[1]
        return self._rgb

    @cached_property
    def depth_m(self) -> np.ndarray:
        return self.depth_mm.astype(np.float32) * 0.001

    def age_s(self, now_ns: int | None = None) -> float:
        return ((now_ns or time.time_ns()) - self.receive_ns) / 1e9

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth_mm.shape  # type: ignore[return-value]


class FrameStore:
    """Keeps the last few raw colour/depth/segmentation payloads per stamp and the tf history, and builds
    the newest complete Frame on demand (decoding only what is used)."""

    def __init__(self, need_segmentation: bool = False, keep: int = 8, tf_keep: int = 200) -> None:
        self.need_segmentation = need_segmentation
        self.keep = keep
        self._slots: OrderedDict[int, dict[str, object]] = OrderedDict()
        self._tf_stamps: deque[int] = deque(maxlen=tf_keep)
        self._tf_poses: deque[np.ndarray] = deque(maxlen=tf_keep)
        self.base_from_camera: np.ndarray | None = None
        self.intr: Intrinsics | None = None
        self.labels: object | None = None
        self.complete_stamp = 0  # newest stamp with every part present
        self.complete_receive_ns = 0
        self.revision = 0  # bumps when a frame completes or a pose arrives: something may have become usable
        self.counts = {"color": 0, "depth": 0, "segmentation": 0, "tf": 0, "calibration": 0, "bad": 0}
        self._cache: tuple[int, Frame] | None = None

    # ---- inputs (raw payloads; cheap)

    def _slot(self, stamp: int) -> dict[str, object]:
        slot = self._slots.get(stamp)
        if slot is None:
            slot = self._slots[stamp] = {}
            while len(self._slots) > self.keep:
                self._slots.popitem(last=False)
        return slot

    def _check_complete(self, stamp: int, slot: dict[str, object], receive_ns: int) -> None:
        parts = ("color", "depth", "segmentation") if self.need_segmentation else ("color", "depth")
        if all(p in slot for p in parts) and "receive_ns" not in slot:
            slot["receive_ns"] = receive_ns
            self.revision += 1
            if stamp >= self.complete_stamp:
                self.complete_stamp = stamp
                self.complete_receive_ns = receive_ns

    def add_color(self, payload: bytes, receive_ns: int | None = None) -> None:
        from shared.sensors import CompressedImage, decode_proto, stamp_to_ns

        stamp = stamp_to_ns(decode_proto(CompressedImage, payload).timestamp)
        self._add("color", stamp, payload, receive_ns)

    def add_depth(self, payload: bytes, receive_ns: int | None = None) -> None:
        stamp, img = parse_depth(payload)
        self._add("depth", stamp, img, receive_ns)

    def add_segmentation(self, payload: bytes, receive_ns: int | None = None) -> None:
        stamp, img = parse_raw16(payload)
        self._add("segmentation", stamp, img, receive_ns)

    def _add(self, part: str, stamp: int, value: object, receive_ns: int | None) -> None:
        self.counts[part] += 1
        slot = self._slot(stamp)
        slot[part] = value
        if part == "segmentation" or "labels" not in slot:
            slot["labels"] = self.labels
        self._check_complete(stamp, slot, receive_ns or time.time_ns())

    def add_calibration(self, intr: Intrinsics) -> None:
        self.counts["calibration"] += 1
        self.intr = intr

    def add_tf(self, payload: bytes) -> None:
        self.counts["tf"] += 1
        for (parent, child), (stamp, T) in parse_transforms(payload).items():  # noqa: N806
            if (parent, child) == (WORLD, BASE):
                if self._tf_stamps and stamp < self._tf_stamps[-1]:
                    continue  # out of order: keep the history sorted
                self._tf_stamps.append(stamp)
                self._tf_poses.append(T)
                self.revision += 1
            elif (parent, child) == (BASE, CAMERA):
                self.base_from_camera = T

    def add_labels(self, labels: object) -> None:
        self.labels = labels

    # ---- output

    def world_from_base_at(self, stamp: int) -> tuple[np.ndarray, int] | None:
        """The world->base_link pose at `stamp` and the offset of the sample used (ns), or None.

        Zenoh does not order samples across keys, so a frame may arrive before its pose. Using the nearest
        older pose then is wrong by however far the vehicle moved (half a metre during a climb was seen), so
        a pose is only taken from a sample within TF_EXACT_NS or interpolated between samples that bracket
        the stamp; otherwise None: the frame waits for its pose, never a guess."""
        if not self._tf_stamps:
            return None
        stamps = list(self._tf_stamps)
        i = bisect.bisect_left(stamps, stamp)
        near = [j for j in (i - 1, i) if 0 <= j < len(stamps) and abs(stamps[j] - stamp) <= TF_EXACT_NS]
        if near:
            best = min(near, key=lambda j: abs(stamps[j] - stamp))
            return self._tf_poses[best], stamps[best] - stamp
        if 0 < i < len(stamps) and stamps[i] - stamps[i - 1] <= TF_BRACKET_NS:
            a = (stamp - stamps[i - 1]) / (stamps[i] - stamps[i - 1])
            before, after = self._tf_poses[i - 1], self._tf_poses[i]
            T = (before if a < 0.5 else after).copy()  # noqa: N806 - rotation of the nearer sample
            T[:3, 3] = (1 - a) * before[:3, 3] + a * after[:3, 3]
            return T, 0
        return None

    def missing(self) -> str:
        """What is missing for a first frame, in words."""
        parts = []
        if not self.counts["color"]:
            parts.append("colour images")
        if not self.counts["depth"]:
            parts.append("depth images")
        if self.need_segmentation and not self.counts["segmentation"]:
            parts.append("segmentation images")
        if self.need_segmentation and self.labels is None:
            parts.append("sim/labels")
        if not self._tf_stamps:
            parts.append("tf world->base_link")
        if self.base_from_camera is None:
            parts.append("tf base_link->camera")
        if self.counts["color"] and self.counts["depth"] and not self.complete_stamp:
            parts.append("a colour/depth pair with the same timestamp")
        elif self.complete_stamp and self._tf_stamps and self.world_from_base_at(self.complete_stamp) is None:
            parts.append("a world->base_link transform at the frame's timestamp")
        return ", ".join(parts)

    def latest(self) -> Frame | None:
        """Newest complete frame whose pose is known, or None (see `missing()`)."""
        if self.base_from_camera is None:
            return None
        for stamp in sorted(self._slots, reverse=True):
            slot = self._slots[stamp]
            if "receive_ns" not in slot:
                continue
            if self._cache is not None and self._cache[0] == stamp:
                return self._cache[1]
            base = self.world_from_base_at(stamp)
            if base is not None:
                return self._build(stamp, slot, base[0])
        return None

    def _build(self, stamp: int, slot: dict[str, object], world_from_base: np.ndarray) -> Frame | None:
        if self.need_segmentation and slot.get("labels") is None:
            if self.labels is None:
                return None  # instance ids without names are useless
            slot["labels"] = self.labels
        depth = slot["depth"]
        assert isinstance(depth, np.ndarray)
        intr = self.intr or DEFAULT_INTRINSICS
        if (intr.height, intr.width) != depth.shape:
            # Calibration for another resolution: scale it rather than mis-project.
            sx, sy = depth.shape[1] / intr.width, depth.shape[0] / intr.height
            intr = Intrinsics(depth.shape[1], depth.shape[0], intr.fx * sx, intr.fy * sy, intr.cx * sx, intr.cy * sy)
        frame = Frame(stamp, depth, intr, world_from_base @ self.base_from_camera, int(cast(int, slot["receive_ns"])),
                      slot.get("color"), slot.get("segmentation"), slot.get("labels"))  # type: ignore[arg-type]
        self._cache = (stamp, frame)
        return frame
