"""`sim` segmenter: the simulator's instance-id image plus its label table (ground-truth masks)."""

from __future__ import annotations

from functools import partial

import numpy as np

from services.perception.frames import Frame
from services.perception.segmenters.base import Segment, Segmenter, register
from shared.messages import SimLabel


def _instance_pixels(flat: np.ndarray, inst: int) -> np.ndarray:
    """Flat indices of the pixels of instance `inst` (computed only when a segment's pixels are asked for)."""
    return np.flatnonzero(flat == inst)


@register
class SimSegmenter(Segmenter):
    """Masks come from `camera/@segmentation` (same stamp as colour/depth), names from `sim/labels`. Only the
    matching is exercised here, so it measures the geometry and the query logic without vision errors."""

    type = "sim"
    needs_segmentation = True

    def _labels(self, frame: Frame | None) -> dict[int, SimLabel]:
        labels = getattr(frame, "labels", None) if frame is not None else None
        return {lab.id: lab for lab in getattr(labels, "labels", ())}

    def known_names(self, frame: Frame | None) -> list[str]:
        return sorted({lab.name for lab in self._labels(frame).values()})

    def detect(self, frame: Frame) -> list[Segment]:
        seg = frame.segmentation
        if seg is None:
            return []
        labels = self._labels(frame)
        flat = seg.ravel()
        counts = np.bincount(flat, minlength=1)
        out = []
        min_px = self.settings.min_pixels
        for inst in np.flatnonzero(counts >= min_px):
            lab = labels.get(int(inst))
            if inst == 0 or lab is None:
                continue
            size = lab.size
            volume = float(size.x * size.y * size.z) if size is not None else 0.0
            # The simulator's label carries the object's extent as built (the oracle's catalogue).
            nominal = ((max(size.x, size.y), min(size.x, size.y), size.z)
                       if size is not None and lab.category == "object" else None)
            out.append(Segment(int(inst), lab.name, lab.category, lab.color, 1.0, volume, int(counts[inst]),
                               nominal, _compute=partial(_instance_pixels, flat, int(inst))))
        return out
