"""Helpers shared by the built-in skills."""

from __future__ import annotations

from shared.messages import ObjectEstimate, PlacementEstimate, Vec3


def fmt(p: Vec3) -> str:
    """A position as the model reads it: (x, y, z) in metres, two decimals."""
    return f"({p.x:.2f}, {p.y:.2f}, {p.z:.2f})"


def not_found(query: str, est: ObjectEstimate | PlacementEstimate) -> str:
    """Why a localization found nothing, written for the model."""
    why = {"not_visible": "not visible", "ambiguous": "ambiguous (several matches)",
           "too_few_points": "seen but with too few depth points", "no_free_spot": "without a free spot"}
    return f"{query} {why.get(est.reason, est.reason)}" + (f": {est.message}" if est.message else "")
