"""A tiny deterministic world + executor stand-in for reasoner tests (no physics: skill semantics only).

`MiniWorld` keeps which objects exist, which heading sees them, what is localized and held; `apply()`
runs a skill like the executor would and returns its SkillStatus. `MiniWorldPort` plugs it into the loop
directly; `serve_executor()` serves it on a real bus as `executor/skills`, `executor/run_skill`,
`executor/skill_status`, `executor/memory`, `perception/detections` and `autopilot/state`.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field

from services.reasoner.library import default_library
from services.reasoner.loop import World
from services.reasoner.prompt import Observation
from shared import skills as S  # noqa: N812
from shared.action import SKILL_ACTION, ActionServer, ServerGoalHandle
from shared.bus import Bus
from shared.keys import Keys
from shared.messages import (
    CancelGoal,
    CancelReply,
    Detection,
    Detections,
    LandedState,
    MemoryObject,
    OutcomeCode,
    SkillAccept,
    SkillLibrary,
    SkillOutcome,
    SkillRequest,
    SkillState,
    SkillStatus,
    Vec3,
    VehicleState,
    WorkingMemory,
    new_id,
    now_ns,
)


@dataclass
class Thing:
    label: str
    category: str = "object"
    headings: tuple[int, ...] = (0,)
    """Yaw indices (0..7, one per 45 deg yaw_left) from which it is visible."""
    size: tuple[float, float, float] = (0.08, 0.08, 0.1)
    needs_forward: int = 0
    """Forward steps needed before it becomes visible."""
    catalog: tuple[float, float, float] | None = None
    """Its class's catalogued extent standing, as perception reports it (None: no catalogue)."""


@dataclass
class MiniWorld:
    things: list[Thing]
    heading: int = 0
    forward: int = 0
    airborne: bool = False
    localized: dict[str, str] = field(default_factory=dict)
    placements: dict[str, str] = field(default_factory=dict)
    held: str | None = None
    placed_on: dict[str, str] = field(default_factory=dict)
    executed: list[str] = field(default_factory=list)
    checks: list[SkillRequest] = field(default_factory=list)
    """Requests the served executor was asked to check (executor/check_skill), in order."""
    fail_next: dict[str, int] = field(default_factory=dict)
    """Skill -> how many of its next runs fail (fault injection)."""

    def visible(self) -> list[Thing]:
        return [t for t in self.things if self.heading % 8 in t.headings and self.forward >= t.needs_forward
                and t.label != self.held]

    def detections(self) -> tuple[Detection, ...]:
        return tuple(Detection(label=t.label, category=t.category if t.category != "surface" else "surface",
                               size=Vec3(x=t.size[0], y=t.size[1], z=t.size[2]),
                               catalog_size=Vec3(x=t.catalog[0], y=t.catalog[1], z=t.catalog[2]) if t.catalog else None,
                               centroid=Vec3(x=1.0 + 0.1 * i, y=0.0, z=0.5)) for i, t in enumerate(self.visible()))

    def memory(self) -> WorkingMemory:
        return WorkingMemory(
            objects=tuple(MemoryObject(label=v, query=k, position=Vec3(x=1.0)) for k, v in self.localized.items()),
            placements=tuple(MemoryObject(label=v, query=k, position=Vec3(x=1.0)) for k, v in self.placements.items()),
            held_object=self.held, visible=tuple(t.label for t in self.visible()), executed=tuple(self.executed))

    def state(self) -> VehicleState:
        return VehicleState(armed=self.airborne, landed_state=LandedState.IN_AIR if self.airborne
                            else LandedState.ON_GROUND, position=Vec3(z=1.2 if self.airborne else 0.0),
                            link_ok=True, offboard_ok=self.airborne, mode="OFFBOARD" if self.airborne else "HOLD")

    def _find(self, query: str) -> Thing | None:
        q = query.lower()
        for t in self.visible():
            if q == t.label or q in t.label or t.label in q:
                return t
        return None

    def apply(self, req: SkillRequest) -> tuple[SkillState, str, str]:
        """(state, message, perceived)."""
        self.executed.append(f"{req.skill}({req.argument})" if req.argument else req.skill)
        if self.fail_next.get(req.skill, 0) > 0:
            self.fail_next[req.skill] -= 1
            return SkillState.FAILED, f"{req.skill} failed (injected)", ""
        sk = req.skill
        if sk == S.TAKEOFF:
            self.airborne = True
        elif sk == S.YAW_LEFT:
            self.heading = (self.heading + 1) % 8
        elif sk == S.YAW_RIGHT:
            self.heading = (self.heading - 1) % 8
        elif sk == S.FORWARD:
            self.forward += 1
        elif sk == S.OBJ_LOCALIZATION:
            t = self._find(req.argument or "")
            if t is None or t.category != "object":
                return SkillState.FAILED, f"{req.argument} is not visible", ""
            self.localized[req.argument or ""] = t.label
            return SkillState.SUCCEEDED, f"localized {t.label}", f"{t.label} at (1.00, 0.00, 0.50)"
        elif sk == S.GRASP:
            if not self.localized:
                return SkillState.FAILED, "nothing localized: run obj_localization first", ""
            label = list(self.localized.values())[-1]
            self.held = label
            self.localized.clear()
            return SkillState.SUCCEEDED, f"grasped {label}", f"holding {label}"
        elif sk == S.PLACEMENT_LOCALIZATION:
            t = self._find(req.argument or "")
            if t is None or t.category == "object":
                return SkillState.FAILED, f"no surface {req.argument} visible", ""
            self.placements[req.argument or ""] = t.label
            return SkillState.SUCCEEDED, f"placement spot on {t.label}", ""
        elif sk == S.PLACE:
            if self.held is None or not self.placements:
                return SkillState.FAILED, "nothing held or no placement localized", ""
            self.placed_on[self.held] = list(self.placements.values())[-1]
            self.held = None
            self.placements.clear()
        return SkillState.SUCCEEDED, f"{sk} done", ""


class MiniWorldPort(World):
    """The loop's World backed by a MiniWorld, in-process."""

    def __init__(self, world: MiniWorld, library: SkillLibrary | None = None) -> None:
        self.world = world
        self.library = library or default_library()

    async def skill_library(self) -> SkillLibrary:
        return self.library

    async def observe(self, newer_than_ns: int) -> Observation:
        return Observation(image_jpeg=b"\xff\xd8fake-jpeg\xff\xd9", image_stamp_ns=now_ns(), state=self.world.state(),
                           detections=self.world.detections(), memory=self.world.memory())

    async def run_skill(self, request: SkillRequest, timeout: float,
                        ready_timeout: float = 0.0) -> tuple[SkillAccept, SkillStatus | None]:
        goal = new_id("goal-")
        state, msg, perceived = self.world.apply(request)
        status = SkillStatus(goal_id=goal, skill=request.skill, argument=request.argument, state=state,
                             message=msg, outcome=SkillOutcome(perceived=perceived, held_object=self.world.held),
                             task_id=request.task_id, step=request.step, ended_ns=now_ns())
        return SkillAccept(accepted=True, goal_id=goal), status


async def serve_executor(bus: Bus, world: MiniWorld, keys: Keys, *, skill_delay: float = 0.0,
                         library: SkillLibrary | None = None,
                         refuse: Callable[[SkillRequest], tuple[str, SkillOutcome] | None] | None = None,
                         ) -> asyncio.Task:
    """Serve the MiniWorld on the bus like the executor (plus detections and state); returns the publisher task.
    `refuse(request)` adds a precondition (a reason and outcome when the skill may not start), applied like the
    executor's to both run_skill and check_skill."""
    lib = library or default_library()
    lock = asyncio.Lock()
    checks = world.checks

    async def skills(_req: object) -> SkillLibrary:
        return lib

    names = {sk.name for sk in lib.skills}

    def refusal(req: SkillRequest) -> tuple[str, SkillOutcome] | None:
        if req.skill not in names:  # like the executor: an unknown skill is refused, never run
            return f"unknown skill {req.skill!r}", SkillOutcome(code=OutcomeCode.FAILED)
        return refuse(req) if refuse is not None else None

    async def accept(req: SkillRequest) -> SkillAccept:
        no = refusal(req)
        if no is not None:
            return SkillAccept(accepted=False, goal_id=new_id("goal-"), reason=no[0], outcome=no[1])
        return SkillAccept(accepted=True, goal_id=new_id("goal-"))

    async def check(req: SkillRequest) -> SkillAccept:
        checks.append(req)
        no = refusal(req)
        return SkillAccept(accepted=no is None, goal_id="", reason=no[0] if no else "", outcome=no[1] if no else None)

    async def execute(handle: ServerGoalHandle[SkillRequest, SkillStatus]) -> None:
        req, goal = handle.request, handle.goal_id
        async with lock:
            started = now_ns()
            handle.publish(SkillStatus(goal_id=goal, skill=req.skill, argument=req.argument,
                                       state=SkillState.RUNNING, task_id=req.task_id, started_ns=started))
            if skill_delay:
                await asyncio.sleep(skill_delay)
            state, msg, perceived = world.apply(req)
            publish_world()
            handle.publish(SkillStatus(
                goal_id=goal, skill=req.skill, argument=req.argument, state=state, message=msg,
                outcome=SkillOutcome(perceived=perceived, held_object=world.held), task_id=req.task_id,
                step=req.step, started_ns=started, ended_ns=now_ns()))

    def publish_world() -> None:
        bus.publish(keys.detections, Detections(items=world.detections()))
        bus.publish(keys.memory, world.memory())
        bus.publish(keys.autopilot_state, world.state())

    async def cancel_skill(handle: ServerGoalHandle[SkillRequest, SkillStatus], req: CancelGoal) -> CancelReply:
        return CancelReply(accepted=False, reason=f"goal {req.goal_id} cannot be cancelled (skills here end at once)")

    async def restore_memory(req: object) -> CancelReply:
        return CancelReply(accepted=False, reason="this stand-in's memory is its MiniWorld's; it takes no recorded one")

    bus.serve(keys.skills, skills)
    bus.serve(keys.check_skill, check)
    bus.serve(keys.restore_memory, restore_memory)
    ActionServer(bus, SKILL_ACTION, keys.vehicle_id, goal_callback=accept, execute_callback=execute,
                 cancel_callback=cancel_skill).start()

    async def ticker() -> None:
        while True:
            with contextlib.suppress(Exception):
                publish_world()
            await asyncio.sleep(0.1)

    return asyncio.create_task(ticker())
