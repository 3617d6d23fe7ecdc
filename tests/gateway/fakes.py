"""Stand-ins for the vehicle side of the bus (reasoner, executor, bridge, camera) and a harness that runs a
real Zenoh router, the stand-ins and optionally the gateway app in a background thread with its own loop."""

from __future__ import annotations

import asyncio
import contextlib
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from shared.action import TASK_ACTION, ActionServer
from shared.bus import Bus
from shared.keys import FLEET_ABORT, Keys
from shared.messages import (
    Abort,
    AbortAck,
    ApprovalDecision,
    ApprovalState,
    ApprovalStatus,
    CancelGoal,
    CancelReply,
    DescriptiveReasoningTrace,
    Detection,
    Detections,
    ModelCall,
    ReasoningStep,
    SkillLibrary,
    SkillState,
    SkillStatus,
    SkillToExecute,
    TaskAccept,
    TaskRequest,
    TaskState,
    TaskStatus,
    Vec3,
    VehicleState,
    new_id,
)
from shared.sensors import color_message
from tests.helpers import free_port

SKILLS = ["takeoff", "obj_localization", "forward", "grasp", "placement_localization", "place"]


class FakeVehicle:
    """A real queryable `reasoner/start_task` that runs a scripted task: a few steps, each with a skill
    status, then `succeeded`; a command containing "until abort" keeps stepping until an Abort arrives.
    Also publishes vehicle state, camera frames and answers aborts like the executor (AbortAck).
    Held by `release` (set it on the harness loop): "slow to stop" acknowledges an abort at once but reports
    the task aborted only then; "withholds its last step" reports the end before its last step, sent then."""

    def __init__(self, bus: Bus, vehicle_id: str = "am1", steps: int = 3, step_delay_s: float = 0.3,
                 services: tuple[str, ...] = ("reasoner", "executor", "autopilot_bridge")) -> None:
        self.bus = bus
        self.keys = Keys(vehicle_id)
        self.vehicle_id = vehicle_id
        self.n_steps = steps
        self.step_delay_s = step_delay_s
        self.services = services
        self.current: asyncio.Task | None = None
        self.current_req: TaskRequest | None = None
        self.aborts: list[Abort] = []
        self.frames = 0
        self.decisions: list[ApprovalDecision] = []
        self._pending: dict[str, asyncio.Future[ApprovalDecision]] = {}
        self._tasks: list[asyncio.Task] = []
        self.release = asyncio.Event()

    async def start(self) -> None:
        for s in self.services:
            self.bus.declare_token(self.keys.alive(s))
        # The task action through the one ActionServer, like the reasoner (statuses: _task_status).
        self.action = ActionServer(self.bus, TASK_ACTION, self.vehicle_id, goal_callback=self._start,
                                   cancel_callback=lambda _handle, req: self._cancel(req)).start()
        self.bus.serve(self.keys.decide_approval, self._decide)
        if "executor" in self.services:
            self.bus.serve(self.keys.skills, self._skills)
            self.bus.serve(self.keys.restore_memory, self._restore_memory)
        self._tasks += [asyncio.create_task(self._aborts(self.bus.subscribe(key))) for key in (self.keys.abort,
                                                                                                FLEET_ABORT)]
        self._tasks.append(asyncio.create_task(self._publish_sensors()))

    async def stop(self) -> None:
        for t in [*self._tasks, *([self.current] if self.current else [])]:
            t.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t

    def status(self, req: TaskRequest, state: TaskState, steps: int, message: str = "") -> TaskStatus:
        return TaskStatus(vehicle_id=self.vehicle_id, task_id=req.task_id, command=req.command, state=state,
                          message=message, steps=steps, model_calls=steps + (1 if steps >= 2 else 0),
                          invalid_answers=1 if steps >= 2 else 0, backend="rules",
                          ended_ns=time.time_ns() if state.terminal else 0)

    async def _start(self, req: TaskRequest) -> TaskAccept:
        if self.current is not None and not self.current.done():
            return TaskAccept(accepted=False, task_id=req.task_id, reason="a task is already running")
        self.current_req = req
        self.current = asyncio.create_task(self._run_task(req))
        return TaskAccept(accepted=True, task_id=req.task_id)

    def _task_status(self, st: TaskStatus) -> None:
        handle = self.action.goals.get(st.task_id)
        if handle is not None:
            handle.publish(st)
        else:
            self.action.publish(st)

    async def _restore_memory(self, req: object) -> CancelReply:
        return CancelReply(accepted=False, reason="this stand-in executor keeps no working memory to restore")

    async def _skills(self, _req: object) -> SkillLibrary:
        from services.reasoner.library import default_library

        return default_library()

    async def _cancel(self, req: CancelGoal) -> CancelReply:
        if self.current is None or self.current.done() or self.current_req is None \
                or self.current_req.task_id != req.goal_id:
            return CancelReply(accepted=False, reason=f"task {req.goal_id} is not running")
        self.current.cancel()
        self._task_status(self.status(self.current_req, TaskState.ABORTED, 0, req.reason))
        return CancelReply(accepted=True)

    async def _decide(self, d: ApprovalDecision) -> CancelReply:
        fut = self._pending.pop(d.approval_id, None)
        if fut is None or fut.done():
            return CancelReply(accepted=False, reason=f"approval {d.approval_id} is not pending")
        fut.set_result(d)
        return CancelReply(accepted=True)

    async def _approved(self, req: TaskRequest, step: int, skill: str) -> None:
        """Like the reasoner with approval on: wait for the operator; a rejection makes it ask again (the
        policy chooses the same skill again here)."""
        while True:
            ask = ApprovalStatus(vehicle_id=self.vehicle_id, task_id=req.task_id, step=step, skill=skill,
                                 reasoning=f"{skill} is the next step of the plan",
                                 expires_ns=time.time_ns() + 60_000_000_000)
            fut: asyncio.Future[ApprovalDecision] = asyncio.get_running_loop().create_future()
            self._pending[ask.approval_id] = fut
            self.bus.publish(self.keys.approval, ask)
            d = await fut
            self.decisions.append(d)
            self.bus.publish(self.keys.approval, ask.model_copy(update={
                "state": ApprovalState.APPROVED if d.approved else ApprovalState.REJECTED, "reason": d.reason}))
            if d.approved:
                return

    async def _run_task(self, req: TaskRequest) -> None:
        self._task_status(self.status(req, TaskState.RUNNING, 0))
        endless = "until abort" in req.command
        withhold = "withholds its last step" in req.command
        step = 0
        while endless or step < self.n_steps:
            step += 1
            await asyncio.sleep(self.step_delay_s)
            skill = SKILLS[(step - 1) % len(SKILLS)]
            if "with approval" in req.command and skill == "grasp":
                await self._approved(req, step, skill)
            goal = new_id("goal-")
            started = time.time_ns()
            self.bus.publish(self.keys.skill_status, SkillStatus(goal_id=goal, task_id=req.task_id, step=step,
                                                                 skill=skill, state=SkillState.RUNNING,
                                                                 started_ns=started))
            calls = [ModelCall(raw_answer="{}", valid=True, latency_s=0.1 * step)]
            if step == 2:
                calls.insert(0, ModelCall(raw_answer="nonsense", valid=False, error="not JSON", latency_s=0.5))
            self.bus.publish(self.keys.skill_status, SkillStatus(
                goal_id=goal, task_id=req.task_id, step=step, skill=skill, state=SkillState.SUCCEEDED,
                message=f"{skill} done", started_ns=started, ended_ns=time.time_ns()))
            last = not endless and step >= self.n_steps
            if withhold and last:
                self._task_status(self.status(req, TaskState.SUCCEEDED, step, "task complete"))
                await self.release.wait()
            self.bus.publish(self.keys.reasoning_step, ReasoningStep(
                vehicle_id=self.vehicle_id, task_id=req.task_id, step=step, backend="rules",
                prompt={"command": req.command}, calls=tuple(calls),
                drt=DescriptiveReasoningTrace(image_description=f"a red cup on a table (step {step})",
                                              summary=f"{step - 1} skills executed so far",
                                              action_predictions={s: f"predicted outcome of {s}" for s in SKILLS},
                                              reasoning=f"{skill} is the next step of the plan"),
                ste=SkillToExecute(skill=skill, argument="red cup" if "localization" in skill else None),
                valid=True, retries=len(calls) - 1, skill_state=SkillState.SUCCEEDED, skill_message="ok"))
            if withhold and last:
                return
            self._task_status(self.status(req, TaskState.RUNNING, step))
            if step >= 500:
                break
        self._task_status(self.status(req, TaskState.SUCCEEDED, step, "task complete"))

    async def _aborts(self, sub) -> None:
        async for ab in sub:
            self.aborts.append(ab)
            self.bus.publish(self.keys.abort_ack, AbortAck(abort_stamp_ns=ab.stamp_ns, message="holding"))
            if self.current is not None and not self.current.done():
                self.current.cancel()
                req = self.current_req
                if "slow to stop" in req.command:
                    self._tasks.append(asyncio.create_task(self._aborted_on_release(req, ab.reason)))
                else:
                    self._task_status(self.status(req, TaskState.ABORTED, 0, ab.reason))

    async def _aborted_on_release(self, req: TaskRequest, reason: str) -> None:
        await self.release.wait()
        self._task_status(self.status(req, TaskState.ABORTED, 0, reason))

    async def _publish_sensors(self) -> None:
        t0 = time.monotonic()
        while True:
            t = time.monotonic() - t0
            self.bus.publish(self.keys.autopilot_state, VehicleState(
                vehicle_id=self.vehicle_id, position=Vec3(x=math.cos(t / 3), y=math.sin(t / 3), z=1.5),
                yaw=t / 3, armed=True, mode="OFFBOARD", link_ok=True, offboard_ok=True, battery_remaining=87.0,
                battery_voltage=15.9))
            self.frames += 1
            img = np.zeros((48, 64, 3), np.uint8)
            img[:, :, 0] = (self.frames * 37) % 256
            img[: (self.frames % 48), :, 1] = 200
            self.bus.publish(self.keys.camera_color, color_message(img, time.time_ns()))
            self.bus.publish(self.keys.detections, Detections(items=(
                Detection(label="red cup", centroid=Vec3(x=1.2, y=0.3, z=0.8), size=Vec3(x=0.08, y=0.08, z=0.11),
                          confidence=0.9),)))
            await asyncio.sleep(0.2)


class Harness:
    """Router + FakeVehicle (+ the gateway app served by uvicorn, when `gateway_settings` is given) on a
    loop in a background thread, so sync tests (httpx, Playwright) can talk to it."""

    def __init__(self, tmp: Path, *, gateway_settings: dict[str, Any] | None = None, fake: bool = True,
                 **fake_kwargs: Any) -> None:
        self.tmp = tmp
        self.router_port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.router_port}"
        self.gateway_settings = gateway_settings
        self.with_fake = fake
        self.fake_kwargs = fake_kwargs
        self.http_port = free_port()
        self.base_url = f"http://127.0.0.1:{self.http_port}"
        self.loop: asyncio.AbstractEventLoop | None = None
        self.fake: FakeVehicle | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(target=self._main, name="gateway-harness", daemon=True)
        self._extra: list[tuple[FakeVehicle, Bus]] = []

    def start(self, timeout: float = 60.0) -> Harness:
        self._thread.start()
        if not self._ready.wait(timeout):
            raise TimeoutError("harness did not start")
        if self._error:
            raise self._error
        return self

    def stop(self) -> None:
        if self.loop and self._stop:
            self.loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(30)

    def add_vehicle(self, vehicle_id: str, **kwargs: Any) -> FakeVehicle:
        """Another stand-in vehicle on its own bus session to the router (a fleet); stopped with the harness."""
        async def add() -> FakeVehicle:
            bus = await Bus.open(connect=[self.endpoint])
            fake = FakeVehicle(bus, vehicle_id, **kwargs)
            await fake.start()
            self._extra.append((fake, bus))
            return fake

        return self.call(add)

    def call(self, fn: Callable[[], Any]) -> Any:
        """Run `fn` on the harness loop (coroutine functions are awaited) and return its result."""
        async def wrap():
            r = fn()
            return await r if asyncio.iscoroutine(r) else r
        return asyncio.run_coroutine_threadsafe(wrap(), self.loop).result(30)

    def _main(self) -> None:
        asyncio.run(self._amain())

    async def _amain(self) -> None:
        self.loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        router = fake_bus = server = serving = None
        try:
            router = await Bus.open(mode="router", listen=[self.endpoint], connect=[])
            if self.with_fake:
                fake_bus = await Bus.open(connect=[self.endpoint])
                self.fake = FakeVehicle(fake_bus, **self.fake_kwargs)
                await self.fake.start()
            if self.gateway_settings is not None:
                server, serving = await self._serve_gateway()
        except BaseException as exc:
            self._error = exc
        self._ready.set()
        try:
            if self._error is None:
                await self._stop.wait()
        finally:
            if server is not None:
                server.app_state_fleet_closing()
                server.should_exit = True
                with contextlib.suppress(BaseException):
                    await asyncio.wait_for(serving, 20)
            if self.fake:
                await self.fake.stop()
            for extra, extra_bus in self._extra:
                await extra.stop()
                await extra_bus.close()
            for b in (fake_bus, router):
                if b is not None:
                    await b.close()

    async def _serve_gateway(self):
        import uvicorn

        from services.gateway.app import create_app
        from services.gateway.service import _Server
        from services.gateway.settings import GatewaySettings

        settings = GatewaySettings(**{"zenoh_connect": [self.endpoint], "port": self.http_port,
                                      "db_path": str(self.tmp / "gateway.sqlite3"), **self.gateway_settings})
        app = create_app(settings)
        self.app = app
        server = _Server(uvicorn.Config(app, host="127.0.0.1", port=self.http_port, log_config=None,
                                        timeout_graceful_shutdown=2))

        def closing() -> None:
            fleet = getattr(app.state, "fleet", None)
            if fleet is not None:
                fleet.closing.set()

        server.app_state_fleet_closing = closing
        serving = asyncio.create_task(server.serve())
        while not server.started:
            if serving.done():
                serving.result()
                raise RuntimeError("gateway server stopped during startup")
            await asyncio.sleep(0.05)
        return server, serving
