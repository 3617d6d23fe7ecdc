"""The reasoner's link gate (issue 18): while the vehicle's state is missing, old (a silent or dead bridge
leaves its last state behind, still showing `link_ok`), or shows a lost link, no skill is issued and no step
is spent; the task continues when the link is back, or holds and fails with the reason after `link_wait_s`."""

from __future__ import annotations

import asyncio
import dataclasses
from collections.abc import Callable

from services.reasoner.backends.rules import RulesBackend
from services.reasoner.loop import TaskRunner
from services.reasoner.prompt import Observation
from services.reasoner.settings import ReasonerSettings
from shared.errors import NoResponder
from shared.messages import (
    LandedState,
    SkillAccept,
    SkillRequest,
    SkillState,
    SkillStatus,
    TaskRequest,
    TaskState,
    VehicleState,
)
from tests.reasoner.fake_world import MiniWorld, MiniWorldPort, Thing

TABLE = Thing("table", "surface", headings=(0, 1, 7), size=(1.2, 0.8, 0.75))
COMMAND = "Pick up the red cup and place it on the table"


class SilentBridgeWorld(MiniWorldPort):
    """After the take-off, the vehicle state stops arriving: observations carry the last state, ageing; after
    `silent_observations` observations it arrives again (never, if None)."""

    def __init__(self, world: MiniWorld, silent_observations: int | None) -> None:
        super().__init__(world)
        self.silent_left = silent_observations
        self.gated = 0
        self.holds: list[str] = []

    async def observe(self, newer_than_ns: int) -> Observation:
        obs = await super().observe(newer_than_ns)
        if self.world.executed == ["takeoff"] and (self.silent_left is None or self.silent_left > 0):
            self.gated += 1
            if self.silent_left is not None:
                self.silent_left -= 1
            return dataclasses.replace(obs, state_age_s=3.0 + 0.5 * self.gated)
        return obs

    async def run_skill(self, request: SkillRequest, timeout: float,
                        ready_timeout: float = 0.0) -> tuple[SkillAccept, SkillStatus | None]:
        if request.skill == "hold":
            self.holds.append(request.task_id or "")
        return await super().run_skill(request, timeout, ready_timeout)


def _run(port: SilentBridgeWorld, **settings: object):
    steps: list = []
    runner = TaskRunner(TaskRequest(command=COMMAND), ReasonerSettings(max_steps=40, **settings), RulesBackend(),
                        port, publish_step=steps.append, publish_status=lambda _s: None)
    return asyncio.run(runner.run(asyncio.Event())), steps


def test_a_silent_bridge_stops_the_skills_then_the_task_holds_and_fails_with_the_reason() -> None:
    w = MiniWorld([Thing("red cup"), TABLE])
    port = SilentBridgeWorld(w, silent_observations=None)
    final, steps = _run(port, link_wait_s=1.0, state_stale_s=2.0)
    assert final.state is TaskState.FAILED
    assert "no vehicle state from the autopilot bridge for" in final.message, final.message
    assert w.executed == ["takeoff", "hold"], "a skill other than the gate's hold ran while the state was stale"
    assert port.gated >= 2 and port.holds, "the gate neither waited nor held"
    assert steps == [], "a step was spent while waiting for the link (the take-off comes before the first step)"


def test_the_task_continues_when_the_state_comes_back() -> None:
    w = MiniWorld([Thing("red cup"), TABLE])
    port = SilentBridgeWorld(w, silent_observations=3)
    final, _ = _run(port, link_wait_s=30.0, state_stale_s=2.0)
    assert final.state is TaskState.SUCCEEDED, final.message
    assert port.gated == 3 and not port.holds
    assert w.placed_on == {"red cup": "table"}


class LandingWorld(MiniWorldPort):
    """After the take-off PX4 brings the vehicle down on its own (AUTO.LAND, as after a bridge kill): the
    state says landing, with offboard control gone."""

    def __init__(self, world: MiniWorld) -> None:
        super().__init__(world)
        self.skills: list[str] = []

    async def observe(self, newer_than_ns: int) -> Observation:
        obs = await super().observe(newer_than_ns)
        if self.world.executed and obs.state is not None:
            landing = obs.state.model_copy(update={"landed_state": LandedState.LANDING, "offboard_ok": False,
                                                   "mode": "AUTO.LAND"})
            return dataclasses.replace(obs, state=landing)
        return obs

    async def run_skill(self, request: SkillRequest, timeout: float,
                        ready_timeout: float = 0.0) -> tuple[SkillAccept, SkillStatus | None]:
        self.skills.append(request.skill)
        return await super().run_skill(request, timeout, ready_timeout)


def test_no_skill_while_the_vehicle_lands_without_offboard_control() -> None:
    port = LandingWorld(MiniWorld([Thing("red cup"), TABLE]))
    final, steps = _run(port, link_wait_s=1.0)
    assert final.state is TaskState.FAILED
    assert "offboard control is not healthy (mode AUTO.LAND, landing)" in final.message, final.message
    assert port.skills == ["takeoff", "hold"] and steps == []


class GoneExecutorWorld(MiniWorldPort):
    """The executor stops answering after the take-off: `back_after` more calls fail with NoResponder (the
    reasoner's retry waits for it with `ready_timeout`), None for an executor that never comes back."""

    def __init__(self, world: MiniWorld, back_after: int | None) -> None:
        super().__init__(world)
        self.failing = back_after
        self.calls: list[tuple[str, float]] = []

    async def run_skill(self, request: SkillRequest, timeout: float,
                        ready_timeout: float = 0.0) -> tuple[SkillAccept, SkillStatus | None]:
        self.calls.append((request.skill, ready_timeout))
        if self.world.executed and (self.failing is None or self.failing > 0):
            if self.failing is not None:
                self.failing -= 1
            raise NoResponder(f"no queryable for {request.skill}")
        return await super().run_skill(request, timeout, ready_timeout)


def test_an_executor_that_comes_back_gets_the_same_skill_again_without_a_spent_step() -> None:
    w = MiniWorld([Thing("red cup"), TABLE])
    port = GoneExecutorWorld(w, back_after=1)
    final, steps = _run(port, link_wait_s=5.0)
    assert final.state is TaskState.SUCCEEDED, final.message
    first, retry = port.calls[1], port.calls[2]
    assert first[0] == retry[0] and (first[1], retry[1]) == (0.0, 5.0)  # the same skill, now waiting for a server
    assert all("unreachable" not in (s.skill_message or "") for s in steps)


def test_an_absent_executor_ends_the_task_after_one_step() -> None:
    w = MiniWorld([Thing("red cup"), TABLE])
    port = GoneExecutorWorld(w, back_after=None)
    final, steps = _run(port, link_wait_s=5.0)
    assert final.state is TaskState.FAILED
    assert "executor unreachable for 5 s" in final.message, final.message
    assert len(steps) == 1 and steps[0].skill_state is SkillState.FAILED  # the one step, logged with the reason
    assert "executor unreachable" in steps[0].skill_message


class AbortSeenElsewhereFirst(MiniWorldPort):
    """An abort reaches the executor or the bridge before this loop (the bus delivers one message to its three
    subscribers in any order), during the skill `at`; the loop's own abort signal is never set.
    `where="executor"`: the executor cancels the running skill (ABORTED). `"bridge"`: the bridge stops the
    command and latches its takeover ("aborted by ...") in the state; the executor reports the skill ABORTED
    (AbortSeen). `"between"`: the skill ends first, then only the bridge's latched takeover shows the abort."""

    def __init__(self, world: MiniWorld, where: str, at: str) -> None:
        super().__init__(world)
        self.where, self.at, self.override_ns = where, at, 0

    async def observe(self, newer_than_ns: int) -> Observation:
        obs = await super().observe(newer_than_ns)
        if self.override_ns and obs.state is not None:
            obs = dataclasses.replace(obs, state=obs.state.model_copy(update={
                "override": "aborted by gateway: operator", "override_ns": self.override_ns}))
        return obs

    async def run_skill(self, request: SkillRequest, timeout: float,
                        ready_timeout: float = 0.0) -> tuple[SkillAccept, SkillStatus | None]:
        accept, status = await super().run_skill(request, timeout, ready_timeout)
        if request.skill == self.at and status is not None and not self.override_ns:
            if self.where != "executor":
                self.override_ns = 1
            if self.where != "between":
                status = status.model_copy(update={"state": SkillState.ABORTED,
                                                   "message": f"{request.skill} aborted (gateway: operator)"})
        return accept, status


def test_an_abort_that_reaches_the_executor_or_the_bridge_first_still_ends_the_task_aborted() -> None:
    """The race CI met (tests/ros2/test_live.py): an abort during the take-off ended the task `failed`
    ("takeoff aborted") when the executor's answer overtook the loop's own abort signal."""
    for where in ("executor", "bridge", "between"):
        for at in ("takeoff", "obj_localization"):
            w = MiniWorld([Thing("red cup"), TABLE])
            final, _ = _run(AbortSeenElsewhereFirst(w, where, at))
            assert final.state is TaskState.ABORTED, (where, at, final.message)
            assert "grasp" not in w.executed, (where, at, w.executed)


def test_px4_holding_in_the_air_is_no_reason_to_wait_but_a_landing_or_a_pilot_is() -> None:
    """A new task that finds PX4 holding in the air (AUTO.LOITER: its offboard-loss Hold after a bridge restart)
    issues its skills, which take the vehicle back into OFFBOARD; PX4 landing or returning, or a pilot's
    POSCTL, still gate. (A takeover during the task ends it before the gate: _authority_end.)"""
    port = MiniWorldPort(MiniWorld([Thing("red cup"), TABLE]))
    runner = TaskRunner(TaskRequest(command=COMMAND), ReasonerSettings(), RulesBackend(), port,
                        publish_step=lambda _s: None, publish_status=lambda _s: None)
    obs = asyncio.run(port.observe(0))
    assert obs.state is not None

    def problem(mode: str, landed: LandedState) -> str | None:
        st = obs.state.model_copy(update={"armed": True, "offboard_ok": False, "mode": mode, "landed_state": landed})
        return runner._link_problem(dataclasses.replace(obs, state=st))

    assert problem("AUTO.LOITER", LandedState.IN_AIR) is None
    for mode, landed in (("AUTO.LAND", LandedState.LANDING), ("AUTO.RTL", LandedState.IN_AIR),
                         ("POSCTL", LandedState.IN_AIR), ("AUTO.LOITER", LandedState.LANDING)):
        assert "offboard control is not healthy" in (problem(mode, landed) or ""), (mode, landed)


class LaggingStateWorld(MiniWorldPort):
    """The vehicle state lags the skill statuses, as Zenoh allows across keys: the first `lagging` observations
    after the take-off carry the state sampled before the take-off took effect (grounded, its own old stamp).
    With `lands_after` set, the vehicle really comes down (a fresh grounded state) once that skill has run."""

    def __init__(self, world: MiniWorld, lagging: int, lands_after: str | None = None) -> None:
        super().__init__(world)
        self.before = world.state()  # sampled on the ground, before anything ran
        self.lagging = lagging
        self.lands_after = lands_after

    async def observe(self, newer_than_ns: int) -> Observation:
        obs = await super().observe(newer_than_ns)
        if self.world.executed == ["takeoff"] and self.lagging > 0:
            self.lagging -= 1
            return dataclasses.replace(obs, state=self.before)
        if self.lands_after is not None and self.lands_after in self.world.executed:
            self.world.airborne = False  # PX4 landed it (a failsafe, a pilot): sampled now
            return dataclasses.replace(obs, state=self.world.state())
        return obs


def test_a_grounded_state_from_before_the_takeoff_does_not_end_the_task() -> None:
    """ci of stop 40: the take-off's status overtook the airborne state, and the task ended 'landed without being
    asked' one second in. A grounded state sampled before the skill ended says nothing about its effect."""
    w = MiniWorld([Thing("red cup"), TABLE])
    port = LaggingStateWorld(w, lagging=3)
    final, _steps = _run(port)
    assert final.state is TaskState.SUCCEEDED, final.message
    assert port.lagging == 0  # the stale state was seen, and waited out
    assert w.placed_on == {"red cup": "table"}


def test_a_vehicle_that_comes_down_mid_task_ends_it_with_the_reason() -> None:
    w = MiniWorld([Thing("red cup"), TABLE])
    port = LaggingStateWorld(w, lagging=0, lands_after="grasp(red cup)")
    final, _steps = _run(port)
    assert final.state is TaskState.FAILED
    assert final.message.startswith("the vehicle landed without being asked (mode HOLD"), final.message
    assert w.executed[-1] == "grasp(red cup)" and "place" not in w.executed


class EarlyStatesWorld(MiniWorldPort):
    """The first `count` observations (all of them, if None) carry `early(state)` instead of the vehicle's state:
    None for a first state still on its way (a new route under load), or a state without the autopilot's facts."""

    def __init__(self, world: MiniWorld, count: int | None,
                 early: Callable[[VehicleState], VehicleState | None]) -> None:
        super().__init__(world)
        self.left = count
        self.early = early
        self.replaced = 0

    async def observe(self, newer_than_ns: int) -> Observation:
        obs = await super().observe(newer_than_ns)
        if self.left is None or self.left > 0:
            self.replaced += 1
            if self.left is not None:
                self.left -= 1
            assert obs.state is not None
            return dataclasses.replace(obs, state=self.early(obs.state))
        return obs


def no_state(_st: VehicleState) -> None:
    return None


def no_link_yet(st: VehicleState) -> VehicleState:
    """A bridge that has just started: no heartbeat yet, so link down, armed and landed state unknown."""
    return st.model_copy(update={"link_ok": False, "armed": False, "landed_state": LandedState.UNKNOWN})


def test_the_takeoff_waits_for_the_first_vehicle_state() -> None:
    """ci of stop 41: no state had arrived when the task started, the take-off was skipped as if the vehicle
    were airborne, and the first grounded state to arrive ended the task 'landed without being asked'."""
    w = MiniWorld([Thing("red cup"), TABLE])
    port = EarlyStatesWorld(w, 5, no_state)
    final, _steps = _run(port)
    assert final.state is TaskState.SUCCEEDED, final.message
    assert port.replaced == 5 and w.executed[0] == "takeoff"
    assert w.placed_on == {"red cup": "table"}


def test_no_vehicle_state_at_all_fails_the_task_before_anything_flies() -> None:
    w = MiniWorld([Thing("red cup"), TABLE])
    port = EarlyStatesWorld(w, None, no_state)
    final, steps = _run(port, link_wait_s=1.0)
    assert final.state is TaskState.FAILED
    assert final.message == "no vehicle state from the autopilot bridge within 1 s; nothing took off", final.message
    assert w.executed == [] and steps == [] and port.replaced >= 2


def test_the_takeoff_waits_for_the_autopilots_link_and_fails_without_it() -> None:
    w = MiniWorld([Thing("red cup"), TABLE])
    final, _ = _run(EarlyStatesWorld(w, 4, no_link_yet))
    assert final.state is TaskState.SUCCEEDED, final.message
    assert w.executed[0] == "takeoff" and w.placed_on == {"red cup": "table"}
    w = MiniWorld([Thing("red cup"), TABLE])
    final, steps = _run(EarlyStatesWorld(w, None, no_link_yet), link_wait_s=1.0)
    assert final.state is TaskState.FAILED
    assert final.message == "no link to the autopilot within 1 s; nothing took off", final.message
    assert w.executed == [] and steps == []
