"""Motion primitives (paper Table II): fixed body-frame steps and yaw turns."""

from __future__ import annotations

import math
from typing import ClassVar

from services.executor.context import SkillContext
from services.executor.envelope import altitude_problem, geofence_problem, wrap
from services.executor.registry import Category, Skill, SkillResult, register
from services.executor.skills.common import Refusal, coded, fmt
from shared import skills as names
from shared.messages import (
    OutcomeCode,
    SkillParameter,
    Vec3,
    VehicleState,
)

# --------------------------------------------------------------------------- motion primitives


class _Step(Skill):
    """A fixed body-frame step: translation (fx, fy, fz) times the step size, or a yaw turn."""

    category: ClassVar[Category] = "motion"
    body: tuple[float, float, float] = (0.0, 0.0, 0.0)
    turn: float = 0.0  # +1 left (counter-clockwise), -1 right

    def _distance(self) -> float:
        return self.settings.vertical_step if self.body[2] else self.settings.horizontal_step

    def parameters(self) -> tuple[SkillParameter, ...]:
        s = self.settings
        if self.turn:
            return (SkillParameter(name="angle", value=s.yaw_step_deg, unit="deg"),)
        return (SkillParameter(name="distance", value=self._distance(), unit="m"),
                SkillParameter(name="speed", value=s.translation_speed, unit="m/s"))

    def target(self, st: VehicleState) -> tuple[Vec3, float]:
        p = st.position
        step = self.settings.yaw_step_deg if self.turn else self._distance()
        x, y, z, yaw = names.motion_end(self.name, p.x, p.y, p.z, st.yaw, step)
        if self.turn:
            return p, wrap(yaw)
        return Vec3(x=x, y=y, z=z), yaw

    def check(self, ctx: SkillContext, argument: str | None) -> str | None:
        st = ctx.state.value
        assert st is not None
        if self.turn:
            return None
        target, _ = self.target(st)
        fence = geofence_problem(target, self.settings, f"{self.name} target")
        if fence:
            return Refusal(fence, OutcomeCode.OUT_OF_REACH)
        problem = altitude_problem(target.z, self.settings, what=f"{self.name} target")
        if problem:
            return problem
        held = ctx.memory.held_size if ctx.memory.held else None
        if self.body[2] < 0 and held is not None:
            # Down with an object in the fingers: it hangs below the gripper point and must stay off the floor.
            bottom = target.z + self.settings.gripper_offset_z - held.z
            if bottom < 0.05:
                return (f"{self.name} would put the held object's bottom at {bottom:.2f} m, at the floor; nothing "
                        "was moved")
        if self.body[0] > 0:
            # Only the forward direction is seen by the camera; other directions rely on the geofence. The
            # corridor reaches down to the bottom of a held object (it hangs below the gripper point).
            below = self.settings.clearance_below
            if held is not None:
                below = max(below, -self.settings.gripper_offset_z + held.z + 0.05)
            return ctx.clearance.forward_problem(st.position.z, self._distance(), self.settings, below=below)
        return None

    def timeout_s(self, ctx: SkillContext, argument: str | None) -> float:
        s = self.settings
        if self.turn:
            return math.radians(s.yaw_step_deg) / math.radians(30.0) + s.motion_slack_s
        return self._distance() / s.translation_speed + s.motion_slack_s

    async def run(self, ctx: SkillContext, argument: str | None) -> SkillResult:
        st = ctx.current()
        target, yaw = self.target(st)
        end = await ctx.goto(target, yaw, self.settings.translation_speed, what=f"{self.name} target",
                             timeout=self.timeout_s(ctx, argument))
        moved = math.dist(st.position.as_tuple(), end.position.as_tuple())
        return coded(f"{self.name} done: now at {fmt(end.position)}, yaw {math.degrees(end.yaw):.0f} deg",
                     distance_m=round(moved, 3))


# Paper Table II as a table: (name, Skill Library text); the body-frame direction or turn of each is
# shared.skills.STEP_AXES / TURNS (the reasoner predicts a motion's end from them: speculation.py).
_PRIMITIVES: tuple[tuple[str, str], ...] = (
    (names.YAW_LEFT, "Rotate left (counter-clockwise) about the body z-axis by {s.yaw_step_deg:g} deg, to look "
     "around."),
    (names.YAW_RIGHT, "Rotate right (clockwise) about the body z-axis by {s.yaw_step_deg:g} deg, to look around."),
    (names.FORWARD, "Translate forward along the body x-axis by {s.horizontal_step:g} m, to approach a target "
     "(refused when the depth image shows an obstacle in the way)."),
    (names.BACKWARD, "Translate backward along the body x-axis by {s.horizontal_step:g} m, to retreat."),
    (names.LEFT, "Translate left along the body y-axis by {s.horizontal_step:g} m, to correct lateral "
     "misalignment."),
    (names.RIGHT, "Translate right along the body y-axis by {s.horizontal_step:g} m, to correct lateral "
     "misalignment."),
    (names.UP, "Climb by {s.vertical_step:g} m, to gain clearance or see more of the scene."),
    (names.DOWN, "Descend by {s.vertical_step:g} m, to reach manipulation height or see closer."),
)

for _name, _text in _PRIMITIVES:
    register(type(_name.title().replace("_", ""), (_Step,), {
        "name": _name, "description": _text, "body": names.STEP_AXES.get(_name, (0.0, 0.0, 0.0)),
        "turn": names.TURNS.get(_name, 0.0), "__module__": __name__,
        "__doc__": f"Motion primitive `{_name}` (paper Table II)."}))
