"""The speculative next step (issue 27): asked for while the skill flies, on the observation its predicted outcome
implies; used only when the skill ended so and the fresh observation agrees, otherwise discarded and asked again."""

from __future__ import annotations

import asyncio
import math
import time

from services.reasoner.backends.base import Backend, ModelReply, ModelRequest
from services.reasoner.backends.rules import render_answer
from services.reasoner.library import default_library
from services.reasoner.loop import TaskRunner, World, policy_context
from services.reasoner.prompt import History, HistoryEntry, Observation
from services.reasoner.settings import ReasonerSettings
from services.reasoner.speculation import Tolerance, assume, disagreement, height_problem
from shared import skills as S  # noqa: N812
from shared.messages import (
    Detection,
    LandedState,
    OutcomeCode,
    Pose,
    SkillAccept,
    SkillFacts,
    SkillLibrary,
    SkillOutcome,
    SkillRequest,
    SkillState,
    SkillStatus,
    SkillToExecute,
    TaskRequest,
    TaskState,
    Vec3,
    VehicleState,
    WorkingMemory,
    new_id,
    now_ns,
)

LIB = default_library()
STEP_M = next(float(p.value) for s in LIB.skills if s.name == S.FORWARD for p in s.parameters
              if p.name == "distance")
TURN_DEG = next(float(p.value) for s in LIB.skills if s.name == S.YAW_LEFT for p in s.parameters
                if p.name == "angle")
CUP = Detection(label="red cup", centroid=Vec3(x=3.0, y=0.2, z=0.8), size=Vec3(x=0.08, y=0.08, z=0.1))


def state(x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> VehicleState:
    return VehicleState(armed=True, landed_state=LandedState.IN_AIR, position=Vec3(x=x, y=y, z=1.2), yaw=yaw,
                        link_ok=True, offboard_ok=True, mode="OFFBOARD")


def observation(x: float = 0.0, yaw: float = 0.0, detections: tuple[Detection, ...] = (CUP,)) -> Observation:
    return Observation(image_jpeg=b"\xff\xd8jpeg\xff\xd9", image_stamp_ns=now_ns(), state=state(x, 0.0, yaw),
                       detections=detections, memory=WorkingMemory())


def assumed(skill: str, argument: str | None = None, obs: Observation | None = None):
    return assume(History(), obs or observation(), LIB, SkillToExecute(skill=skill, argument=argument), 1,
                  "closer to the cup", "", "")


def done_entry(skill: str, end: Pose, argument: str | None = None, code: OutcomeCode = OutcomeCode.SUCCEEDED,
               estimate=None) -> HistoryEntry:
    # the facts the executor reports: a localization names its target
    facts = SkillFacts(target=argument if skill == S.OBJ_LOCALIZATION else None)
    outcome = SkillOutcome(code=code, facts=facts, end_pose=end, estimate=estimate)
    return HistoryEntry(1, skill, argument, "succeeded" if code is OutcomeCode.SUCCEEDED else "failed", "moved",
                        outcome=outcome)


def contexts(guess, real_entry: HistoryEntry, fresh: Observation):
    history = History()
    history.append(real_entry)
    return (policy_context("go", "full", LIB, guess.history, guess.obs),
            policy_context("go", "full", LIB, history, fresh))


def test_a_motion_is_predicted_to_end_where_its_library_step_takes_it() -> None:
    g = assumed(S.FORWARD, obs=observation(yaw=math.pi / 2))
    assert g is not None
    p = g.obs.state.position
    assert abs(p.x) < 1e-9 and abs(p.y - STEP_M) < 1e-9 and p.z == 1.2  # forward is along the heading
    assert g.entry.outcome.code is OutcomeCode.SUCCEEDED and g.entry.outcome.end_pose.position == p
    assert g.history.entries == [g.entry] and g.obs.detections == (CUP,)
    turned = assumed(S.YAW_LEFT)
    assert abs(math.degrees(turned.obs.state.yaw) - TURN_DEG) < 1e-9


def test_a_localization_is_predicted_only_for_what_is_detected() -> None:
    g = assumed(S.OBJ_LOCALIZATION, "red cup")
    assert g is not None
    assert g.entry.outcome.estimate.pose.position == CUP.centroid
    assert [o.label for o in g.obs.memory.objects] == ["red cup"]
    assert assumed(S.OBJ_LOCALIZATION, "banana") is None  # not detected: its outcome is the question
    for skill in (S.GRASP, S.PLACE, S.PLACEMENT_LOCALIZATION, S.DONE):  # outcomes the step is for
        assert assumed(skill, "red cup") is None


def test_the_fresh_observation_must_agree_with_the_assumed_one() -> None:
    g = assumed(S.FORWARD)
    ahead = Pose(position=Vec3(x=STEP_M, z=1.2))
    a, b = contexts(g, done_entry(S.FORWARD, ahead), observation(x=STEP_M))
    assert disagreement(a, b) is None
    # within the tolerance: a few centimetres of drift
    a, b = contexts(g, done_entry(S.FORWARD, Pose(position=Vec3(x=STEP_M + 0.05, z=1.2))), observation(STEP_M + 0.05))
    assert disagreement(a, b) is None
    # a forward that stopped short: the vehicle is elsewhere
    short = Pose(position=Vec3(x=0.1, z=1.2))
    a, b = contexts(g, done_entry(S.FORWARD, short), observation(x=0.1))
    assert "vehicle" in (disagreement(a, b) or "") or "end pose" in (disagreement(a, b) or "")
    # it got there, but the cup is no longer seen
    a, b = contexts(g, done_entry(S.FORWARD, ahead), observation(x=STEP_M, detections=()))
    assert "detections differ" in (disagreement(a, b) or "")
    # it got there but reported another code
    a, b = contexts(g, done_entry(S.FORWARD, ahead, code=OutcomeCode.BLOCKED), observation(x=STEP_M))
    assert "blocked" in (disagreement(a, b) or "")
    assert disagreement(a, b, Tolerance(position_m=10.0)) is not None  # a code is never within a tolerance


def test_a_climb_that_fell_short_disagrees_on_height() -> None:
    g = assumed(S.UP)
    climbed = g.obs.state.position.z
    assert climbed > 1.2
    assert height_problem(climbed, observation()) is not None  # still at 1.2 m
    reached = observation()
    reached.state = reached.state.model_copy(update={"position": Vec3(z=climbed + 0.05)})
    assert height_problem(climbed, reached) is None


def test_a_localization_agrees_when_the_estimate_is_where_the_detection_was() -> None:
    from shared.messages import MemoryObject, ObjectEstimate

    g = assumed(S.OBJ_LOCALIZATION, "red cup")
    here = Pose(position=Vec3(z=1.2))

    def localized(at: Vec3):
        est = ObjectEstimate(query="red cup", found=True, label="red cup", pose=Pose(position=at))
        memory = WorkingMemory(objects=(MemoryObject(label="red cup", query="red cup", position=at),))
        fresh = Observation(state=state(), detections=(CUP,), memory=memory)
        return contexts(g, done_entry(S.OBJ_LOCALIZATION, here, "red cup", estimate=est), fresh)

    assert disagreement(*localized(Vec3(x=3.03, y=0.18, z=0.8))) is None
    assert "estimate" in (disagreement(*localized(Vec3(x=3.5, y=0.2, z=0.8))) or "")


class ApproachBackend(Backend):
    """A stand-in model that answers after `delay` s: forward until the cup is within 2 m, then done; it
    records the pose each answer was made on."""

    kind = "approach-test"
    name = "approach-test"

    def __init__(self, delay: float, world: FlyingWorld) -> None:
        self.delay, self.world = delay, world
        self.asked: list[float] = []
        self.in_flight: list[bool] = []
        """Whether a skill was flying when each answer was made."""

    async def complete(self, request: ModelRequest) -> ModelReply:
        await asyncio.sleep(self.delay)
        ctx = request.context
        self.asked.append(ctx.pose[0] if ctx.pose else math.nan)
        self.in_flight.append(self.world.flying)
        near = [v for v in ctx.visible if v.label == "red cup" and v.distance is not None and v.distance <= 2.0]
        skill = S.DONE if near else S.FORWARD
        return ModelReply(text=render_answer(ctx, skill, None, "approach the cup"), latency_s=self.delay)


class FlyingWorld(World):
    """A vehicle on a line toward a cup at x = 3: forward moves it `step` m (the library says STEP_M) and takes
    `skill_s` seconds; the cup is seen from everywhere."""

    def __init__(self, step: float, skill_s: float) -> None:
        self.x, self.step, self.skill_s = 0.0, step, skill_s
        self.flying = False

    async def skill_library(self) -> SkillLibrary:
        return LIB

    async def observe(self, newer_than_ns: int) -> Observation:
        return observation(self.x)

    async def run_skill(self, request: SkillRequest, timeout: float,
                        ready_timeout: float = 0.0) -> tuple[SkillAccept, SkillStatus | None]:
        goal, start = new_id("goal-"), Pose(position=Vec3(x=self.x, z=1.2))
        self.flying = True
        try:
            await asyncio.sleep(self.skill_s if request.skill == S.FORWARD else 0.0)
        finally:
            self.flying = False
        if request.skill == S.FORWARD:
            self.x += self.step
        end = Pose(position=Vec3(x=self.x, z=1.2))
        return SkillAccept(accepted=True, goal_id=goal), SkillStatus(
            goal_id=goal, skill=request.skill, state=SkillState.SUCCEEDED, message=f"now at ({self.x:.2f}, 0, 1.2)",
            task_id=request.task_id, step=request.step, ended_ns=now_ns(),
            outcome=SkillOutcome(code=OutcomeCode.SUCCEEDED, start_pose=start, end_pose=end))


def forwards_needed(step: float) -> int:
    n = 0
    while math.dist((n * step, 0.0, 1.2), (CUP.centroid.x, CUP.centroid.y, CUP.centroid.z)) > 2.0:
        n += 1
    return n


def run(world: FlyingWorld, backend: ApproachBackend, speculate: bool | None):
    """The task on `world`; `speculate` None: the settings' default."""
    steps: list = []
    settings = ReasonerSettings() if speculate is None else ReasonerSettings(speculate=speculate)
    runner = TaskRunner(TaskRequest(command="approach the red cup"), settings,
                        backend, world, publish_step=steps.append, publish_status=lambda _s: None)
    t0 = time.perf_counter()
    final = asyncio.run(runner.run(asyncio.Event()))
    return final, steps, time.perf_counter() - t0


def test_predicted_steps_are_used_and_the_model_is_not_waited_for() -> None:
    world = FlyingWorld(STEP_M, skill_s=0.6)
    backend = ApproachBackend(0.1, world)
    final, steps, _ = run(world, backend, speculate=True)
    assert final.state is TaskState.SUCCEEDED, final.message
    skills = [s.ste.skill for s in steps]
    n_forward = skills.count(S.FORWARD)
    assert skills == [S.FORWARD] * n_forward + [S.DONE] and n_forward == forwards_needed(STEP_M)
    # every step after the first was asked while the forward before it flew, and used
    assert [s.speculative for s in steps] == [False] + [True] * n_forward
    assert final.speculations == final.speculations_used == n_forward
    assert final.model_calls == sum(len(s.calls) for s in steps) == len(steps)
    # each answer after the first was made while the forward before it flew (the 0.1 s answer during the 0.6 s
    # flight, on one event loop: the order of the two timers is fixed), so the step waited for none of it
    assert backend.in_flight == [False] + [True] * n_forward
    assert all(s.timing.model_s < s.calls[0].latency_s for s in steps[1:])


def test_a_skill_that_ends_elsewhere_discards_the_speculation_and_asks_again() -> None:
    # every forward covers 0.3 x the step: each speculation assumed the vehicle one full step ahead
    world = FlyingWorld(0.3 * STEP_M, skill_s=0.5)
    backend = ApproachBackend(0.05, world)
    final, steps, _ = run(world, backend, speculate=True)
    assert final.state is TaskState.SUCCEEDED, final.message
    assert final.speculations >= 3 and final.speculations_used == 0
    assert not any(s.speculative for s in steps)
    # each answer used was made on the pose the vehicle really had
    assert final.model_calls == len(steps)
    asked_fresh = [x for x, flying in zip(backend.asked, backend.in_flight, strict=True) if not flying]
    assert len(asked_fresh) == len(steps)
    assert all(abs(x - i * 0.3 * STEP_M) < 1e-9 for i, x in enumerate(asked_fresh)), asked_fresh
    # the last answer (done) came when the cup was really within 2 m
    x_done = backend.asked[-1]
    assert 3.0 - x_done <= 2.0 + 1e-9


def test_speculation_is_off_by_default(monkeypatch) -> None:
    monkeypatch.delenv("AERMANI_REASONER_SPECULATE", raising=False)
    assert ReasonerSettings().speculate is False
    world = FlyingWorld(STEP_M, skill_s=0.05)
    final, steps, _ = run(world, ApproachBackend(0.01, world), speculate=None)
    assert final.state is TaskState.SUCCEEDED
    assert final.speculations == 0 and not any(s.speculative for s in steps)
