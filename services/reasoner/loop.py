"""Algorithm 1: observe, compile P_t, query the policy, validate (re-prompt), execute, update History.

The loop talks to the rest of the stack only through `World` (observation, skill registry, run a skill,
wait for its status), so it runs unchanged against the bus (service.py) and against test doubles.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, replace

from services.reasoner.backends.base import Backend, ModelRequest, PastStep, PolicyContext, Seen
from services.reasoner.baselines import restrict_library
from services.reasoner.library import policy_skills
from services.reasoner.parse import ParsedAnswer, parse_answer, recorded_answer
from services.reasoner.prompt import (
    CompiledPrompt,
    History,
    HistoryEntry,
    Observation,
    PromptCompiler,
)
from services.reasoner.settings import ReasonerSettings
from services.reasoner.speculation import assume, disagreement, height_problem
from shared import skills as S  # noqa: N812
from shared.errors import AermaniError, InvalidAnswer, ModelError, ServerLost
from shared.messages import (
    ApprovalState,
    ApprovalStatus,
    DescriptiveReasoningTrace,
    LandedState,
    ModelCall,
    ReasoningStep,
    ResumeStep,
    SkillAccept,
    SkillLibrary,
    SkillOutcome,
    SkillRequest,
    SkillScore,
    SkillState,
    SkillStatus,
    SkillToExecute,
    StepTiming,
    TaskRequest,
    TaskState,
    TaskStatus,
    VehicleState,
    now_ns,
)
from shared.tasks import REFUSED_BEFORE_TAKEOFF
from shared.text import plain_text

log = logging.getLogger("aermani.reasoner.loop")

AIRBORNE = (LandedState.IN_AIR, LandedState.TAKEOFF, LandedState.LANDING)
"""Flight phases in which a skill needs healthy offboard control."""
EFFECT_WAIT_S = 2.0
"""How long a step waits for a vehicle state sampled after its skill ended, before judging a grounded one."""


class ExecutorUnreachable(AermaniError):
    """No executor answered a skill, even after waiting `link_wait_s` for one: the task ends."""


class World(ABC):
    """What the loop needs from the stack."""

    @abstractmethod
    async def skill_library(self) -> SkillLibrary: ...

    @abstractmethod
    async def observe(self, newer_than_ns: int) -> Observation: ...

    @abstractmethod
    async def run_skill(self, request: SkillRequest, timeout: float,
                        ready_timeout: float = 0.0) -> tuple[SkillAccept, SkillStatus | None]:
        """Send the skill goal (action protocol); when accepted, wait up to `timeout` for its terminal status
        (None when none came in time). With `ready_timeout` > 0, wait that long for an executor to answer
        (a supervised restart) before giving up with an AermaniError."""

    async def check_skill(self, request: SkillRequest) -> SkillAccept:
        """Whether the executor would accept `request` now (its preconditions and envelope), starting nothing:
        asked before an operator's approval. A world that cannot ask its executor says no, so no approval is
        asked for a skill nobody checked."""
        return SkillAccept(accepted=False, goal_id="", reason="this world has no executor to check the skill with")

    async def request_approval(self, request: ApprovalStatus, timeout: float) -> ApprovalStatus:
        """Ask the operator whether `request.skill` may run; the decided status (approved, rejected, or
        expired after `timeout`). A world without an operator channel refuses, so nothing that needs an
        approval runs unapproved."""
        return request.model_copy(update={"state": ApprovalState.REJECTED,
                                          "reason": "no operator channel in this world"})

    async def hold(self, task_id: str, reason: str) -> None:
        """Command a hold (best effort): the failure path of a step."""
        with contextlib.suppress(Exception):
            await self.run_skill(SkillRequest(skill=S.HOLD, task_id=task_id), 0.0)

    async def cancel_skill(self, task_id: str, reason: str) -> SkillStatus | None:
        """Cancel the running skill of the task (the executor stops it and holds) and return its terminal
        status; with no skill running, hold. The default has no skill to cancel: it holds."""
        await self.hold(task_id, reason)
        return None


def policy_context(command: str, variant: str, library: SkillLibrary, history: History,
                   obs: Observation) -> PolicyContext:
    pos = obs.state.position if obs.state else None
    seen = []
    for d in obs.detections:
        vol = d.size.x * d.size.y * d.size.z if d.size is not None else None
        dist = (math.dist((d.centroid.x, d.centroid.y, d.centroid.z), (pos.x, pos.y, pos.z))
                if d.centroid is not None and pos is not None else None)
        c = d.catalog_size
        seen.append(Seen(d.label, d.category, vol, dist, c.x * c.y * c.z if c is not None else None))
    mem = obs.memory
    return PolicyContext(
        command=command, variant=variant, skills=[s.name for s in policy_skills(library)],
        steps=[PastStep.from_outcome(e.skill, e.argument, e.state, e.message, e.outcome) for e in history.entries],
        held=mem.held_object if mem else None, visible=seen,
        known_objects=[o.label for o in mem.objects] if mem else [],
        known_placements=[p.label for p in mem.placements] if mem else [],
        pose=(obs.state.position.x, obs.state.position.y, obs.state.yaw) if obs.state else None,
        positions={o.label: (o.position.x, o.position.y)
                   for o in (*mem.seen, *mem.objects, *mem.placements)} if mem else {})


def history_entry(r: ResumeStep) -> HistoryEntry:
    """A recorded step as the History keeps it (a resumed task's, rereason's)."""
    return HistoryEntry(r.step, r.skill, r.argument, r.state, r.message, r.perceived, r.summary, r.reasoning,
                        r.outcome, r.image_description, r.prediction)


CLOCK_STEP_S = 1.0
"""A wall-clock interval this much longer or shorter than the monotonic one over the same skill: the clock stepped."""


def skill_times(st: SkillStatus, sent_ns: int, received_ns: int,
                elapsed_s: float | None = None) -> dict[str, float]:
    """accept_s, skill_s and report_s of StepTiming from a terminal status: the executor stamps its goal's start
    and end; a refusal made here (approval, feasibility) has this host's stamps. `elapsed_s` is the same interval
    on this host's monotonic clock: when the wall clock stepped meanwhile (a full run saw 24.0 s of wall time
    in 13.6 s), skill_s is what remains of it after the accept and the report, never more than was waited."""
    started = st.started_ns or sent_ns
    ended = st.ended_ns or received_ns
    times = {"accept_s": max(0.0, (started - sent_ns) / 1e9), "skill_s": max(0.0, (ended - started) / 1e9),
             "report_s": max(0.0, (received_ns - ended) / 1e9)}
    if elapsed_s is not None and abs((received_ns - sent_ns) / 1e9 - elapsed_s) > CLOCK_STEP_S:
        times["skill_s"] = max(0.0, elapsed_s - times["accept_s"] - times["report_s"])
    return times


@dataclass
class Guess:
    """The next step's answer, asked for while the current skill flies (`speculation.py`)."""

    task: asyncio.Task[tuple[StepResult, float]]
    context: PolicyContext
    """What the policy was given: compared with the fresh context when the skill has ended."""
    height: float | None
    """The assumed vehicle height (the prompt shows it; PolicyContext's pose is x, y, yaw)."""


SPECULATION_VARIANTS_EXCLUDED = ("plan_once", "saycan")
"""plan_once answers once per task; saycan weighs its candidates by the executor's feasibility now, which the
running skill is changing."""


@dataclass
class StepResult:
    """One finished reasoning step: the published record and the parsed answer (None when invalid)."""

    record: ReasoningStep
    parsed: ParsedAnswer | None
    failure: str | None = None
    """The backend's reason when its (valid) answer ends the task as failed (ModelReply.failure)."""
    prompt_s: float = 0.0
    """Compiling the prompt (before the first model call)."""
    first_call: float = 0.0
    """time.perf_counter() at the first model call."""


class TaskRunner:
    """Runs one task to a terminal TaskStatus; publishes every step and status through the callbacks."""

    def __init__(self, request: TaskRequest, settings: ReasonerSettings, backend: Backend, world: World, *,
                 publish_step: Callable[[ReasoningStep], None], publish_status: Callable[[TaskStatus], None]) -> None:
        self.req = request
        self.settings = settings
        self.backend = backend
        self.world = world
        self.variant = request.variant or settings.variant
        self.t_max = request.t_max_s or settings.t_max_s
        self.publish_step = publish_step
        self.publish_status = publish_status
        self.history = History(settings.history_full_steps, settings.history_max_chars, paper=settings.paper_history)
        self.plan: list[SkillToExecute] | None = None
        """Plan-once variant: the plan's steps not yet run (None until the model gave one)."""
        self.categories: dict[str, str] = {}
        self.steps = 0
        self.calls = 0
        self.invalid = 0
        self.speculations = 0
        self.speculations_used = 0
        self._guess: Guess | None = None
        self.started_ns = now_ns()
        self.records: list[ReasoningStep] = []
        self._abort: asyncio.Event | None = None
        self.resume = request.resume
        if self.resume is not None:  # a flight fork: the recorded steps before its first one, as the loop kept them
            for r in self.resume.history:
                self.history.append(history_entry(r))
            self.steps = self.resume.origin.step - 1
        self._override_ns = 0  # takeover seen when the task started (the bridge's; a new one ends the task)
        self._effect_ns = 0  # when the last skill ended (the executor's stamp): states before it predate its effect

    def status(self, state: TaskState, message: str = "") -> TaskStatus:
        return TaskStatus(vehicle_id=self.settings.vehicle_id, task_id=self.req.task_id, command=self.req.command,
                          state=state, message=message, steps=self.steps, model_calls=self.calls,
                          invalid_answers=self.invalid, backend=self.backend.name, variant=self.variant,
                          started_ns=self.started_ns, ended_ns=0 if not state.terminal else now_ns(),
                          forked_from=self.resume.origin if self.resume is not None else None,
                          speculations=self.speculations, speculations_used=self.speculations_used)

    async def run(self, abort: asyncio.Event) -> TaskStatus:
        """Run until done/failure/abort/T_max; always returns (and publishes) the terminal status."""
        self.publish_status(self.status(TaskState.RUNNING, "task started"))
        self._abort = abort
        body = asyncio.create_task(self._run())
        aborter = asyncio.create_task(abort.wait())
        try:
            done, _ = await asyncio.wait({body, aborter}, timeout=self.t_max, return_when=asyncio.FIRST_COMPLETED)
            if body in done:
                final = body.result()
            elif aborter in done and getattr(abort, "cancel", False):
                final = await self._cancelled(body, getattr(abort, "reason", "") or "cancelled")
            else:
                body.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await body
                if aborter in done:
                    # The executor holds the vehicle itself on an abort it received.
                    final = self.status(TaskState.ABORTED, "aborted: " + (getattr(abort, "reason", "") or "abort"))
                else:
                    await self.world.hold(self.req.task_id, "T_max")
                    final = self.status(TaskState.TIMEOUT, f"T_max of {self.t_max:.0f} s passed; vehicle held")
        except Exception as exc:  # a bug or a bus failure must still end the task visibly
            log.exception("task %s crashed", self.req.task_id)
            await self.world.hold(self.req.task_id, "crash")
            final = self.status(TaskState.FAILED, f"reasoner error: {type(exc).__name__}: {exc}")
        finally:
            aborter.cancel()
            await self._drop_guess()
        self.publish_status(final)
        return final

    async def _cancelled(self, body: asyncio.Task[TaskStatus], reason: str) -> TaskStatus:
        """A cancel of the task: stop its running skill and hold (the executor does both and reports the skill
        aborted) before the loop stops, then end ABORTED with the reason."""
        stopped = await self.world.cancel_skill(self.req.task_id, reason)
        body.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await body
        what = (f"skill {stopped.skill} {stopped.state.value}" if stopped is not None
                else "no skill was running")
        return self.status(TaskState.ABORTED, f"cancelled: {reason}; {what}; vehicle held")

    async def _run(self) -> TaskStatus:
        try:
            library = await self.world.skill_library()
        except AermaniError as exc:
            return self.status(TaskState.FAILED, f"no skill library from the executor: {exc}")
        self.categories = {spec.name: spec.category for spec in library.skills}
        library = restrict_library(self.variant, library)  # waypoint: the motion primitives only
        compiler = PromptCompiler(self.variant, library, free_text_baselines=self.settings.free_text_baselines)
        if self.variant == "plan_once" and self.resume is not None and self.resume.origin.step > 1:
            return self.status(TaskState.FAILED, "a plan-once task cannot be forked after its first step: its plan "
                                                 "is its first step's one answer; fork it at step 1")
        ended = await self._preflight(library)
        if ended is not None:
            return ended
        failed_in_row = 0
        last_skill = self.history.entries[-1].skill if self.history.entries else S.TAKEOFF
        last_end_ns = now_ns()  # the first observation must come after the take-off (not a stale grounded state)
        last_end = time.perf_counter()  # the same moment on the step-timing clock
        while True:
            if self.steps >= self.settings.max_steps:
                await self.world.hold(self.req.task_id, "max steps")
                return self.status(TaskState.FAILED, f"no completion within {self.settings.max_steps} steps; "
                                                     "vehicle held")
            t_step = time.perf_counter()
            obs = await self.world.observe(last_end_ns)
            obs = await self._after_effect(obs, last_skill)
            ended = self._authority_end(obs, last_skill)
            if ended is not None:
                return ended
            t_link = time.perf_counter()
            obs, ended = await self._await_link(obs, last_end_ns, last_skill)
            if ended is not None:
                return ended
            link_s = time.perf_counter() - t_link
            self.steps += 1
            try:
                result, model_time = await self._take_guess(library, obs) or await self._next(compiler, library, obs)
            except ModelError as exc:
                await self.world.hold(self.req.task_id, "model outage")
                rec = ReasoningStep(vehicle_id=self.settings.vehicle_id, task_id=self.req.task_id, step=self.steps,
                                    backend=self.backend.name, variant=self.variant, skill_message=str(exc),
                                    calls=exc.calls)
                self._publish(rec)
                return self.status(TaskState.FAILED, f"model unavailable, vehicle held: {exc}")
            rec, parsed = result.record, result.parsed
            timing = StepTiming(to_model_s=max(0.0, result.first_call - last_end), frame_wait_s=obs.frame_wait_s,
                                detections_wait_s=obs.detections_wait_s, state_wait_s=obs.state_wait_s,
                                link_wait_s=link_s, prompt_s=result.prompt_s, model_s=model_time)
            if parsed is None:
                failed_in_row += 1
                await self.world.hold(self.req.task_id, "invalid answer")
                err = rec.calls[-1].error if rec.calls else "no answer"
                self.history.append(HistoryEntry(self.steps, "(invalid answer)", None, "failed",
                                                 f"no valid skill after {rec.retries} re-prompts: {err}; held"))
                rec = rec.model_copy(update={"overhead_s": time.perf_counter() - t_step - model_time,
                                             "timing": timing})
                self._publish(rec)
                last_end = time.perf_counter()  # the hold ended this step: the next one waits from here
                if failed_in_row >= self.settings.max_failed_steps:
                    return self.status(TaskState.FAILED, f"{failed_in_row} steps without a valid answer "
                                                         f"(last error: {err}); vehicle held")
                continue
            failed_in_row = 0
            overhead = time.perf_counter() - t_step - model_time
            ste = parsed.ste
            if self._speculating():
                self._guess = self._speculate(compiler, library, obs, parsed)
            t_skill, sent_ns = time.perf_counter(), now_ns()
            try:
                st = await self._execute(SkillRequest(skill=ste.skill, argument=ste.argument,
                                                      task_id=self.req.task_id, step=self.steps),
                                         self.settings.skill_timeout_s, reasoning=parsed.drt.reasoning or "")
                if st.state is not SkillState.SUCCEEDED:
                    await self._drop_guess()  # it assumed a success
            except ExecutorUnreachable as exc:
                self._publish(rec.model_copy(update={"skill_state": SkillState.FAILED, "skill_message": str(exc),
                                                     "overhead_s": overhead}))
                return self.status(TaskState.FAILED, str(exc))
            skill_s = time.perf_counter() - t_skill
            t_upd = last_end = time.perf_counter()
            last_end_ns = now_ns()  # local clock: the next frame must arrive after this
            timing = timing.model_copy(update=skill_times(st, sent_ns, last_end_ns, skill_s))
            last_skill = ste.skill
            self.history.append(HistoryEntry(
                self.steps, ste.skill, ste.argument, st.state.value, st.message, st.outcome.perceived,
                parsed.drt.summary or "", parsed.drt.reasoning or "", st.outcome,
                image_description=parsed.drt.image_description or "",
                prediction=(parsed.drt.action_predictions or {}).get(ste.skill, "")))
            overhead += time.perf_counter() - t_upd
            rec = rec.model_copy(update={"skill_state": st.state, "skill_message": st.message, "outcome": st.outcome,
                                         "overhead_s": overhead, "skill_duration_s": skill_s, "timing": timing})
            self._publish(rec)
            ended = await self._step_end(ste, st, result.failure)
            if ended is not None:
                return ended

    async def _step_end(self, ste: SkillToExecute, st: SkillStatus, failure: str | None) -> TaskStatus | None:
        """The task's end after a step's skill ended, or None to go on."""
        if self.variant == "plan_once" and st.state is not SkillState.SUCCEEDED:
            if st.state is SkillState.ABORTED:
                return self.status(TaskState.ABORTED, f"skill {ste.skill} aborted: {st.message}")
            await self.world.hold(self.req.task_id, "plan failed")
            return self.status(TaskState.FAILED, f"plan step {self.steps} {ste.skill} {st.state.value}: "
                                                 f"{st.message}; the plan-once baseline does not re-plan; "
                                                 "vehicle held")
        if ste.skill == S.DONE:
            if failure:  # the policy ends the task as failed ("not found: ..."), not as complete
                await self.world.hold(self.req.task_id, "policy gave up")
                return self.status(TaskState.FAILED, failure)
            if st.state is SkillState.SUCCEEDED:
                return self.status(TaskState.SUCCEEDED, "the policy declared the task complete")
            log.warning("done was %s: %s", st.state.value, st.message)
        if st.state is SkillState.ABORTED:
            return self.status(TaskState.ABORTED, f"skill {ste.skill} aborted: {st.message}")
        return None

    async def _preflight(self, library: SkillLibrary) -> TaskStatus | None:
        """Before the first step: the backend's refusal (nothing flies for a command the policy cannot carry
        out), then the takeoff when the vehicle is on the ground. The failed status, or None to go on."""
        refused = (self.backend.unsupported(self.variant)
                   or self.backend.refusal(self.req.command, [s.name for s in policy_skills(library)]))
        if refused:
            return self.status(TaskState.FAILED, f"{REFUSED_BEFORE_TAKEOFF}: {refused}")
        obs = await self.world.observe(0)
        deadline = time.monotonic() + self.settings.link_wait_s
        while (obs.state is None or not obs.state.link_ok) and time.monotonic() < deadline:
            # No vehicle state yet (the bridge's first sample is still on its way), or one without the
            # autopilot's facts (a bridge that just started: no heartbeat, armed and landed state unknown):
            # whether to take off is decided on a state, never on its absence (ci of stop 41: the take-off was
            # skipped, and the first grounded state to arrive then read as a landing nobody asked for).
            await asyncio.sleep(0.1)
            obs = await self.world.observe(0)
        vs = obs.state
        if vs is None or not vs.link_ok:
            missing = "vehicle state from the autopilot bridge" if vs is None else "link to the autopilot"
            return self.status(TaskState.FAILED, f"no {missing} within {self.settings.link_wait_s:.0f} s; "
                                                 "nothing took off")
        while vs.landed_state is LandedState.LANDING and time.monotonic() < deadline:
            # A landing in progress (an abort mid-takeoff lands): take off again once it is down.
            await asyncio.sleep(0.5)
            vs = (await self.world.observe(0)).state or vs
        self._override_ns = vs.override_ns
        grounded = vs.landed_state is LandedState.ON_GROUND or (
            vs.landed_state is LandedState.UNKNOWN and not vs.armed)
        if self.req.takeoff and grounded:
            try:
                st = await self._execute(SkillRequest(skill=S.TAKEOFF, task_id=self.req.task_id, step=0),
                                         self.settings.takeoff_timeout_s)
            except ExecutorUnreachable as exc:
                return self.status(TaskState.FAILED, f"takeoff failed: {exc}")
            if st.state is SkillState.ABORTED:  # the executor (or the bridge) got the abort before this loop
                return self.status(TaskState.ABORTED, f"takeoff aborted: {st.message}")
            if st.state is not SkillState.SUCCEEDED:
                return self.status(TaskState.FAILED, f"takeoff {st.state.value}: {st.message}")
        return None

    async def _after_effect(self, obs: Observation, last_skill: str) -> Observation:
        """A grounded vehicle after a skill that does not land ends the task (`_authority_end`), so that verdict
        is made only on a state sampled after the skill ended: Zenoh orders nothing across keys, and a state
        from before the take-off's effect can arrive after the take-off's status (received after the skill's
        end, so `observe` took it as fresh). Both stamps are the vehicle's (bridge and executor). Waits at
        most `EFFECT_WAIT_S` for such a state; a state still older then is no landing (`_authority_end`), and a
        silent bridge is what `_await_link` reports. The wait counts in the step's state wait."""
        first, t0 = obs, time.perf_counter()

        def stale_grounded(o: Observation) -> bool:
            return (o.state is not None and self._grounded_unasked(o.state, last_skill)
                    and o.state.stamp_ns <= self._effect_ns)

        if not stale_grounded(obs):
            return obs
        log.info("task %s: a grounded state from before %s ended; waiting for a later one", self.req.task_id,
                 last_skill)
        deadline = time.monotonic() + EFFECT_WAIT_S
        while stale_grounded(obs) and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
            obs = await self.world.observe(0)
        return replace(obs, frame_wait_s=first.frame_wait_s, detections_wait_s=first.detections_wait_s,
                       state_wait_s=first.state_wait_s + time.perf_counter() - t0)

    def _grounded_unasked(self, st: VehicleState, last_skill: str) -> bool:
        """On the ground in a task that took off, and the last skill was no landing."""
        return self.req.takeoff and st.landed_state is LandedState.ON_GROUND and last_skill != S.LAND

    def _authority_end(self, obs: Observation, last_skill: str) -> TaskStatus | None:
        """PX4's authority: when PX4, the pilot or an abort took control during this task, or the vehicle came
        down without being asked, the task ends with that reason. Nothing takes off again on its own: that
        needs a new operator command (a new task)."""
        st = obs.state
        if st is None or (self._abort is not None and self._abort.is_set()):
            return None
        if st.override and st.override_ns != self._override_ns and st.taken_by_abort(self._override_ns):
            # The bridge got the abort before this loop did (its subscribers see it in any order).
            return self.status(TaskState.ABORTED, f"aborted: the bridge holds ({st.override})")
        if st.override and st.override_ns != self._override_ns:
            return self.status(TaskState.FAILED, f"the autopilot took control: {st.override}; the task ends "
                                                 "here, a new command is needed to fly again")
        if self._grounded_unasked(st, last_skill) and st.stamp_ns > self._effect_ns:
            # (an older state predates the last skill's effect: _after_effect waited for a later one)
            return self.status(TaskState.FAILED, f"the vehicle landed without being asked (mode {st.mode}"
                                                 f"{': ' + st.message if st.message else ''}); the task ends "
                                                 "here, a new command is needed to fly again")
        return None

    def _link_problem(self, obs: Observation) -> str | None:
        st = obs.state
        if st is None:
            return "no vehicle state from the autopilot bridge"
        if obs.state_age_s > self.settings.state_stale_s:
            return f"no vehicle state from the autopilot bridge for {obs.state_age_s:.1f} s"
        if not st.link_ok:
            return "no link to the autopilot"
        if st.landed_state in AIRBORNE and not st.offboard_ok and not (
                st.mode == "AUTO.LOITER" and st.landed_state is LandedState.IN_AIR):
            # PX4 holding in the air (AUTO.LOITER) is no reason to wait: a takeover during this task ended it
            # already (_authority_end); one from before it (a restarted bridge found PX4's offboard-loss Hold)
            # is what this task's first skill takes back from, into OFFBOARD.
            # Taking off or landing counts too: a vehicle that PX4 is bringing down after a bridge kill is
            # not one to send a skill to (7 were issued in 4.7 s when only "in_air" was checked).
            return f"offboard control is not healthy (mode {st.mode}, {st.landed_state.value})"
        return None

    async def _await_link(self, obs: Observation, newer_than_ns: int,
                          last_skill: str) -> tuple[Observation, TaskStatus | None]:
        """Issue no skill while the vehicle's link or offboard control is bad (a skill would fail and burn a
        step): wait up to `link_wait_s` for it to recover, then hold and end the task with the reason."""
        problem = self._link_problem(obs)
        if problem is None:
            return obs, None
        log.warning("task %s: %s; waiting up to %.0f s before the next step", self.req.task_id, problem,
                    self.settings.link_wait_s)
        deadline = time.monotonic() + self.settings.link_wait_s
        while problem is not None and time.monotonic() < deadline:
            await asyncio.sleep(0.5)
            obs = await self.world.observe(newer_than_ns)
            ended = self._authority_end(obs, last_skill)
            if ended is not None:
                return obs, ended
            problem = self._link_problem(obs)
        if problem is None:
            log.info("task %s: the vehicle's link is back; continuing", self.req.task_id)
            return obs, None
        await self.world.hold(self.req.task_id, "link lost")
        return obs, self.status(TaskState.FAILED, f"{problem} for {self.settings.link_wait_s:.0f} s; no skill was "
                                                  "issued meanwhile; vehicle held (if it still listens)")

    def _publish(self, rec: ReasoningStep) -> None:
        rec = rec.model_copy(update={"published_ns": now_ns()})
        self.records.append(rec)
        self.publish_step(rec)

    async def _decide(self, compiler: PromptCompiler, library: SkillLibrary, obs: Observation,
                      history: History | None = None, step: int | None = None,
                      count: bool = True) -> tuple[StepResult, float]:
        """Query the policy, re-prompting with the error up to N times. Returns (result, model seconds).
        `history` and `step` default to the task's; a speculative step passes its assumed ones and `count`
        False (its calls count when it is used)."""
        history = self.history if history is None else history
        step = self.steps if step is None else step
        t_prompt = time.perf_counter()
        prompt: CompiledPrompt = compiler.compile(self.req.command, history, obs)
        ctx = policy_context(self.req.command, self.variant, library, history, obs)
        first_call = time.perf_counter()
        feedback: list[tuple[str, str]] = []
        calls: list[ModelCall] = []
        parsed: ParsedAnswer | None = None
        failure: str | None = None
        model_time = 0.0
        for _attempt in range(self.settings.max_reprompts + 1):
            t0 = time.perf_counter()
            try:
                reply = await self.backend.complete(ModelRequest(prompt, ctx, list(feedback)))
            except ModelError as exc:
                # The answers of this step so far (invalid ones) stay in the step record: IAR counts them.
                exc.calls = tuple(calls)
                raise
            model_time += time.perf_counter() - t0
            self.calls += count
            try:
                parsed = parse_answer(reply.text, self.variant, library, coverage=self.settings.prediction_coverage)
                calls.append(ModelCall(raw_answer=recorded_answer(reply.text), valid=True, latency_s=reply.latency_s,
                                       tokens_in=reply.tokens_in, tokens_out=reply.tokens_out,
                                       structured=reply.structured, tokens_cached=reply.cached_tokens))
                failure = reply.failure
                break
            except InvalidAnswer as exc:
                self.invalid += count
                calls.append(ModelCall(raw_answer=recorded_answer(reply.text), valid=False, error=str(exc),
                                       latency_s=reply.latency_s,
                                       tokens_in=reply.tokens_in, tokens_out=reply.tokens_out,
                                       structured=reply.structured, tokens_cached=reply.cached_tokens))
                feedback.append((reply.text, str(exc)))
                log.info("invalid answer (step %d): %s", step, plain_text(exc))  # it may quote the answer
        scores: tuple[SkillScore, ...] = ()
        if parsed is not None and parsed.scores:
            parsed, scores = await self._weigh(parsed)
        rec = ReasoningStep(
            vehicle_id=self.settings.vehicle_id, task_id=self.req.task_id, step=step, backend=self.backend.name,
            variant=self.variant, prompt=prompt.parts, image_stamp_ns=obs.image_stamp_ns if prompt.has_image else 0,
            calls=tuple(calls), drt=parsed.drt if parsed else None, ste=parsed.ste if parsed else None,
            valid=parsed is not None, retries=len(calls) - 1, scores=scores, plan=parsed.plan if parsed else ())
        return StepResult(rec, parsed, failure, first_call - t_prompt, first_call), model_time

    async def _next(self, compiler: PromptCompiler, library: SkillLibrary,
                    obs: Observation) -> tuple[StepResult, float]:
        """This step's decision and model seconds: the model's answer, or for plan-once after its one plan the
        plan's next step (no model call)."""
        if self.plan is not None:
            return self._planned(obs), 0.0
        result, model_time = await self._decide(compiler, library, obs)
        if self.variant == "plan_once" and result.parsed is not None:
            self.plan = list(result.parsed.plan[1:])  # the first step runs now
        return result, model_time

    def _speculating(self) -> bool:
        return (self.settings.speculate and self.backend.speculates
                and self.variant not in SPECULATION_VARIANTS_EXCLUDED
                and self.steps < self.settings.max_steps)  # no step after the last one

    def _speculate(self, compiler: PromptCompiler, library: SkillLibrary, obs: Observation,
                   parsed: ParsedAnswer) -> Guess | None:
        """Ask for step k+1 now, on the observation skill k's predicted success implies; None when its outcome
        cannot be predicted (speculation.assume)."""
        ste, drt = parsed.ste, parsed.drt
        assumed = assume(self.history, obs, library, ste, self.steps, (drt.action_predictions or {}).get(ste.skill, ""),
                         drt.summary or "", drt.reasoning or "")
        if assumed is None:
            return None
        self.speculations += 1
        ctx = policy_context(self.req.command, self.variant, library, assumed.history, assumed.obs)
        task = asyncio.create_task(self._decide(compiler, library, assumed.obs, assumed.history, self.steps + 1,
                                                count=False))
        return Guess(task, ctx, assumed.obs.state.position.z if assumed.obs.state is not None else None)

    async def _drop_guess(self) -> None:
        """Cancel the speculative call (if any) and wait for it to stop. A cancel of this loop meanwhile (T_max,
        an abort) still reaches the loop: asyncio.wait re-raises the caller's cancellation, never the guess's."""
        guess, self._guess = self._guess, None
        if guess is None:
            return
        guess.task.cancel()
        await asyncio.wait({guess.task})
        if not guess.task.cancelled():
            guess.task.exception()  # retrieved: a failed guess is not logged as "never retrieved"

    async def _take_guess(self, library: SkillLibrary, obs: Observation) -> tuple[StepResult, float] | None:
        """This step's speculative answer when the skill before it ended as predicted and the policy would read
        the same from the fresh observation (speculation.disagreement); else None (it is discarded, with the
        reason in the log). The seconds returned are the wait for it after the skill's end (often none)."""
        guess = self._guess
        if guess is None:
            return None
        fresh = policy_context(self.req.command, self.variant, library, self.history, obs)
        why = disagreement(guess.context, fresh) or height_problem(guess.height, obs)
        if why is None:
            t0 = time.perf_counter()
            try:
                result, _ = await guess.task
            except Exception as exc:  # a model outage, or anything else: the step is asked again, not lost
                why = f"the model failed: {type(exc).__name__}: {exc}"
            else:
                if result.parsed is None:
                    why = "its answers were invalid"
        if why is not None:
            log.info("task %s step %d: speculative answer discarded: %s", self.req.task_id, self.steps, why)
            await self._drop_guess()
            return None
        self._guess = None
        self.speculations_used += 1
        self.calls += len(result.record.calls)
        self.invalid += sum(not c.valid for c in result.record.calls)
        record = result.record.model_copy(update={"speculative": True})
        # The user waited for none of the prompt's compilation, only for what was left of the model's answer.
        return replace(result, record=record, prompt_s=0.0, first_call=t0), time.perf_counter() - t0

    def _planned(self, obs: Observation) -> StepResult:
        """Plan-once: the plan's next step as this step's record (no model call, no prompt)."""
        if not self.plan:  # a plan ends with done, which ends the task: only a bug gets here
            raise AermaniError("the plan has no step left")
        ste = self.plan.pop(0)
        rec = ReasoningStep(vehicle_id=self.settings.vehicle_id, task_id=self.req.task_id, step=self.steps,
                            backend=self.backend.name, variant=self.variant, ste=ste, valid=True)
        return StepResult(rec, ParsedAnswer(DescriptiveReasoningTrace(), ste), first_call=time.perf_counter())

    async def _weigh(self, parsed: ParsedAnswer) -> tuple[ParsedAnswer, tuple[SkillScore, ...]]:
        """SayCan: each candidate's score times the executor's feasibility (check_skill: 1 or 0); the highest
        weighted candidate is the step's skill. When the executor would accept none, the top-rated one runs
        (the executor then refuses it with its reason, which the History shows)."""
        scored: list[SkillScore] = []
        for skill, argument, score in parsed.scores:
            req = SkillRequest(skill=skill, argument=argument, task_id=self.req.task_id, step=self.steps)
            refused = await self._feasible(req, "SayCan weight 0")
            scored.append(SkillScore(skill=skill, argument=argument, score=score, feasible=refused is None,
                                     reason=refused.message if refused is not None else "",
                                     weighted=score if refused is None else 0.0))
        feasible = [c for c in scored if c.feasible]
        best = max(feasible or scored, key=lambda c: c.weighted if feasible else c.score)
        ste = SkillToExecute(skill=best.skill, argument=best.argument)
        return ParsedAnswer(parsed.drt, ste, parsed.recovered, parsed.scores, parsed.plan), tuple(scored)

    def _needs_approval(self, skill: str) -> bool:
        wanted = set(self.settings.approval)
        return bool(wanted) and (skill in wanted or self.categories.get(skill, "") in wanted)

    async def _feasible(self, req: SkillRequest, purpose: str = "no approval asked") -> SkillStatus | None:
        """None when the executor would accept the skill now; else the rejection that ends the step, with the
        executor's reason and outcome code, as if run_skill had refused it. An operator is never asked to approve
        a skill the executor would then refuse (a grasp out of reach)."""
        started = now_ns()
        try:
            check = await self.world.check_skill(req)
        except AermaniError as exc:
            check = SkillAccept(accepted=False, goal_id="", reason=f"executor unreachable: {exc}")
        if check.accepted:
            return None
        log.info("%s(%s) not feasible now (%s): the executor refuses it: %s", req.skill, req.argument or "",
                 purpose, check.reason)
        return SkillStatus(goal_id="", skill=req.skill, argument=req.argument, state=SkillState.REJECTED,
                           message=check.reason, task_id=req.task_id, step=req.step, started_ns=started,
                           ended_ns=now_ns(), outcome=check.outcome or SkillOutcome())

    async def _approved(self, req: SkillRequest, reasoning: str) -> SkillStatus | None:
        """None when the skill may run; else the status that ends the step (rejected, or failed on timeout)."""
        timeout = self.settings.approval_timeout_s
        ask = ApprovalStatus(vehicle_id=self.settings.vehicle_id, task_id=req.task_id, step=req.step, skill=req.skill,
                             argument=req.argument, reasoning=reasoning, expires_ns=now_ns() + int(timeout * 1e9))
        started = now_ns()
        decided = await self.world.request_approval(ask, timeout)
        log.info("approval of %s(%s): %s %s", req.skill, plain_text(req.argument or ""), decided.state.value,
                 plain_text(decided.reason))
        base = {"goal_id": "", "skill": req.skill, "argument": req.argument, "task_id": req.task_id, "step": req.step,
                "started_ns": started}
        if decided.state is ApprovalState.APPROVED:
            return None
        if decided.state is ApprovalState.REJECTED:
            return SkillStatus(**base, state=SkillState.REJECTED, ended_ns=now_ns(),
                               message=f"rejected by the operator ({decided.operator or 'operator'}): "
                                       f"{decided.reason or 'no reason given'}; choose another skill")
        await self.world.hold(req.task_id, "approval timeout")
        return SkillStatus(**base, state=SkillState.FAILED, ended_ns=now_ns(),
                           message=f"no operator decision within {timeout:.0f} s; vehicle held")

    async def _send(self, req: SkillRequest, timeout: float) -> tuple[SkillAccept, SkillStatus | None]:
        """`world.run_skill`; with no executor answering, wait for one (a restart takes 1-2 s) and send the same
        skill again, instead of spending the next steps on "executor unreachable". ServerLost (the executor
        died mid-skill) passes through; no answer after the wait holds and raises ExecutorUnreachable."""
        try:
            return await self.world.run_skill(req, timeout)
        except ServerLost:
            raise
        except AermaniError as exc:
            log.warning("task %s: executor unreachable (%s); waiting up to %.0f s for it", req.task_id, exc,
                        self.settings.link_wait_s)
        try:
            return await self.world.run_skill(req, timeout, ready_timeout=self.settings.link_wait_s)
        except ServerLost:
            raise
        except AermaniError as again:
            await self.world.hold(req.task_id, "executor unreachable")
            raise ExecutorUnreachable(f"executor unreachable for {self.settings.link_wait_s:.0f} s "
                                      f"({again}); vehicle held (if it still listens)") from again

    async def _execute(self, req: SkillRequest, timeout: float, reasoning: str = "") -> SkillStatus:
        """Run one skill on the executor and wait for its terminal status; raises only ExecutorUnreachable (no
        executor answered, even after waiting for one: the task ends). A skill that needs the operator's
        approval waits for it first."""
        if self._needs_approval(req.skill):
            refused = await self._feasible(req) or await self._approved(req, reasoning)
            if refused is not None:
                return refused
        started = now_ns()
        try:
            accept, st = await self._send(req, timeout)
        except ServerLost as exc:  # the executor died mid-skill: known within Zenoh's lease, not at the timeout
            await self.world.hold(req.task_id, "executor lost")
            return SkillStatus(goal_id="", skill=req.skill, argument=req.argument, state=SkillState.FAILED,
                               message=f"executor stopped mid-skill: {exc}", task_id=req.task_id, step=req.step,
                               started_ns=started, ended_ns=now_ns())
        if not accept.accepted:
            # The refusal's code and facts (out_of_reach, blocked...) travel with the accept reply.
            return SkillStatus(goal_id="", skill=req.skill, argument=req.argument, state=SkillState.REJECTED,
                               message=accept.reason, task_id=req.task_id, step=req.step, started_ns=started,
                               ended_ns=now_ns(), outcome=accept.outcome or SkillOutcome())
        if st is not None:
            self._effect_ns = st.ended_ns or st.stamp_ns  # the executor's clock, like the bridge's state stamps
        if st is None:
            await self.world.hold(req.task_id, "skill timeout")
            return SkillStatus(goal_id=accept.goal_id, skill=req.skill, argument=req.argument,
                               state=SkillState.TIMEOUT, message=f"no terminal status within {timeout:.0f} s; held",
                               task_id=req.task_id, step=req.step, started_ns=started, ended_ns=now_ns())
        return st
