"""Summary statistics the services and tools share (one percentile for latency figures, timelines and reports)."""

from __future__ import annotations

import math
from collections.abc import Sequence


def percentile(values: Sequence[float], q: float) -> float:
    """The q-th percentile (q in 0..100) with linear interpolation between closest ranks (numpy's default)."""
    if not values:
        raise ValueError("percentile of no values")
    xs = sorted(values)
    pos = (len(xs) - 1) * q / 100.0
    lo, hi = math.floor(pos), math.ceil(pos)
    return xs[lo] + (xs[hi] - xs[lo]) * (pos - lo)


def percentile_or_none(values: Sequence[float], q: float) -> float | None:
    """`percentile`, or None for no values (a figure nobody measured, not zero)."""
    return percentile(values, q) if values else None
