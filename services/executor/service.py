"""The executor service: run one skill at a time on request, publish its status, hold on abort."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from dataclasses import dataclass, field

from services.executor.context import AuthorityLost, SkillContext, SkillFailed, StateTracker, pose_of
from services.executor.envelope import DepthClearance, airborne, offboard_problem, state_problem
from services.executor.memory import Memory
from services.executor.registry import Skill, build_library
from services.executor.settings import ExecutorSettings
from shared.bus import Bus
from shared.errors import BusError, DecodeError
from shared.frames import DEFAULT_INTRINSICS
from shared.keys import FLEET_ABORT, BoundTopic
from shared.messages import (
    Abort,
    AbortAck,
    AutopilotResult,
    CancelGoal,
    CancelReply,
    GripperState,
    HoldCommand,
    OutcomeCode,
    SkillAccept,
    SkillFacts,
    SkillLibrary,
    SkillOutcome,
    SkillRequest,
    SkillState,
    SkillStatus,
    new_id,
    now_ns,
)
from shared.sensors import parse_calibration, parse_raw16

UNKNOWN_HELD = "unidentified object"
"""What memory calls an object the gripper reports holding that this executor did not grasp itself."""
log = logging.getLogger("aermani.executor")


@dataclass
class Goal:
    """A skill goal the executor accepted: the request, the skill instance and the tasks running it."""

    goal_id: str
    request: SkillRequest
    skill: Skill
    started_ns: int = field(default_factory=now_ns)
    start_pose: object = None
    task: asyncio.Task | None = None  # the skill's own run()
    runner: asyncio.Task | None = None  # supervises run(): timeout, status
    aborted_by: str = ""


class Executor:
    """Serves the skill library over the bus: accepts skill goals, runs one at a time, publishes status and memory."""

    def __init__(self, bus: Bus, settings: ExecutorSettings) -> None:
        self.bus = bus
        self.settings = settings
        self.keys = settings.keys
        self.skills = build_library(settings)
        self.memory = Memory(on_change=self._memory_changed)
        self.state = StateTracker()
        self.clearance = DepthClearance(DEFAULT_INTRINSICS, mount=settings.mount)
        self.ctx = SkillContext(bus, settings, self.memory, self.state, self.clearance)
        self.goal: Goal | None = None
        self._memory_dirty = False
        self._background: set[asyncio.Task] = set()

    # ---- publication

    def _memory_changed(self) -> None:
        # Coalesce bursts of changes into one publication on the next loop turn.
        if not self._memory_dirty:
            self._memory_dirty = True
            asyncio.get_running_loop().call_soon(self._publish_memory)

    def _publish_memory(self) -> None:
        self._memory_dirty = False
        with contextlib.suppress(BusError):
            self.bus.publish(self.keys.memory, self.memory.snapshot())

    def _status(self, goal_id: str, req: SkillRequest, state: SkillState, message: str = "",
                outcome: SkillOutcome | None = None, started_ns: int = 0) -> SkillStatus:
        st = SkillStatus(goal_id=goal_id, request_id=req.request_id, task_id=req.task_id, step=req.step,
                         skill=req.skill, argument=req.argument, state=state, message=message,
                         outcome=outcome or SkillOutcome(), started_ns=started_ns,
                         ended_ns=now_ns() if state.terminal else 0)
        self.bus.publish(self.keys.skill_status, st)
        return st

    def library(self) -> SkillLibrary:
        return SkillLibrary(skills=tuple(sk.spec() for sk in self.skills.values()))

    # ---- preconditions

    def validate(self, req: SkillRequest) -> tuple[Skill | None, str | None, str]:
        """(skill, argument, '') when it may start, else (None, None, reason for the model)."""
        skill = self.skills.get(req.skill.strip())
        if skill is None:
            names = ", ".join(n for n, sk in self.skills.items() if sk.policy_visible)
            return None, None, f"unknown skill {req.skill!r}; choose one of: {names}"
        arg = (req.argument or "").strip() or None
        if skill.argument is None:
            arg = None  # a stray argument to a skill without one is harmless
        elif skill.argument_required and not arg:
            return None, None, f"{skill.name} needs an argument ({skill.argument})"
        st = self.state.value
        if skill.moves:
            problem = state_problem(st, self.state.age_s, self.settings)
            if problem:
                return None, None, problem
            assert st is not None
            if skill.needs_airborne and not airborne(st):
                return None, None, "the vehicle is on the ground: only takeoff is possible now; nothing was moved"
            if skill.needs_offboard:
                problem = offboard_problem(st)
                if problem:
                    return None, None, problem
        elif st is None and skill.category == "manipulation":
            return None, None, "no vehicle state received yet"
        try:
            problem = skill.check(self.ctx, arg)
        except Exception as exc:  # a broken check must refuse, never fly
            log.exception("precondition of %s failed", skill.name)
            problem = f"precondition check of {skill.name} failed: {exc}"
        if problem:
            return None, None, problem
        return skill, arg, ""

    # ---- run_skill

    async def handle_run_skill(self, req: SkillRequest) -> SkillAccept:
        goal_id = new_id("goal-")
        self.memory.begin_task(req.task_id)
        if self.goal is not None:
            reason = (f"skill {self.goal.request.skill} is still running (goal {self.goal.goal_id}): wait for its "
                      "status or abort it; nothing was started")
            self._status(goal_id, req, SkillState.REJECTED, reason)
            return SkillAccept(accepted=False, goal_id=goal_id, reason=reason)
        skill, arg, reason = self.validate(req)
        if skill is None:
            self._status(goal_id, req, SkillState.REJECTED, reason)
            log.info("rejected %s(%s): %s", req.skill, req.argument or "", reason)
            return SkillAccept(accepted=False, goal_id=goal_id, reason=reason)
        goal = Goal(goal_id, req, skill, start_pose=pose_of(self.state.value))
        self.goal = goal  # set before any await: one skill at a time
        self.ctx.reset_outcome(req.task_id)
        self._status(goal_id, req, SkillState.RUNNING, f"{skill.name} started", started_ns=goal.started_ns,
                     outcome=SkillOutcome(start_pose=goal.start_pose))
        goal.task = asyncio.create_task(skill.run(self.ctx, arg), name=f"skill.{skill.name}")
        goal.runner = asyncio.create_task(self._supervise(goal, arg), name=f"goal.{goal_id}")
        log.info("started %s(%s) goal %s", skill.name, arg or "", goal_id)
        return SkillAccept(accepted=True, goal_id=goal_id)

    async def _hold(self) -> AutopilotResult | None:
        try:
            return await self.bus.query(self.keys.autopilot_command, HoldCommand(), timeout=2.0)
        except BusError as exc:
            log.warning("hold command failed: %s", exc)
            return None

    async def _supervise(self, goal: Goal, arg: str | None) -> None:
        assert goal.task is not None
        skill = goal.skill
        timeout = skill.timeout_s(self.ctx, arg)
        state, message = SkillState.FAILED, ""
        code: OutcomeCode | None = None  # what the skill itself declared (grasp and place measure theirs)
        facts = SkillFacts()
        try:
            done, _ = await asyncio.wait({goal.task}, timeout=timeout)
            if goal.aborted_by and not done:
                done, _ = await asyncio.wait({goal.task}, timeout=1.0)
            if not done:
                goal.task.cancel()
                with contextlib.suppress(BaseException):
                    await goal.task
                state, message = SkillState.TIMEOUT, f"{skill.name} did not finish within {timeout:.0f} s; holding"
                if skill.moves:
                    await self._hold()
            elif goal.task.cancelled() or (goal.aborted_by and isinstance(goal.task.exception(),
                                                                          asyncio.CancelledError)):
                state = SkillState.ABORTED
                message = f"{skill.name} aborted ({goal.aborted_by or 'cancelled'}); holding position"
            else:
                exc = goal.task.exception()
                if exc is None:
                    result = goal.task.result()
                    state, message = SkillState.SUCCEEDED, result.message
                    code, facts = result.code, result.facts or facts
                elif isinstance(exc, TimeoutError):
                    state, message = SkillState.TIMEOUT, f"{skill.name}: {exc}; holding"
                    if skill.moves:
                        await self._hold()
                elif isinstance(exc, AuthorityLost) and goal.aborted_by:
                    # The bridge saw the abort first (it holds on its own): still this executor's abort.
                    state = SkillState.ABORTED
                    message = f"{skill.name} aborted ({goal.aborted_by}); holding position"
                elif isinstance(exc, AuthorityLost):
                    state, message = SkillState.FAILED, str(exc)  # no hold: PX4 or the pilot is in charge
                elif isinstance(exc, SkillFailed):
                    state, message = SkillState.FAILED, str(exc)
                    code, facts = exc.code, exc.facts or facts
                    if skill.moves:
                        await self._hold()
                else:
                    log.error("skill %s crashed", skill.name, exc_info=exc)
                    state, message = SkillState.FAILED, f"{skill.name} failed: {type(exc).__name__}: {exc}"
                    if skill.moves:
                        await self._hold()
        finally:
            if skill.moves:
                self.ctx.settled_ns = time.time_ns()
            outcome = SkillOutcome(code=code, facts=facts, start_pose=goal.start_pose,
                                   end_pose=pose_of(self.state.value), perceived="; ".join(self.ctx.perceived),
                                   held_object=self.memory.held,
                                   estimate=self.ctx.estimate)
            entry = goal.skill.name + (f"({arg})" if arg else "")
            self.memory.record_executed(f"{entry}: {state.value}")
            self.goal = None
            with contextlib.suppress(BusError):
                self._status(goal.goal_id, goal.request, state, message, outcome, goal.started_ns)
            log.info("%s goal %s %s: %s", skill.name, goal.goal_id, state.value, message)

    # ---- abort

    async def handle_abort(self, abort: Abort) -> AbortAck:
        goal = self.goal
        if abort.task_id and goal is not None and goal.request.task_id != abort.task_id:
            ack = AbortAck(abort_stamp_ns=abort.stamp_ns, goal_id=None,
                           message=f"no skill of task {abort.task_id} runs; nothing done")
            self.bus.publish(self.keys.abort_ack, ack)
            return ack
        if goal is not None and goal.task is not None and not goal.task.done():
            goal.aborted_by = f"{abort.source}: {abort.reason}"
            self.ctx.stop_requested = True
            goal.task.cancel()
        result = None
        if airborne(self.state.value) or goal is not None:
            result = await self._hold()
        if goal is not None and goal.runner is not None:
            # Wait for the status so the executor is ready for the next skill when the ack arrives.
            with contextlib.suppress(TimeoutError, asyncio.CancelledError):
                await asyncio.wait_for(asyncio.shield(goal.runner), 1.0)
        if result is None and (goal is not None or airborne(self.state.value)):
            text = "hold command failed"
        elif result is None:
            text = "vehicle on the ground; nothing to hold"
        else:
            text = "holding position"
        what = f"stopped {goal.skill.name} (goal {goal.goal_id}), " if goal is not None else "no skill running, "
        ack = AbortAck(abort_stamp_ns=abort.stamp_ns, goal_id=goal.goal_id if goal else None, message=what + text)
        self.bus.publish(self.keys.abort_ack, ack)
        log.warning("abort from %s (%s): %s", abort.source, abort.reason, ack.message)
        return ack

    async def handle_cancel(self, req: CancelGoal) -> CancelReply:
        """Action protocol: cancel the running goal `req.goal_id` (it ends ABORTED, the vehicle holds)."""
        goal = self.goal
        if goal is None or goal.goal_id != req.goal_id:
            return CancelReply(accepted=False, reason=f"goal {req.goal_id} is not running")
        await self.handle_abort(Abort(reason=req.reason, source=req.source, task_id=goal.request.task_id or None))
        return CancelReply(accepted=True)

    # ---- inputs

    async def _pump_resets(self) -> None:
        sub = self.bus.subscribe(self.keys.sim_reset_notice, maxsize=4)
        while True:
            notice = await sub.recv()
            log.info("world reset (seed %d): working memory cleared", notice.seed)
            self.memory.world_reset()

    async def _pump_state(self) -> None:
        sub = self.bus.subscribe(self.keys.autopilot_state, maxsize=4, overflow="latest")
        while True:
            rec = await sub.recv_sample()
            self.state.update(rec.value, rec.receive_ns)
            # An open gripper holds nothing: keeps memory true to the vehicle when the object is taken out
            # by hand or the world is reset (skills manage `held` themselves while they run).
            if self.goal is None and self.memory.held and rec.value.gripper == GripperState.OPEN:
                log.info("gripper reports open: no longer holding the %s", self.memory.held)
                self.memory.set_held(None)
            # The gripper's own report wins over memory, which a restart of this service empties: an object
            # between closed fingers is held, whatever the memory says, so no skill opens the gripper on it.
            elif (self.goal is None and not self.memory.held and rec.value.gripper == GripperState.CLOSED
                  and rec.value.gripper_holding):
                log.warning("the gripper reports an object between its fingers that memory did not know of")
                self.memory.set_held(UNKNOWN_HELD)

    async def _pump_aborts(self, key: BoundTopic[Abort]) -> None:
        sub = self.bus.subscribe(key, maxsize=16, overflow="drop_newest")
        while True:
            abort = await sub.recv()
            # Abort handling runs beside the pump so a second abort is not queued behind a slow hold.
            task = asyncio.create_task(self.handle_abort(abort))
            self._background.add(task)
            task.add_done_callback(self._background.discard)

    async def _pump_depth(self) -> None:
        sub = self.bus.subscribe(self.keys.camera_depth, maxsize=1, overflow="latest")
        while True:
            data = await sub.recv()
            try:
                stamp, img = parse_raw16(data)
            except DecodeError as exc:
                log.debug("bad depth frame: %s", exc)
                continue
            self.clearance.update(stamp, img)

    async def _pump_calibration(self) -> None:
        sub = self.bus.subscribe(self.keys.camera_calibration, maxsize=1, overflow="latest")
        while True:
            data = await sub.recv()
            with contextlib.suppress(DecodeError):
                self.clearance.intr = parse_calibration(data)

    async def _pump_detections(self) -> None:
        sub = self.bus.subscribe(self.keys.detections, maxsize=2, overflow="latest")
        while True:
            self.memory.set_visible(await sub.recv())

    async def _memory_ticker(self) -> None:
        while True:
            self._publish_memory()
            await asyncio.sleep(self.settings.memory_period_s)

    async def run(self, stop: asyncio.Event) -> None:
        self.bus.serve(self.keys.run_skill, self.handle_run_skill)
        self.bus.serve(self.keys.cancel_skill, self.handle_cancel)

        async def skills(_req: object) -> SkillLibrary:
            return self.library()

        self.bus.serve(self.keys.skills, skills)
        log.info("executor serving %d skills: %s", len(self.skills), ", ".join(self.skills))
        try:
            async with asyncio.TaskGroup() as tg:
                for coro in (self._pump_state(), self._pump_aborts(self.keys.abort), self._pump_aborts(FLEET_ABORT),
                             self._pump_depth(), self._pump_calibration(),
                             self._pump_detections(), self._pump_resets(), self._memory_ticker()):
                    tg.create_task(coro)
                await stop.wait()
                raise _Stop
        except* _Stop:
            pass
        finally:
            goal = self.goal
            if goal is not None and goal.task is not None:
                goal.task.cancel()
                goal.aborted_by = "executor shutting down"
                with contextlib.suppress(BaseException):
                    await asyncio.wait_for(self._hold(), 2.0)


class _Stop(Exception):
    pass


async def run(bus: Bus, settings: ExecutorSettings, stop: asyncio.Event) -> None:
    await Executor(bus, settings).run(stop)


