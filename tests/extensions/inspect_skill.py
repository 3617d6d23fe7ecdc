"""A skill that lives only in this test module: one class plus its registration, nothing else changed."""

from __future__ import annotations

from services.executor.context import SkillContext
from services.executor.registry import Skill, SkillResult, register
from shared.messages import SkillParameter, Vec3


@register
class InspectBelow(Skill):
    """Drop to the lowest flight altitude to look at something low."""

    name = "inspect_below"
    category = "motion"
    description = "Drop to {s.min_altitude:g} m to inspect something low, then report."

    def parameters(self) -> tuple[SkillParameter, ...]:
        return (SkillParameter(name="altitude", value=self.settings.min_altitude, unit="m"),)

    def check(self, ctx: SkillContext, argument: str | None) -> str | None:
        return None if ctx.memory.held is None else "cannot inspect while holding an object"

    async def run(self, ctx: SkillContext, argument: str | None) -> SkillResult:
        st = ctx.current()
        p = st.position
        await ctx.goto(Vec3(x=p.x, y=p.y, z=self.settings.min_altitude), st.yaw, self.settings.descent_speed)
        return SkillResult("at inspection height")
