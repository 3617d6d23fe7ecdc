"""Built-in segmenters; importing this package registers them."""

from __future__ import annotations

from typing import TYPE_CHECKING

from services.perception.segmenters import color, sam3, sim  # noqa: F401
from services.perception.segmenters.base import (
    SEGMENTERS,
    Found,
    Segment,
    Segmenter,
    register,
)

__all__ = ["SEGMENTERS", "Found", "Segment", "Segmenter", "make_segmenter", "register"]

if TYPE_CHECKING:
    from services.perception.settings import PerceptionSettings


def make_segmenter(settings: PerceptionSettings) -> Segmenter:
    """Build and start the configured segmenter; raises PerceptionError with a fix when it cannot start."""
    seg = SEGMENTERS.lookup(settings.segmenter)(settings)
    seg.start()
    return seg
