"""Built-in segmenters; importing this package registers them."""

from services.perception.segmenters import color, sam3, sim  # noqa: F401
from services.perception.segmenters.base import (
    SEGMENTERS,
    Found,
    Segment,
    Segmenter,
    make_segmenter,
    register,
)

__all__ = ["SEGMENTERS", "Found", "Segment", "Segmenter", "make_segmenter", "register"]
