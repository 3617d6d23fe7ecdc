"""Perception-driven routines (paper Table III): obj_localization and placement_localization."""

from __future__ import annotations

from services.executor.context import SkillContext, SkillFailed
from services.executor.envelope import outside_geofence
from services.executor.memory import horizontal_distance
from services.executor.registry import Category, Skill, SkillResult, register
from services.executor.skills.common import fmt, not_found
from shared import skills as names

# --------------------------------------------------------------------------- perception routines


class _Localization(Skill):
    """Perception routines: ask perception, store the estimate; they never move the vehicle."""

    category: Category = "perception"
    argument_required = True
    moves = False
    needs_airborne = False
    needs_offboard = False

    def timeout_s(self, ctx: SkillContext, argument: str | None) -> float:
        return self.settings.localize_timeout_s + 2.0


@register
class ObjLocalization(_Localization):
    name = names.OBJ_LOCALIZATION
    description = ("Estimate the 3D pose of the queried object (open-vocabulary segmentation fused with depth) "
                   "and store it in working memory. Fails when the object is not in view.")
    argument = "object query"

    async def run(self, ctx: SkillContext, argument: str | None) -> SkillResult:
        assert argument
        est = await ctx.localize_object(argument)
        if not est.found or est.pose is None:
            raise SkillFailed(not_found(argument, est))
        if outside_geofence(est.pose.position, self.settings, 0.05):
            # e.g. depth through a gap or a pose/frame mismatch: never store a target no skill may fly to
            raise SkillFailed(f"{argument} estimate {fmt(est.pose.position)} lies outside the flyable room: "
                              "implausible, not stored; look again")
        mo = ctx.memory.store_object(est, argument)
        text = f"{mo.label} at {fmt(mo.position)}"
        st = ctx.state.value
        if st is not None:
            text += f", {horizontal_distance(mo.position, st.position):.2f} m away horizontally"
        ctx.note(text)
        return SkillResult(f"localized {text} (confidence {est.confidence:.2f})")


@register
class PlacementLocalization(_Localization):
    name = names.PLACEMENT_LOCALIZATION
    description = ("Find the queried support surface in the point cloud and compute a collision-free placement "
                   "pose with a vertical offset for the held object; store it in working memory.")
    argument = "surface query"

    async def run(self, ctx: SkillContext, argument: str | None) -> SkillResult:
        assert argument
        est = await ctx.localize_placement(argument, ctx.memory.held_size)
        if not est.found or est.pose is None:
            raise SkillFailed(not_found(argument, est))
        mo = ctx.memory.store_placement(est, argument)
        text = f"placement spot on the {mo.label} at {fmt(mo.position)}"
        ctx.note(text)
        return SkillResult(f"found {text} (surface z {est.surface_z if est.surface_z is not None else 0:.2f})")
