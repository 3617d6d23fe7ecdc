"""Helpers shared by the built-in skills."""

from __future__ import annotations

from typing import TYPE_CHECKING

from services.executor.memory import horizontal_distance
from shared.messages import ObjectEstimate, PlacementEstimate, Vec3

if TYPE_CHECKING:
    from services.executor.context import SkillContext


def fmt(p: Vec3) -> str:
    """A position as the model reads it: (x, y, z) in metres, two decimals."""
    return f"({p.x:.2f}, {p.y:.2f}, {p.z:.2f})"


def beyond_reach(ctx: SkillContext, position: Vec3, reach: float, what: str, why: str = "") -> str | None:
    """Why `what` at `position` is too far (horizontally) from the vehicle to act on, or None within `reach`;
    `why` follows the reach in the message (", where ... is accurate enough")."""
    st = ctx.state.value
    assert st is not None
    d = horizontal_distance(position, st.position)
    if not d > reach:
        return None
    return f"{what} is {d:.2f} m away (reach {reach:.2f} m{why}): too far: approach first"


def not_found(query: str, est: ObjectEstimate | PlacementEstimate) -> str:
    """Why a localization found nothing, written for the model."""
    why = {"not_visible": "not visible", "ambiguous": "ambiguous (several matches)",
           "too_few_points": "seen but with too few depth points", "no_free_spot": "without a free spot"}
    return f"{query} {why.get(est.reason, est.reason)}" + (f": {est.message}" if est.message else "")
