"""Perception-driven routines (paper Table III): obj_localization and placement_localization."""

from __future__ import annotations

from abc import abstractmethod
from typing import ClassVar

from services.executor.context import SkillContext
from services.executor.envelope import outside_geofence
from services.executor.memory import horizontal_distance
from services.executor.registry import Category, Skill, SkillResult, register
from services.executor.skills.common import coded, failure, fmt, not_found
from shared import skills as names
from shared.messages import ObjectEstimate, OutcomeCode, PlacementEstimate

# --------------------------------------------------------------------------- perception routines


class _Localization(Skill):
    """Perception routines: ask perception, store the estimate; they never move the vehicle."""

    category: ClassVar[Category] = "perception"
    argument_required = True
    moves = False
    needs_airborne = False
    needs_offboard = False

    def timeout_s(self, ctx: SkillContext, argument: str | None) -> float:
        return self.settings.localize_timeout_s + 2.0

    async def run(self, ctx: SkillContext, argument: str | None) -> SkillResult:
        assert argument
        est = await self.localize(ctx, argument)
        if not est.found or est.pose is None:
            raise failure(not_found(argument, est), OutcomeCode.NOT_DETECTED, target=argument)
        text, result = self.store(ctx, est, argument)
        ctx.note(text)
        st = ctx.state.value
        distance = None if st is None else round(horizontal_distance(est.pose.position, st.position), 3)
        return coded(result, target=argument, distance_m=distance)

    @abstractmethod
    async def localize(self, ctx: SkillContext, argument: str) -> ObjectEstimate | PlacementEstimate:
        """Ask perception."""

    @abstractmethod
    def store(self, ctx: SkillContext, est: ObjectEstimate | PlacementEstimate, argument: str) -> tuple[str, str]:
        """Put a found estimate into working memory; returns (what was perceived, the result message)."""


@register
class ObjLocalization(_Localization):
    """Skill obj_localization: estimate the queried object's 3D pose and store it in working memory."""

    name = names.OBJ_LOCALIZATION
    description = ("Estimate the 3D pose of the queried object (open-vocabulary segmentation fused with depth) "
                   "and store it in working memory. Fails when the object is not in view.")
    argument = "object query"

    async def localize(self, ctx: SkillContext, argument: str) -> ObjectEstimate:
        return await ctx.localize_object(argument)

    def store(self, ctx: SkillContext, est: ObjectEstimate | PlacementEstimate, argument: str) -> tuple[str, str]:
        assert isinstance(est, ObjectEstimate) and est.pose is not None
        if outside_geofence(est.pose.position, self.settings, 0.05):
            # e.g. depth through a gap or a pose/frame mismatch: never store a target no skill may fly to
            raise failure(f"{argument} estimate {fmt(est.pose.position)} lies outside the flyable room: "
                          "implausible, not stored; look again", OutcomeCode.NOT_DETECTED, target=argument)
        mo = ctx.memory.store_object(est, argument)
        text = f"{mo.label} at {fmt(mo.position)}"
        st = ctx.state.value
        if st is not None:
            text += f", {horizontal_distance(mo.position, st.position):.2f} m away horizontally"
        return text, f"localized {text} (confidence {est.confidence:.2f})"


@register
class PlacementLocalization(_Localization):
    """Skill placement_localization: find a placement pose on the queried surface and store it in memory."""

    name = names.PLACEMENT_LOCALIZATION
    description = ("Find the queried support surface in the point cloud and compute a collision-free placement "
                   "pose with a vertical offset for the held object; store it in working memory.")
    argument = "surface query"

    async def localize(self, ctx: SkillContext, argument: str) -> PlacementEstimate:
        return await ctx.localize_placement(argument, ctx.memory.held_size)

    def store(self, ctx: SkillContext, est: ObjectEstimate | PlacementEstimate, argument: str) -> tuple[str, str]:
        assert isinstance(est, PlacementEstimate)
        mo = ctx.memory.store_placement(est, argument)
        text = f"placement spot on the {mo.label} at {fmt(mo.position)}"
        surface_z = est.surface_z if est.surface_z is not None else 0.0
        return text, f"found {text} (surface z {surface_z:.2f})"
