"""The executor service: run one skill at a time on request, publish its status, hold on abort."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from dataclasses import dataclass, field

from services.executor.context import AbortSeen, AuthorityLost, SkillContext, SkillFailed, StateTracker, pose_of
from services.executor.envelope import DepthClearance, airborne, offboard_problem, state_problem
from services.executor.memory import Memory
from services.executor.registry import Skill, build_library
from services.executor.settings import ExecutorSettings
from services.executor.skills.common import Refusal
from shared import skills as S  # noqa: N812
from shared.action import SKILL_ACTION, ActionServer, ServerGoalHandle
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
    LandCommand,
    LandedState,
    MemoryRestore,
    OutcomeCode,
    SkillAccept,
    SkillFacts,
    SkillLibrary,
    SkillOutcome,
    SkillRequest,
    SkillState,
    SkillStatus,
    VehicleState,
    new_id,
    now_ns,
)
from shared.sensors import parse_calibration, parse_depth
from shared.service import announce

UNKNOWN_HELD = "unidentified object"
"""What memory calls an object the gripper reports holding that this executor did not grasp itself."""
SLIP_S = 0.3
"""How long a held object's pads may show no contact (closed fingers) before it counts as slipped: contact
flickers for a sample or two as a held object swings or touches down."""
FIRST_STATE_WAIT_S = 3.0
"""How long a first request waits for the bridge's first state (it comes at 20-50 Hz)."""
log = logging.getLogger("aermani.executor")


@dataclass
class Goal:
    """A skill goal the executor accepted: the request, the skill instance and the tasks running it."""

    goal_id: str
    request: SkillRequest
    skill: Skill
    started_ns: int = field(default_factory=now_ns)
    start_pose: object = None
    argument: str | None = None
    task: asyncio.Task | None = None  # the skill's own run()
    runner: asyncio.Task | None = None  # supervises run(): timeout, status
    handle: ServerGoalHandle[SkillRequest, SkillStatus] | None = None  # reports the goal (action protocol)
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
        self._lost_since: int | None = None  # receive time of the first state showing a held object's pads apart
        self.slipped: str = ""
        """The held object lost in flight (noticed from the gripper's contact), reported with the next status."""
        self.clearance = DepthClearance(DEFAULT_INTRINSICS, mount=settings.mount)
        self.ctx = SkillContext(bus, settings, self.memory, self.state, self.clearance)
        self.goal: Goal | None = None
        self.action = ActionServer(bus, SKILL_ACTION, settings.vehicle_id, goal_callback=self.handle_run_skill,
                                   execute_callback=self._execute, cancel_callback=self._cancel)
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
                outcome: SkillOutcome | None = None, started_ns: int = 0,
                handle: ServerGoalHandle[SkillRequest, SkillStatus] | None = None) -> SkillStatus:
        st = SkillStatus(goal_id=goal_id, request_id=req.request_id, task_id=req.task_id, step=req.step,
                         skill=req.skill, argument=req.argument, state=state, message=message,
                         outcome=outcome or SkillOutcome(), started_ns=started_ns,
                         ended_ns=now_ns() if state.terminal else 0)
        if handle is not None:
            handle.publish(st)
        else:  # a rejection: no goal to follow
            self.action.publish(st)
        return st

    def library(self) -> SkillLibrary:
        return SkillLibrary(skills=tuple(sk.spec() for sk in self.skills.values()))

    # ---- preconditions

    def validate(self, req: SkillRequest) -> tuple[Skill | None, str | None, Refusal | None]:
        """(skill, argument, None) when it may start, else (None, None, why not: a message with its code)."""
        skill, arg, problem = self._validate(req)
        if problem is None:
            return skill, arg, None
        return None, None, problem if isinstance(problem, Refusal) else Refusal(problem, OutcomeCode.BLOCKED)

    def _validate(self, req: SkillRequest) -> tuple[Skill | None, str | None, str | None]:
        skill = self.skills.get(req.skill.strip())
        if skill is None:
            names = ", ".join(n for n, sk in self.skills.items() if sk.policy_visible)
            return None, None, Refusal(f"unknown skill {req.skill!r}; choose one of: {names}", OutcomeCode.FAILED)
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
            problem = Refusal(f"precondition check of {skill.name} failed: {exc}", OutcomeCode.FAILED)
        if problem:
            return None, None, problem
        return skill, arg, None

    # ---- run_skill

    async def _first_state(self) -> None:
        """A freshly started (or restarted) executor judges its first request on a vehicle state, not on the
        absence of one: wait briefly for the bridge's first sample (at 20-50 Hz it is on its way); a bridge that
        is really silent is then refused with that reason."""
        if self.state.value is None:
            await self.state.next(FIRST_STATE_WAIT_S)

    async def handle_run_skill(self, req: SkillRequest) -> SkillAccept:
        """Goal callback: accept a skill that may start now (it is reserved at once: one skill at a time) or
        reject it with its reason, code and facts; `_execute` runs an accepted one."""
        await self._first_state()  # the only await: from here to the reservation below nothing yields
        goal_id = new_id("goal-")
        self.memory.begin_task(req.task_id)
        if self.goal is not None:
            reason = (f"skill {self.goal.request.skill} is still running (goal {self.goal.goal_id}): wait for its "
                      "status or abort it; nothing was started")
            outcome = self._refused(OutcomeCode.BLOCKED)
            self._status(goal_id, req, SkillState.REJECTED, reason, outcome)
            return SkillAccept(accepted=False, goal_id=goal_id, reason=reason, outcome=outcome)
        skill, arg, refusal = self.validate(req)
        if skill is None:
            assert refusal is not None
            outcome = self._refused(refusal.code, refusal.facts, req.argument)
            self._status(goal_id, req, SkillState.REJECTED, str(refusal), outcome)
            log.info("rejected %s(%s): %s (%s)", req.skill, req.argument or "", refusal, refusal.code.value)
            return SkillAccept(accepted=False, goal_id=goal_id, reason=str(refusal), outcome=outcome)
        goal = Goal(goal_id, req, skill, start_pose=pose_of(self.state.value), argument=arg)
        self.goal = goal  # set before any await: one skill at a time
        self.ctx.reset_outcome(req.task_id)
        log.info("accepted %s(%s) goal %s", skill.name, arg or "", goal_id)
        return SkillAccept(accepted=True, goal_id=goal_id)

    async def handle_check_skill(self, req: SkillRequest) -> SkillAccept:
        """`executor/check_skill`: whether `req` would be accepted now, by the same preconditions and envelope as
        run_skill, starting nothing and publishing nothing. The reasoner asks before it asks an operator, so an
        approval is only ever asked for a skill that could start (the answer holds only for now: run_skill
        checks again)."""
        await self._first_state()
        self.memory.begin_task(req.task_id)  # judged with the task's memory, as run_skill would
        if self.goal is not None:
            reason = f"skill {self.goal.request.skill} is still running (goal {self.goal.goal_id})"
            return SkillAccept(accepted=False, goal_id="", reason=reason, outcome=self._refused(OutcomeCode.BLOCKED))
        skill, _arg, refusal = self.validate(req)
        if skill is None:
            assert refusal is not None
            log.info("check of %s(%s): would be refused: %s (%s)", req.skill, req.argument or "", refusal,
                     refusal.code.value)
            return SkillAccept(accepted=False, goal_id="", reason=str(refusal),
                               outcome=self._refused(refusal.code, refusal.facts, req.argument))
        return SkillAccept(accepted=True, goal_id="")

    async def _execute(self, handle: ServerGoalHandle[SkillRequest, SkillStatus]) -> None:
        """Execute callback: run the accepted skill under supervision; its terminal status ends the goal."""
        goal = self.goal
        assert goal is not None and goal.goal_id == handle.goal_id, "an accepted goal is the running one"
        goal.handle = handle
        goal.runner = asyncio.current_task()
        self._status(goal.goal_id, goal.request, SkillState.RUNNING, f"{goal.skill.name} started",
                     started_ns=goal.started_ns, outcome=SkillOutcome(start_pose=goal.start_pose), handle=handle)
        goal.task = asyncio.create_task(goal.skill.run(self.ctx, goal.argument), name=f"skill.{goal.skill.name}")
        if goal.aborted_by:  # an abort came between the accept and this start: the skill never acts
            goal.task.cancel()
        await self._supervise(goal, goal.argument)

    async def _cancel(self, handle: ServerGoalHandle[SkillRequest, SkillStatus], req: CancelGoal) -> CancelReply:
        return await self.handle_cancel(req)

    def _refused(self, code: OutcomeCode, facts: SkillFacts | None = None, target: str | None = None) -> SkillOutcome:
        """The outcome of a skill refused before it started: the vehicle is where it was."""
        pose = pose_of(self.state.value)
        return SkillOutcome(code=code, facts=self._complete(facts or SkillFacts(), target), start_pose=pose,
                            end_pose=pose, held_object=self.memory.held)

    def _complete(self, facts: SkillFacts, target: str | None) -> SkillFacts:
        """Facts the executor knows for every skill, added where the skill left them unset: what is held, the
        gripper's opening, the skill's argument as its target."""
        st = self.state.value
        update: dict[str, object] = {}
        if facts.holding is None and self.memory.held:
            update["holding"] = self.memory.held
        if facts.gripper_width_m is None and st is not None and st.gripper_width is not None:
            update["gripper_width_m"] = round(st.gripper_width, 4)
        if facts.target is None and target:
            update["target"] = target
        return facts.model_copy(update=update) if update else facts

    async def _hold(self) -> AutopilotResult | None:
        return await self._stop_command(HoldCommand())

    async def _stop_command(self, cmd: HoldCommand | LandCommand) -> AutopilotResult | None:
        """A hold or a land for the bridge, outside any skill (timeouts, aborts); None when it did not answer."""
        try:
            return await self.bus.query(self.keys.autopilot_command, cmd, timeout=2.0)
        except BusError as exc:
            log.warning("%s command failed: %s", cmd.kind, exc)
            return None

    async def _supervise(self, goal: Goal, arg: str | None) -> None:
        assert goal.task is not None
        skill = goal.skill
        timeout = skill.timeout_s(self.ctx, arg)
        state, message, code, facts = SkillState.FAILED, "", OutcomeCode.FAILED, SkillFacts()
        try:
            done, _ = await asyncio.wait({goal.task}, timeout=timeout)
            if goal.aborted_by and not done:
                done, _ = await asyncio.wait({goal.task}, timeout=1.0)
            if not done:
                goal.task.cancel()
                with contextlib.suppress(BaseException):
                    await goal.task
                state, message = SkillState.TIMEOUT, f"{skill.name} did not finish within {timeout:.0f} s; holding"
                code = OutcomeCode.TIMED_OUT
                if skill.moves:
                    await self._hold()
            elif goal.task.cancelled() or (goal.aborted_by and isinstance(goal.task.exception(),
                                                                          asyncio.CancelledError)):
                state, code = SkillState.ABORTED, OutcomeCode.ABORTED
                message = f"{skill.name} aborted ({goal.aborted_by or 'cancelled'}); holding position"
            else:
                exc = goal.task.exception()
                if exc is None:
                    result = goal.task.result()
                    state, message, code, facts = SkillState.SUCCEEDED, result.message, result.code, result.facts
                elif isinstance(exc, TimeoutError):
                    state, message, code = SkillState.TIMEOUT, f"{skill.name}: {exc}; holding", OutcomeCode.TIMED_OUT
                    if skill.moves:
                        await self._hold()
                elif isinstance(exc, SkillFailed) and (goal.aborted_by or isinstance(exc, AbortSeen)
                                                       or self._bridge_aborted()):
                    # The bridge saw the abort first and holds on its own (a takeoff it stopped, a command it
                    # refused, a takeover it latched): still an abort, whichever of the two got the message first.
                    state, code = SkillState.ABORTED, OutcomeCode.ABORTED
                    message = f"{skill.name} aborted ({goal.aborted_by or exc}); holding position"
                elif isinstance(exc, AuthorityLost):
                    # no hold: PX4 or the pilot is in charge
                    state, message, code = SkillState.FAILED, str(exc), OutcomeCode.ABORTED
                elif isinstance(exc, SkillFailed):
                    state, message, code, facts = SkillState.FAILED, str(exc), exc.code, exc.facts
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
            message, code = self._with_slip(message, code)
            outcome = SkillOutcome(code=code, facts=self._complete(facts, arg),
                                   start_pose=goal.start_pose, end_pose=pose_of(self.state.value),
                                   perceived="; ".join(self.ctx.perceived), held_object=self.memory.held,
                                   estimate=self.ctx.estimate)
            entry = goal.skill.name + (f"({arg})" if arg else "")
            self.memory.record_executed(f"{entry}: {state.value}")
            self.goal = None
            with contextlib.suppress(BusError):
                self._status(goal.goal_id, goal.request, state, message, outcome, goal.started_ns, goal.handle)
            log.info("%s goal %s %s: %s", skill.name, goal.goal_id, state.value, message)

    def _bridge_aborted(self) -> bool:
        """Whether the bridge latched an abort's takeover while the running skill flew."""
        st = self.state.value
        return st is not None and st.taken_by_abort(self.ctx.override_ns_at_start)

    # ---- abort

    async def handle_abort(self, abort: Abort) -> AbortAck:
        goal = self.goal
        if abort.task_id and goal is not None and goal.request.task_id != abort.task_id:
            ack = AbortAck(abort_stamp_ns=abort.stamp_ns, goal_id=None,
                           message=f"no skill of task {abort.task_id} runs; nothing done")
            self.bus.publish(self.keys.abort_ack, ack)
            return ack
        if goal is not None and (goal.task is None or not goal.task.done()):
            goal.aborted_by = f"{abort.source}: {abort.reason}"
            self.ctx.stop_requested = True
            if goal.task is not None:  # else it is cancelled as it starts (_execute)
                goal.task.cancel()
        result = None
        st = self.state.value
        taking_off = (goal is not None and goal.skill.name == S.TAKEOFF) or (
            st is not None and st.armed and st.landed_state is LandedState.TAKEOFF)
        if taking_off:
            # Holding mid-takeoff leaves the vehicle armed a few centimetres up, in ground effect, where the
            # next task can neither take off nor move (below the minimum altitude): it lands instead.
            result = await self._stop_command(LandCommand())
        elif airborne(st) or goal is not None:
            result = await self._hold()
        if goal is not None and goal.runner is not None:
            # Wait for the status so the executor is ready for the next skill when the ack arrives.
            with contextlib.suppress(TimeoutError, asyncio.CancelledError):
                await asyncio.wait_for(asyncio.shield(goal.runner), 1.0)
        if result is None and (goal is not None or airborne(self.state.value)):
            text = "land command failed" if taking_off else "hold command failed"
        elif result is None:
            text = "vehicle on the ground; nothing to hold"
        elif taking_off:
            text = "landing (aborted mid-takeoff)" if result.ok else f"land refused: {result.message}"
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

    async def handle_restore_memory(self, req: MemoryRestore) -> CancelReply:
        """A recorded working memory put back for a task that continues a recorded one (`aermani fork`): never
        mid-skill, where a skill reads and writes it, and only where AERMANI_EXECUTOR_MEMORY_RESTORE allows it."""
        if not self.settings.memory_restore:
            return CancelReply(accepted=False, reason="this executor does not take a recorded working memory "
                                                      "(AERMANI_EXECUTOR_MEMORY_RESTORE=1 allows it; aermani fork "
                                                      "sets it in the simulated stack it starts)")
        goal = self.goal
        if goal is not None:
            return CancelReply(accepted=False, reason=f"skill {goal.request.skill} is running: working memory is not "
                                                      "replaced mid-skill")
        now = now_ns()
        self.memory.restore(req.memory, req.task_id, now - req.taken_ns, now)
        log.info("working memory restored for task %s: %d objects, %d placements, holding %s", req.task_id,
                 len(req.memory.objects), len(req.memory.placements), req.memory.held_object or "nothing")
        return CancelReply(accepted=True)

    # ---- inputs

    async def _pump_resets(self) -> None:
        sub = self.bus.subscribe(self.keys.sim_reset_notice, maxsize=4)
        while True:
            notice = await sub.recv()
            log.info("world reset (seed %d): working memory cleared", notice.seed)
            self.memory.world_reset(notice.stamp_ns)

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
            elif self.goal is None and not self.memory.held and rec.value.gripper_holding:
                log.warning("the gripper reports an object between its fingers that memory did not know of")
                self.memory.set_held(UNKNOWN_HELD)
            self._watch_slip(rec.value, rec.receive_ns)

    def _with_slip(self, message: str, code: OutcomeCode) -> tuple[str, OutcomeCode]:
        """A slip noticed while (or since) the skill ran is part of its status: the message says it, and a skill
        that otherwise succeeded reports `slipped`."""
        if not self.slipped:
            return message, code
        message = f"{message}; {self.slipped}" if message else self.slipped
        self.slipped = ""
        return message, OutcomeCode.SLIPPED if code is OutcomeCode.SUCCEEDED else code

    def _watch_slip(self, st: VehicleState, receive_ns: int) -> None:
        """A held object whose pads lost contact while the fingers stay closed, for SLIP_S, has slipped out (grasp
        and place watch the contact themselves while they run): memory forgets it and the next skill status
        says so (code `slipped`), instead of a later place releasing nothing."""
        manipulating = self.goal is not None and self.goal.skill.name in (S.GRASP, S.PLACE)
        if (not self.memory.held or manipulating or st.gripper_holding is not False
                or st.gripper != GripperState.CLOSED):
            self._lost_since = None
            return
        if self._lost_since is None:
            self._lost_since = receive_ns
            return
        if receive_ns - self._lost_since >= SLIP_S * 1e9:
            p = st.position
            self.slipped = (f"the {self.memory.held} slipped out of the gripper in flight near "
                            f"({p.x:.2f}, {p.y:.2f}, {p.z:.2f}) (finger contact lost for {SLIP_S:.1f} s)")
            log.warning("%s", self.slipped)
            self.memory.set_held(None)
            self._lost_since = None

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
                stamp, img = parse_depth(data)
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
        self.action.start()

        async def skills(_req: object) -> SkillLibrary:
            return self.library()

        self.bus.serve(self.keys.skills, skills)
        self.bus.serve(self.keys.check_skill, self.handle_check_skill)
        self.bus.serve(self.keys.restore_memory, self.handle_restore_memory, concurrent=False)
        announce(self.bus, self.settings, "executor")  # alive once it answers: a restart's new token means ready
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


