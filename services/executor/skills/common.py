"""Helpers shared by the built-in skills."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from services.executor.context import SkillFailed
from services.executor.memory import horizontal_distance
from services.executor.registry import SkillResult
from shared.messages import ObjectEstimate, OutcomeCode, PlacementEstimate, SkillFacts, Vec3

if TYPE_CHECKING:
    from services.executor.context import SkillContext


class Refusal(str):
    """A precondition's reason (a str, so `Skill.check` keeps its type) that also carries the outcome code and
    facts the executor reports with the rejection; a plain string from `check` is reported as `blocked`."""

    code: OutcomeCode
    facts: SkillFacts

    def __new__(cls, text: str, code: OutcomeCode = OutcomeCode.BLOCKED, facts: SkillFacts | None = None) -> Refusal:
        self = super().__new__(cls, text)
        self.code = code
        self.facts = facts or SkillFacts()
        return self


def coded(message: str, code: OutcomeCode = OutcomeCode.SUCCEEDED, **facts: Any) -> SkillResult:
    """A skill's result with its code and facts (SkillFacts fields by name): `coded("placed", target="cup")`."""
    return SkillResult(message, code, SkillFacts(**facts))


def failure(message: str, code: OutcomeCode, **facts: Any) -> SkillFailed:
    """The SkillFailed to raise for a coded failure: `raise failure("missed", OutcomeCode.MISSED, attempts=2)`."""
    return SkillFailed(message, code, SkillFacts(**facts))


def fmt(p: Vec3) -> str:
    """A position as the model reads it: (x, y, z) in metres, two decimals."""
    return f"({p.x:.2f}, {p.y:.2f}, {p.z:.2f})"


def beyond_reach(ctx: SkillContext, position: Vec3, reach: float, what: str, why: str = "") -> Refusal | None:
    """Why `what` at `position` is too far (horizontally) from the vehicle to act on (`out_of_reach`, with the
    distance and the reach), or None within `reach`; `why` follows the reach in the message (", where ... is
    accurate enough")."""
    st = ctx.state.value
    assert st is not None
    d = horizontal_distance(position, st.position)
    if not d > reach:
        return None
    return Refusal(f"{what} is {d:.2f} m away (reach {reach:.2f} m{why}): too far: approach first",
                   OutcomeCode.OUT_OF_REACH, SkillFacts(distance_m=round(d, 3), reach_m=reach))


def not_found(query: str, est: ObjectEstimate | PlacementEstimate) -> str:
    """Why a localization found nothing, written for the model."""
    why = {"not_visible": "not visible", "ambiguous": "ambiguous (several matches)",
           "too_few_points": "seen but with too few depth points", "no_free_spot": "without a free spot"}
    return f"{query} {why.get(est.reason, est.reason)}" + (f": {est.message}" if est.message else "")
