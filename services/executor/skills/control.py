"""Control and operator skills: done (the policy ends the task), takeoff, land, hold."""

from __future__ import annotations

from typing import ClassVar

from services.executor.context import SkillContext
from services.executor.envelope import airborne
from services.executor.registry import Category, Skill, SkillResult, register
from services.executor.skills.common import fmt
from shared import skills as names
from shared.messages import (
    HoldCommand,
    LandCommand,
    SkillParameter,
    TakeoffCommand,
)

# --------------------------------------------------------------------------- control and operator skills


@register
class Done(Skill):
    """The policy declares the task complete."""

    name = names.DONE
    category: ClassVar[Category] = "control"
    description = "Declare the task complete; the episode ends."
    moves = False
    needs_airborne = False
    needs_offboard = False

    async def run(self, ctx: SkillContext, argument: str | None) -> SkillResult:
        return SkillResult("task declared complete")


class _Operator(Skill):
    """Skills the operator (or the loop itself) runs; never offered to the model."""

    category: ClassVar[Category] = "operator"
    policy_visible = False
    needs_offboard = False


@register
class Takeoff(_Operator):
    """Arm and climb to the flight altitude (the bridge arms and judges arrival)."""

    name = names.TAKEOFF
    description = "Arm and take off to {s.flight_altitude:g} m."
    needs_airborne = False

    def parameters(self) -> tuple[SkillParameter, ...]:
        return (SkillParameter(name="altitude", value=self.settings.flight_altitude, unit="m"),)

    def check(self, ctx: SkillContext, argument: str | None) -> str | None:
        if airborne(ctx.state.value):
            return "already airborne: takeoff is only possible from the ground"
        return None

    def timeout_s(self, ctx: SkillContext, argument: str | None) -> float:
        return self.settings.takeoff_timeout_s

    async def run(self, ctx: SkillContext, argument: str | None) -> SkillResult:
        # The bridge owns arming and judging arrival at the takeoff altitude (PX4's ACKs, its tolerance); its
        # result says whether the vehicle is airborne in OFFBOARD.
        s = self.settings
        res = await ctx.command(TakeoffCommand(altitude=s.flight_altitude), timeout=s.takeoff_timeout_s)
        # Let the state stream catch up with the bridge's verdict before the next skill's preconditions.
        st = await ctx.wait_for(airborne, s.state_max_age_s * 4, "airborne state after takeoff")
        return SkillResult(f"airborne at {fmt(st.position)} ({res.message})")


@register
class Land(_Operator):
    """Land where the vehicle is."""

    name = names.LAND
    description = "Land at the current position."

    def timeout_s(self, ctx: SkillContext, argument: str | None) -> float:
        return self.settings.land_timeout_s

    async def run(self, ctx: SkillContext, argument: str | None) -> SkillResult:
        await ctx.command(LandCommand())
        st = await ctx.wait_for(lambda st: not airborne(st), self.settings.land_timeout_s, "touchdown")
        return SkillResult(f"landed at {fmt(st.position)}")


@register
class Hold(_Operator):
    """Hold the current position (also the loop's failure path)."""

    name = names.HOLD
    description = "Hold the current position."
    needs_airborne = False

    async def run(self, ctx: SkillContext, argument: str | None) -> SkillResult:
        await ctx.command(HoldCommand())
        return SkillResult(f"holding at {fmt(ctx.current().position)}")
