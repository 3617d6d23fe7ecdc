"""The reasoner service: serves `reasoner/start_task`, runs one task at a time per vehicle, publishes steps."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import time

from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

from services.reasoner import tracing
from services.reasoner.backends import make_backend
from services.reasoner.backends.base import Backend
from services.reasoner.loop import TaskRunner, World
from services.reasoner.prompt import Observation
from services.reasoner.settings import ReasonerSettings
from shared.action import TASK_ACTION, ActionServer, GoalHandle, ServerGoalHandle, skill_client
from shared.bus import Bus, Latest, Subscription, query_ready
from shared.errors import AermaniError, ConfigError
from shared.keys import FLEET_ABORT
from shared.messages import (
    Abort,
    ApprovalDecision,
    ApprovalState,
    ApprovalStatus,
    CancelGoal,
    CancelReply,
    Detections,
    SkillAccept,
    SkillLibrary,
    SkillRequest,
    SkillStatus,
    TaskAccept,
    TaskRequest,
    TaskState,
    TaskStatus,
    VehicleState,
    WorkingMemory,
    now_ns,
)
from shared.sensors import decode_proto, stamp_to_ns

log = logging.getLogger("aermani.reasoner")
GOAL_SEND_TIMEOUT_S = 10.0  # a skill goal's accept reply comes within this (a cancel in its window waits as long)


class AbortSignal(asyncio.Event):
    """Ends the running task: an abort (the executor got it too and holds) or a cancel (`cancel`: the loop
    cancels the running skill, which holds, before it reports)."""

    def __init__(self) -> None:
        super().__init__()
        self.reason = ""
        self.cancel = False


class BusWorld(World):
    """The loop's view of the stack over Zenoh."""

    def __init__(self, bus: Bus, settings: ReasonerSettings) -> None:
        self.bus = bus
        self.settings = settings
        self.keys = settings.keys
        latest = functools.partial(bus.subscribe, overflow="latest")  # only the newest value is read
        self.frame: Latest[tuple[bytes, int]] = Latest(latest(self.keys.camera_color, maxsize=2), _jpeg)
        self.state: Latest[VehicleState] = Latest(latest(self.keys.autopilot_state, maxsize=5))
        self.detections: Latest[Detections] = Latest(latest(self.keys.detections, maxsize=5))
        self.memory: Latest[WorkingMemory] = Latest(latest(self.keys.memory, maxsize=5))
        self.skills = skill_client(bus, settings.vehicle_id)
        self.running: GoalHandle[SkillAccept, SkillStatus] | None = None
        self.sending: asyncio.Future[None] | None = None
        """Resolved once the skill goal on its way has its accept reply (or failed to get one): the executor
        starts a goal, and publishes it running, before its reply reaches here."""
        self.approvals: dict[str, tuple[ApprovalStatus, asyncio.Future[ApprovalDecision]]] = {}

    async def pump(self) -> None:
        """Keep the latest values up to date and route skill statuses (runs for the service's lifetime)."""
        self.skills.start()
        try:
            async with asyncio.TaskGroup() as tg:
                for latest in (self.frame, self.state, self.detections, self.memory):
                    tg.create_task(latest.run())
        finally:
            await self.skills.close()

    async def skill_library(self) -> SkillLibrary:
        # An executor not yet known behind the router (a new route, a supervised restart) is waited for like a
        # skill's (`_send`): a NoResponder at once is no reason to fail the task.
        return await query_ready(self.bus, self.keys.skills, None, timeout=self.settings.library_timeout_s,
                                 ready_timeout=self.settings.link_wait_s)

    async def observe(self, newer_than_ns: int) -> Observation:
        t0 = t1 = t2 = time.perf_counter()
        if newer_than_ns and self.settings.frame_wait_s > 0:
            await self.frame.newer_than(newer_than_ns, self.settings.frame_wait_s)
            t1 = time.perf_counter()
            await self.detections.newer_than(newer_than_ns, min(0.3, self.settings.frame_wait_s))
            t2 = time.perf_counter()
        if newer_than_ns:
            # Zenoh does not order samples across keys: the state that shows the skill's effect (e.g. airborne
            # after the take-off) may arrive after its status. The autopilot state comes at >= 20 Hz.
            await self.state.newer_than(newer_than_ns, 1.0)
        t3 = time.perf_counter()
        frame = self.frame.value
        det = self.detections.value
        return Observation(image_jpeg=frame[0] if frame else None, image_stamp_ns=frame[1] if frame else 0,
                           state=self.state.value, state_age_s=self.state.age_s if self.state.value else 0.0,
                           detections=det.items if det else (), memory=self.memory.value,
                           frame_wait_s=t1 - t0, detections_wait_s=t2 - t1, state_wait_s=t3 - t2)

    async def check_skill(self, request: SkillRequest) -> SkillAccept:
        reply: SkillAccept = await self.bus.query(self.keys.check_skill, request, timeout=10.0)
        return reply

    async def run_skill(self, request: SkillRequest, timeout: float,
                        ready_timeout: float = 0.0) -> tuple[SkillAccept, SkillStatus | None]:
        followed = timeout > 0  # a goal whose end this waits for (a hold is sent and not followed)
        sending: asyncio.Future[None] | None = None
        if followed:  # a hold sent meanwhile leaves the goal on its way as it is
            sending = self.sending = asyncio.get_running_loop().create_future()
        try:
            goal = await self.skills.send_goal(request, timeout=GOAL_SEND_TIMEOUT_S, ready_timeout=ready_timeout)
            if goal.accepted and followed:
                self.running = goal
        finally:
            if sending is not None:
                sending.set_result(None)
        try:
            return goal.accept, await goal.result(timeout) if goal.accepted and followed else None
        finally:
            if self.running is goal:
                self.running = None
            goal.close()

    async def cancel_skill(self, task_id: str, reason: str) -> SkillStatus | None:
        sending = self.sending
        if self.running is None and sending is not None and not sending.done():
            # A cancel between the executor accepting a goal (its status already says running) and its reply
            # reaching here: wait for the reply, then cancel that goal (holding alone would leave it unnamed).
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.shield(sending), GOAL_SEND_TIMEOUT_S + 2.0)
        goal = self.running
        if goal is None or goal.accept.goal_id == "":
            await self.hold(task_id, reason)
            return None
        try:
            reply = await goal.cancel(reason=reason, source="reasoner")
        except AermaniError as exc:
            log.warning("cancel of skill goal %s failed: %s", goal.goal_id, exc)
            reply = CancelReply(accepted=False, reason=str(exc))
        if not reply.accepted:  # it ended meanwhile, or the executor is gone: hold all the same
            await self.hold(task_id, reason)
        with contextlib.suppress(AermaniError):
            return await goal.result(timeout=10.0)
        return None


    async def request_approval(self, request: ApprovalStatus, timeout: float) -> ApprovalStatus:
        """Publish the pending request, wait for the operator's decision (`decide`) or the timeout, publish
        the outcome."""
        fut: asyncio.Future[ApprovalDecision] = asyncio.get_running_loop().create_future()
        self.approvals[request.approval_id] = (request, fut)
        self.bus.publish(self.keys.approval, request)
        try:
            decision = await asyncio.wait_for(fut, timeout)
        except TimeoutError:
            done = request.model_copy(update={"state": ApprovalState.EXPIRED, "stamp_ns": now_ns(),
                                              "reason": f"no decision within {timeout:.0f} s"})
        else:
            done = request.model_copy(update={
                "state": ApprovalState.APPROVED if decision.approved else ApprovalState.REJECTED,
                "reason": decision.reason, "operator": decision.operator, "stamp_ns": now_ns()})
        finally:
            self.approvals.pop(request.approval_id, None)
        self.bus.publish(self.keys.approval, done)
        return done

    async def decide(self, decision: ApprovalDecision) -> CancelReply:
        """`reasoner/decide_approval`: settle a pending request (once)."""
        pending = self.approvals.get(decision.approval_id)
        if pending is None or pending[1].done():
            return CancelReply(accepted=False, reason=f"approval {decision.approval_id} is not pending on vehicle "
                                                      f"{self.settings.vehicle_id} (decided, expired or unknown)")
        pending[1].set_result(decision)
        return CancelReply(accepted=True)


def _jpeg(payload: bytes) -> tuple[bytes, int]:
    msg = decode_proto(CompressedImage, payload)
    return bytes(msg.data), stamp_to_ns(msg.timestamp)


class Reasoner:
    """Serves tasks over the bus: runs one task at a time through the policy loop and publishes steps and status."""

    def __init__(self, bus: Bus, settings: ReasonerSettings, world: World | None = None,
                 backend: Backend | None = None) -> None:
        self.bus = bus
        self.settings = settings
        self.world = world or BusWorld(bus, settings)
        self.default_backend: Backend = backend if backend is not None else make_backend(settings)
        self.current: tuple[TaskRequest, asyncio.Task, AbortSignal] | None = None
        self._lock = asyncio.Lock()
        self.action = ActionServer(bus, TASK_ACTION, settings.vehicle_id, goal_callback=self.start_task,
                                   execute_callback=self._follow, cancel_callback=self._cancel)

    async def start_task(self, req: TaskRequest) -> TaskAccept:
        async with self._lock:
            if self.current is not None and not self.current[1].done():
                return TaskAccept(accepted=False, task_id=req.task_id,
                                  reason=f"task {self.current[0].task_id} already runs on vehicle "
                                         f"{self.settings.vehicle_id}; abort it first")
            backend = self.default_backend
            if req.backend and req.backend != self.settings.backend:
                try:
                    backend = await asyncio.to_thread(make_backend, self.settings, req.backend)  # as in run()
                except (ConfigError, ValueError) as exc:
                    return TaskAccept(accepted=False, task_id=req.task_id, reason=str(exc))
            abort = AbortSignal()
            runner = TaskRunner(req, self.settings, backend, self.world, publish_step=self._pub_step,
                                publish_status=self._pub_status)
            task = asyncio.create_task(self._run(runner, backend, abort), name=f"task-{req.task_id}")
            self.current = (req, task, abort)
            log.info("task %s accepted: %r (backend %s, variant %s)", req.task_id, req.command, backend.name,
                     runner.variant)
            return TaskAccept(accepted=True, task_id=req.task_id)

    async def _run(self, runner: TaskRunner, backend: Backend, abort: AbortSignal) -> TaskStatus:
        try:
            final = await runner.run(abort)
            log.info("task %s ended %s: %s", runner.req.task_id, final.state.value, final.message)
            return final
        finally:
            if backend is not self.default_backend:
                with contextlib.suppress(Exception):
                    await backend.aclose()
            await asyncio.to_thread(tracing.flush)  # a no-op unless AERMANI_REASONER_OTLP_ENDPOINT is set

    def _pub_step(self, rec) -> None:
        self.bus.publish(self.settings.keys.reasoning_step, rec)

    def _pub_status(self, st: TaskStatus) -> None:
        handle = self.action.goals.get(st.task_id)
        if handle is not None:  # its terminal status ends the goal on the action server
            handle.publish(st)
        else:
            self.action.publish(st)

    async def _follow(self, handle: ServerGoalHandle[TaskRequest, TaskStatus]) -> None:
        """Execute callback: the task runs as `start_task` started it; its statuses reach the handle."""
        if self.current is not None and self.current[0].task_id == handle.goal_id:
            with contextlib.suppress(Exception):
                await asyncio.shield(self.current[1])

    async def _cancel(self, handle: ServerGoalHandle[TaskRequest, TaskStatus], req: CancelGoal) -> CancelReply:
        return await self.cancel_task(req)

    def on_abort(self, ab: Abort) -> None:
        if self.current is None or self.current[1].done():
            return
        req, _task, signal = self.current
        if ab.task_id is None or ab.task_id == req.task_id:
            signal.reason = f"{ab.reason} (from {ab.source})"
            signal.set()

    async def cancel_task(self, req: CancelGoal) -> CancelReply:
        """Action protocol: cancel the running task. Its running skill is cancelled (the executor stops it
        and holds) before the task ends ABORTED with the reason."""
        if self.current is None or self.current[1].done() or self.current[0].task_id != req.goal_id:
            return CancelReply(accepted=False, reason=f"task {req.goal_id} is not running on vehicle "
                                                      f"{self.settings.vehicle_id}")
        self.current[2].reason = f"{req.reason} (cancelled by {req.source})"
        self.current[2].cancel = True
        self.current[2].set()
        return CancelReply(accepted=True)

    async def close(self) -> None:
        if self.current is not None and not self.current[1].done():
            self.current[2].reason = "reasoner shutting down"
            self.current[2].set()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.current[1], 5.0)
        await self.default_backend.aclose()
        await asyncio.to_thread(tracing.flush)


async def run(bus: Bus, settings: ReasonerSettings, stop: asyncio.Event) -> None:
    # Built off the event loop: a model backend imports its SDK on first use (seconds of CPU, more on a loaded
    # machine), and a loop blocked that long stops the heartbeat, so the launcher kills the reasoner as hung
    # and it never comes up (seen under load: five restarts in 35 s, the demo never started its task).
    reasoner = Reasoner(bus, settings, backend=await asyncio.to_thread(make_backend, settings))
    aborts = [bus.subscribe(settings.keys.abort, maxsize=50), bus.subscribe(FLEET_ABORT, maxsize=50)]
    reasoner.action.start()
    if isinstance(reasoner.world, BusWorld):
        bus.serve(settings.keys.decide_approval, reasoner.world.decide)
    log.info("reasoner ready: backend %s, variant %s", reasoner.default_backend.name, settings.variant)

    async def abort_loop(sub: Subscription[Abort]) -> None:
        while True:
            reasoner.on_abort(await sub.recv())

    try:
        async with asyncio.TaskGroup() as tg:
            if isinstance(reasoner.world, BusWorld):
                tg.create_task(reasoner.world.pump())
            for sub in aborts:
                tg.create_task(abort_loop(sub))
            await stop.wait()
            raise _Stop
    except* _Stop:
        pass
    finally:
        await reasoner.close()


class _Stop(Exception):
    pass


__all__ = ["run", "Reasoner", "BusWorld", "TaskState"]
