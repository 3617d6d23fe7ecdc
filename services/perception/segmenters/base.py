"""The segmenter interface and its registry: `sim`, `color` and `sam3` register here under their `type`."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from services.perception import query as q
from services.perception.frames import Frame
from shared.errors import PerceptionError
from shared.registry import Registry

if TYPE_CHECKING:
    from services.perception.settings import PerceptionSettings


@dataclass
class Segment:
    """One recognised thing in a frame. The pixel mask is computed on first use (cheap listings)."""

    key: int
    label: str
    category: str  # object, surface, furniture, structure
    color: str = ""
    score: float = 1.0
    volume: float = 0.0  # m^3, for size words ("the larger box")
    n_pixels: int = 0
    nominal: tuple[float, float, float] | None = None  # the class's catalogued extent standing: long, short, height
    _indices: np.ndarray | None = field(default=None, repr=False)
    _compute: Callable[[], np.ndarray] | None = field(default=None, repr=False)

    @property
    def indices(self) -> np.ndarray:
        """Flat pixel indices (row * width + col) of the mask."""
        if self._indices is None:
            assert self._compute is not None
            self._indices = self._compute()
        return self._indices

    def candidate(self) -> q.Candidate:
        return q.Candidate(self.key, self.label, self.category, self.color, self.volume)


@dataclass
class Found:
    """What a segmenter answers for a query."""

    segment: Segment | None
    reason: str  # ok, not_visible, ambiguous
    message: str


class Segmenter(ABC):
    """Finds things in RGB-D frames. Subclasses set `type`, implement `detect` (everything recognisable)
    and `known_names` (what a query can name); `find` matches a parsed query against the detections, which
    a text-prompted model (sam3) overrides."""

    type: ClassVar[str] = ""
    needs_segmentation: ClassVar[bool] = False  # wants camera/@segmentation + sim/labels (simulator only)

    def __init__(self, settings: PerceptionSettings) -> None:
        self.settings = settings

    def start(self) -> None:  # noqa: B027 - optional hook
        """Load models or check dependencies; raise PerceptionError saying how to fix a missing piece."""

    @abstractmethod
    def detect(self, frame: Frame) -> list[Segment]:
        """Everything recognisable in `frame` (objects, surfaces, furniture; structure may be included)."""

    @abstractmethod
    def known_names(self, frame: Frame | None) -> list[str]:
        """Every label this segmenter can produce (a query naming one that is not detected is 'not visible')."""

    def find(self, frame: Frame, query: q.Query, categories: tuple[str, ...]) -> Found:
        segments = self.detect(frame)
        result = q.match(query, [s.candidate() for s in segments], self.known_names(frame), categories)
        if result.chosen is None:
            return Found(None, result.reason, result.message)
        seg = next(s for s in segments if s.key == result.chosen.key)
        return Found(seg, "ok", result.message)


SEGMENTERS: Registry[type[Segmenter]] = Registry("segmenter", "type", "AERMANI_PERCEPTION_SEGMENTER",
                                                 PerceptionError)
register = SEGMENTERS.register
"""Class decorator: make a segmenter selectable by its `type` (AERMANI_PERCEPTION_SEGMENTER)."""
