"""The reasoner service: serves `reasoner/start_task`, runs one task at a time per vehicle, publishes steps."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time

from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

from services.reasoner import tracing
from services.reasoner.backends import Backend, make_backend
from services.reasoner.loop import TaskRunner, World
from services.reasoner.prompt import Observation
from services.reasoner.settings import ReasonerSettings
from shared.bus import Bus, Subscription
from shared.errors import AermaniError, ConfigError
from shared.messages import (
    Abort,
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
)
from shared.sensors import decode_proto, stamp_to_ns

log = logging.getLogger("aermani.reasoner")


class AbortSignal(asyncio.Event):
    def __init__(self) -> None:
        super().__init__()
        self.reason = ""


class _Slot:
    """Newest value of a stream with its local receive time, and an event to wait for a newer one."""

    def __init__(self) -> None:
        self.value = None
        self.receive_ns = 0
        self.changed = asyncio.Event()

    def put(self, value: object, receive_ns: int) -> None:
        self.value, self.receive_ns = value, receive_ns
        self.changed.set()
        self.changed = asyncio.Event()

    async def newer_than(self, ns: int, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while self.receive_ns <= ns:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.changed.wait(), remaining)


class BusWorld(World):
    """The loop's view of the stack over Zenoh."""

    def __init__(self, bus: Bus, settings: ReasonerSettings) -> None:
        self.bus = bus
        self.settings = settings
        self.keys = settings.keys
        self.frame = _Slot()
        self.state = _Slot()
        self.detections = _Slot()
        self.memory = _Slot()
        self._statuses: dict[str, SkillStatus] = {}
        self._waiters: dict[str, asyncio.Future[SkillStatus]] = {}

    async def pump(self) -> None:
        """Keep the slots and the status table up to date (runs for the service's lifetime)."""
        subs: list[tuple[Subscription, object]] = [
            (self.bus.subscribe(self.keys.camera_color, None, maxsize=2), self.frame),
            (self.bus.subscribe(self.keys.autopilot_state, VehicleState, maxsize=5), self.state),
            (self.bus.subscribe(self.keys.detections, Detections, maxsize=5), self.detections),
            (self.bus.subscribe(self.keys.memory, WorkingMemory, maxsize=5), self.memory),
        ]
        status_sub = self.bus.subscribe(self.keys.skill_status, SkillStatus, maxsize=1000, overflow="drop_oldest")

        async def feed(sub: Subscription, slot: _Slot) -> None:
            while True:
                rec = await sub.recv_sample()
                value = rec.value
                if slot is self.frame:
                    try:
                        msg = decode_proto(CompressedImage, value)
                    except AermaniError as exc:
                        log.warning("bad colour frame: %s", exc)
                        continue
                    value = (bytes(msg.data), stamp_to_ns(msg.timestamp))
                slot.put(value, rec.receive_ns)

        async def statuses() -> None:
            while True:
                st = await status_sub.recv()
                if not st.state.terminal:
                    continue
                self._statuses[st.goal_id] = st
                if len(self._statuses) > 500:  # bounded: old goals are never asked for again
                    self._statuses.pop(next(iter(self._statuses)))
                fut = self._waiters.pop(st.goal_id, None)
                if fut is not None and not fut.done():
                    fut.set_result(st)

        async with asyncio.TaskGroup() as tg:
            for sub, slot in subs:
                tg.create_task(feed(sub, slot))
            tg.create_task(statuses())

    async def skill_library(self) -> SkillLibrary:
        return await self.bus.query(self.keys.skills, None, SkillLibrary, timeout=self.settings.library_timeout_s)

    async def observe(self, newer_than_ns: int) -> Observation:
        if newer_than_ns and self.settings.frame_wait_s > 0:
            await self.frame.newer_than(newer_than_ns, self.settings.frame_wait_s)
            await self.detections.newer_than(newer_than_ns, min(0.3, self.settings.frame_wait_s))
        frame = self.frame.value
        det = self.detections.value
        return Observation(image_jpeg=frame[0] if frame else None, image_stamp_ns=frame[1] if frame else 0,
                           state=self.state.value, detections=det.items if det else (), memory=self.memory.value)

    async def run_skill(self, request: SkillRequest) -> SkillAccept:
        return await self.bus.query(self.keys.run_skill, request, SkillAccept, timeout=10.0)

    async def wait_status(self, goal_id: str, timeout: float) -> SkillStatus | None:
        if goal_id in self._statuses:
            return self._statuses[goal_id]
        fut = self._waiters.setdefault(goal_id, asyncio.get_running_loop().create_future())
        try:
            return await asyncio.wait_for(asyncio.shield(fut), timeout)
        except TimeoutError:
            self._waiters.pop(goal_id, None)
            return self._statuses.get(goal_id)


class Reasoner:
    def __init__(self, bus: Bus, settings: ReasonerSettings, world: World | None = None) -> None:
        self.bus = bus
        self.settings = settings
        self.world = world or BusWorld(bus, settings)
        self.default_backend: Backend = make_backend(settings)
        self.current: tuple[TaskRequest, asyncio.Task, AbortSignal] | None = None
        self._lock = asyncio.Lock()

    async def start_task(self, req: TaskRequest) -> TaskAccept:
        async with self._lock:
            if self.current is not None and not self.current[1].done():
                return TaskAccept(accepted=False, task_id=req.task_id,
                                  reason=f"task {self.current[0].task_id} already runs on vehicle "
                                         f"{self.settings.vehicle_id}; abort it first")
            backend = self.default_backend
            if req.backend and req.backend != self.settings.backend:
                try:
                    backend = make_backend(self.settings, req.backend)
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
        self.bus.publish(self.settings.keys.task_status, st)

    def on_abort(self, ab: Abort) -> None:
        if self.current is None or self.current[1].done():
            return
        req, _task, signal = self.current
        if ab.task_id is None or ab.task_id == req.task_id:
            signal.reason = f"{ab.reason} (from {ab.source})"
            signal.set()

    async def close(self) -> None:
        if self.current is not None and not self.current[1].done():
            self.current[2].reason = "reasoner shutting down"
            self.current[2].set()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.current[1], 5.0)
        await self.default_backend.aclose()
        await asyncio.to_thread(tracing.flush)


async def run(bus: Bus, settings: ReasonerSettings, stop: asyncio.Event) -> None:
    reasoner = Reasoner(bus, settings)
    aborts = bus.subscribe(settings.keys.abort, Abort, maxsize=50)
    bus.serve(settings.keys.start_task, reasoner.start_task, TaskRequest)
    log.info("reasoner ready: backend %s, variant %s", reasoner.default_backend.name, settings.variant)

    async def abort_loop() -> None:
        while True:
            reasoner.on_abort(await aborts.recv())

    try:
        async with asyncio.TaskGroup() as tg:
            if isinstance(reasoner.world, BusWorld):
                tg.create_task(reasoner.world.pump())
            tg.create_task(abort_loop())
            await stop.wait()
            raise _Stop
    except* _Stop:
        pass
    finally:
        await reasoner.close()


class _Stop(Exception):
    pass


__all__ = ["run", "Reasoner", "BusWorld", "TaskState"]
