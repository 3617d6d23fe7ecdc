"""The gateway's view of the fleet: bus watchers that persist task events and keep the latest state,
camera frame and liveliness of every vehicle (`aermani/v1/*/...`)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from services.gateway.store import Store
from shared.bus import Bus, Subscription
from shared.keys import (
    ALIVE,
    AUTOPILOT_STATE,
    CAMERA_COLOR,
    EXECUTOR_SKILL_STATUS,
    FLEET_ABORT,
    FLEET_ID,
    HEALTH_TOPIC,
    HEARTBEAT_TOPIC,
    PERCEPTION_DETECTIONS,
    REASONER_APPROVAL,
    REASONER_STEP,
    REASONER_TASK_STATUS,
    ROOT,
    SAFETY_ABORT_ACK,
    Keys,
    Topic,
    parse_alive_key,
)
from shared.messages import (
    AbortAck,
    ApprovalState,
    ApprovalStatus,
    Detections,
    Health,
    Heartbeat,
    ReasoningStep,
    SkillStatus,
    TaskState,
    TaskStatus,
    VehicleState,
    now_ns,
)
from shared.sensors import CompressedImage, decode_proto

log = logging.getLogger("aermani.gateway.fleet")

FINISH_GRACE_S = 2.0
# Skill ends the executor publishes a status for (a rejected request or a timeout the reasoner declared may have
# none: the grace bounds the wait for those).
_SKILL_RAN = ("succeeded", "failed", "aborted")
# A reasoner's liveliness token also vanishes when only the way to it breaks (a router restart, a network blip)
# while the process goes on with its task. Its tasks are ended as orphans unless that same process (its
# heartbeat's pid) is back within this grace; a restarted reasoner (another pid) ends them at once.
REASONER_GRACE_S = 5.0


def vehicle_of(key: str) -> str:
    return str(key).split("/")[2]


@dataclass
class Frame:
    """The newest camera frame of a vehicle as received, decoded to JPEG only on demand."""

    payload: bytes
    """The foxglove CompressedImage protobuf, undecoded until someone asks (most frames nobody watches)."""
    receive_ns: int
    seq: int

    def jpeg(self) -> tuple[int, bytes]:
        msg = decode_proto(CompressedImage, self.payload)
        return msg.timestamp.seconds * 1_000_000_000 + msg.timestamp.nanos, bytes(msg.data)


ABORT_SERVICES = ("executor", "autopilot_bridge")  # the services that act on safety/abort and acknowledge it


@dataclass
class VehicleView:
    """What the gateway knows of one vehicle: service liveliness, state, latest frame, detections, approvals."""

    vehicle_id: str
    services: dict[str, bool] = field(default_factory=dict)
    state: VehicleState | None = None
    state_ns: int = 0
    frame: Frame | None = None
    detections: Detections | None = None
    approvals: dict[str, ApprovalStatus] = field(default_factory=dict)
    """Pending operator approvals by id (decided or expired ones are dropped)."""
    acks: list[AbortAck] = field(default_factory=list)
    segmenter: str | None = None
    """Perception's segmenter, from its health (color, sam3, or sim: the simulator's ground-truth oracle)."""
    realism: str | None = None
    """The simulator's realism setting, from its health (absent on a real vehicle)."""
    reasoner_beat: tuple[int, float] | None = None
    """(pid, monotonic receive time) of the reasoner's latest heartbeat: which process it is."""

    @property
    def reasoner_alive(self) -> bool:
        return self.services.get("reasoner", False)


class Broadcast:
    """Wakes every waiter on each `notify`, with no lock: a waiter waits on the current Event, which `notify`
    sets and replaces. Event.wait holds nothing, so a waiter cancelled at any point (a client that leaves
    mid-stream) leaves nothing behind; the abort path waits here too and can never queue behind streams (an
    asyncio.Condition's lock is shared by every waiter, each of which re-acquires it on waking)."""

    def __init__(self) -> None:
        self._event = asyncio.Event()

    def notify(self) -> None:
        event, self._event = self._event, asyncio.Event()
        event.set()

    async def wait(self, timeout: float) -> bool:
        """True when notified within `timeout` seconds. Check the condition, then call this with no await in
        between: a notify cannot slip between the two on one event loop."""
        try:
            await asyncio.wait_for(self._event.wait(), max(0.0, timeout))
            return True
        except TimeoutError:
            return False


class Fleet:
    """Consumes the bus for every vehicle, writes task events to the store and wakes the streams."""

    def __init__(self, bus: Bus, store: Store) -> None:
        self.bus = bus
        self.store = store
        self.vehicles: dict[str, VehicleView] = {}
        self.version = 0  # bumped on every stored event; streams wait for a change
        self.frame_seq = 0
        self.changed = Broadcast()
        self.closing = asyncio.Event()
        self._tasks: list[asyncio.Task] = []
        self._subs: list[Subscription] = []
        self._finishing: set[asyncio.Task] = set()
        self.ending: dict[str, TaskStatus] = {}
        """Terminal statuses received and held for the task's last steps (FINISH_GRACE_S at most), by task id:
        the task has ended though its stored row does not say so yet."""
        self.abort_ns: dict[str, int] = {}
        """When the latest abort was sent to each vehicle (the fleet-wide one under FLEET_ABORT's id): a task
        older than its vehicle's abort is `aborting` until its end is stored. In memory only: set without
        touching the store, so the abort path waits for nothing the streams use."""
        self._gone: set[asyncio.Task] = set()
        self._ordered: asyncio.Queue[tuple[Callable[[str, Any], Awaitable[None]], str, Any]] = asyncio.Queue()

    def view(self, vehicle_id: str) -> VehicleView:
        v = self.vehicles.get(vehicle_id)
        if v is None:
            v = self.vehicles[vehicle_id] = VehicleView(vehicle_id)
        return v

    def reasoner_vehicles(self) -> list[str]:
        return sorted(v.vehicle_id for v in self.vehicles.values() if v.reasoner_alive)

    # ---- lifecycle

    async def start(self) -> None:
        # Snapshot liveliness first so requests right after start see the fleet, then reconcile tasks
        # that were left running while the gateway was down and whose reasoner is gone.
        for key in await self.bus.alive(f"{ROOT}/*/{ALIVE}/*", timeout=2.0):
            with contextlib.suppress(ValueError):
                vid, svc = parse_alive_key(key)
                self.view(vid).services[svc] = True
        for task in await self.store.running_tasks():
            if not self.view(task["vehicle_id"]).reasoner_alive:
                await self.end_orphan(task, "the reasoner was not running when the gateway started")

        def sub(topic: Topic[Any], handler: Callable[[str, Any], Awaitable[None]], maxsize: int = 1000,
                ordered: bool = False, **params: str) -> None:
            s = self.bus.subscribe(topic.fleet(**params), maxsize=maxsize)
            self._subs.append(s)
            run = self._forward(s, handler) if ordered else self._consume(s, handler)
            self._tasks.append(asyncio.create_task(run, name=f"gateway.{topic.name}"))

        # Task events of all three topics go through one queue and one writer, so the database keeps the
        # order they arrived in: the final step is stored before the terminal status that ends the stream.
        sub(REASONER_TASK_STATUS, self._on_status, ordered=True)
        sub(REASONER_STEP, self._on_step, ordered=True)
        sub(EXECUTOR_SKILL_STATUS, self._on_skill, ordered=True)
        self._tasks.append(asyncio.create_task(self._write_ordered(), name="gateway.writer"))
        sub(AUTOPILOT_STATE, self._on_state, maxsize=10)
        sub(CAMERA_COLOR, self._on_frame, maxsize=2)
        sub(SAFETY_ABORT_ACK, self._on_ack, maxsize=100)
        sub(PERCEPTION_DETECTIONS, self._on_detections, maxsize=4)
        sub(REASONER_APPROVAL, self._on_approval, maxsize=100)
        sub(HEALTH_TOPIC, self._on_health, maxsize=10, service="perception")
        sub(HEALTH_TOPIC, self._on_health, maxsize=10, service="sim")
        sub(HEARTBEAT_TOPIC, self._on_reasoner_beat, maxsize=10, service="reasoner")
        queue = self.bus.watch_liveliness(f"{ROOT}/*/{ALIVE}/*", history=True)
        self._tasks.append(asyncio.create_task(self._liveliness(queue), name="gateway.liveliness"))

    async def stop(self) -> None:
        self.closing.set()
        await self._notify()
        if self._finishing:  # terminal statuses still waiting for their last steps: store them now
            await asyncio.wait(set(self._finishing), timeout=5.0)
        for t in [*self._tasks, *self._gone]:
            t.cancel()
        for t in [*self._tasks, *self._gone]:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        for s in self._subs:
            s.close()

    async def _consume(self, sub: Subscription, handler: Callable[[str, Any], Awaitable[None]]) -> None:
        while True:
            rec = await sub.recv_sample()
            try:
                await handler(rec.key, rec.value)
            except asyncio.CancelledError:
                raise
            except Exception:
                # One bad sample must not stop the history of every other task.
                log.exception("could not handle a sample on %s", rec.key)

    async def _forward(self, sub: Subscription, handler: Callable[[str, Any], Awaitable[None]]) -> None:
        # Nothing awaits between receiving and queueing, so the shared queue keeps the loop's arrival order.
        while True:
            rec = await sub.recv_sample()
            self._ordered.put_nowait((handler, rec.key, rec.value))

    async def _write_ordered(self) -> None:
        while True:
            handler, key, value = await self._ordered.get()
            try:
                await handler(key, value)
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("could not store a sample from %s", key)

    async def _notify(self) -> None:
        self.version += 1
        self.changed.notify()

    async def wait_change(self, since: int, timeout: float) -> None:
        """Return when `version` differs from `since`, the gateway closes, or `timeout` passes."""
        deadline = time.monotonic() + timeout
        while self.version == since and not self.closing.is_set():
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not await self.changed.wait(remaining):
                return

    # ---- handlers

    async def _on_status(self, key: str, st: TaskStatus) -> None:
        if st.state.terminal and st.steps > 0:
            # Zenoh does not order samples across keys (large ones travel by shared memory), so the last
            # step can arrive after the terminal status. The status ends the task's streams: hold it until
            # the steps it counts are stored, or a short grace has passed.
            self.ending[st.task_id] = st
            t = asyncio.create_task(self._finish(vehicle_of(key), st), name=f"gateway.finish.{st.task_id}")
            self._finishing.add(t)
            t.add_done_callback(self._finishing.discard)
            return
        await self.store.record_status(vehicle_of(key), st.model_dump(mode="json"))
        await self._notify()

    async def _finish(self, vehicle_id: str, st: TaskStatus) -> None:
        deadline = time.monotonic() + FINISH_GRACE_S
        while time.monotonic() < deadline and not self.closing.is_set():
            seen = self.version
            if await self._all_stored(st):
                break
            await self.wait_change(seen, max(0.01, deadline - time.monotonic()))
        try:
            await self.store.record_status(vehicle_id, st.model_dump(mode="json"))
        finally:
            self.ending.pop(st.task_id, None)
        await self._notify()

    def phase(self, row: dict[str, Any]) -> str:
        """A stored task's state as the API shows it: `aborting` from an abort sent to its vehicle (or the
        fleet) after it was created until its end is stored, else the stored state."""
        state = str(row["state"])
        if TaskState(state).terminal:
            return state
        sent = max(self.abort_ns.get(row["vehicle_id"], 0), self.abort_ns.get(FLEET_ID, 0))
        return "aborting" if sent >= row["created_ns"] else state

    def ended(self, task_id: str) -> TaskStatus | None:
        """The terminal status of a task that has ended but whose end is not stored yet, if any."""
        return self.ending.get(task_id)

    async def _all_stored(self, st: TaskStatus) -> bool:
        """Whether the steps a terminal status counts are stored, and for every stored step whose skill ran to
        an end, that skill's terminal status: the executor publishes it on its own key, so it too can arrive
        after the reasoner's terminal status."""
        if (await self.store.step_counts([st.task_id])).get(st.task_id, 0) < st.steps:
            return False
        events = await self.store.events(st.task_id, kinds=("step", "skill_status"), limit=100_000)
        ran = {e.data.get("step") for e in events if e.kind == "step"
               and e.data.get("skill_state") in _SKILL_RAN}
        ended = {e.data.get("step") for e in events if e.kind == "skill_status"
                 and e.data.get("state") in _SKILL_RAN}
        return ran <= ended

    async def _on_step(self, key: str, step: ReasoningStep) -> None:
        await self.store.add_event(step.task_id, "step", step.stamp_ns, step.model_dump(mode="json"))
        await self._notify()

    async def _on_skill(self, key: str, st: SkillStatus) -> None:
        if not st.task_id:  # operator commands outside any task have no timeline to join
            return
        await self.store.add_event(st.task_id, "skill_status", st.stamp_ns, st.model_dump(mode="json"))
        await self._notify()

    async def _on_state(self, key: str, st: VehicleState) -> None:
        v = self.view(vehicle_of(key))
        v.state, v.state_ns = st, time.time_ns()

    async def _on_frame(self, key: str, payload: bytes) -> None:
        self.frame_seq += 1
        self.view(vehicle_of(key)).frame = Frame(payload, time.time_ns(), self.frame_seq)
        self.changed.notify()

    async def _on_approval(self, key: str, st: ApprovalStatus) -> None:
        v = self.view(vehicle_of(key))
        if st.state is ApprovalState.PENDING:
            v.approvals[st.approval_id] = st
        else:
            v.approvals.pop(st.approval_id, None)
        self.changed.notify()

    def pending_approvals(self) -> list[ApprovalStatus]:
        """Every pending approval of the fleet, oldest first (expired ones the reasoner did not report yet are
        left out)."""
        now = time.time_ns()
        out = [a for v in self.vehicles.values() for a in v.approvals.values()
               if not a.expires_ns or a.expires_ns > now]
        return sorted(out, key=lambda a: a.stamp_ns)

    async def _on_detections(self, key: str, dets: Detections) -> None:
        self.view(vehicle_of(key)).detections = dets

    async def _on_health(self, key: str, h: Health) -> None:
        v = self.view(vehicle_of(key))
        if h.service == "perception" and "segmenter" in h.details:
            v.segmenter = str(h.details["segmenter"])
        elif h.service == "sim" and "realism" in h.details:
            v.realism = str(h.details["realism"])

    async def _on_reasoner_beat(self, key: str, beat: Heartbeat) -> None:
        self.view(vehicle_of(key)).reasoner_beat = (beat.pid, time.monotonic())

    async def _on_ack(self, key: str, ack: AbortAck) -> None:
        v = self.view(vehicle_of(key))
        v.acks = [*v.acks[-19:], ack]
        self.changed.notify()

    async def _liveliness(self, queue: asyncio.Queue[tuple[str, bool]]) -> None:
        while True:
            key, alive = await queue.get()
            try:
                vid, svc = parse_alive_key(key)
            except ValueError:
                continue
            view = self.view(vid)
            was = view.services.get(svc, False)
            view.services[svc] = alive
            if svc == "reasoner" and was and not alive:
                t = asyncio.create_task(self._reasoner_gone(view), name=f"gateway.gone.{vid}")
                self._gone.add(t)
                t.add_done_callback(self._gone.discard)

    async def _reasoner_gone(self, view: VehicleView) -> None:
        """The reasoner's token vanished: end its running tasks, unless the same process is back within
        REASONER_GRACE_S (only the link to it broke, and it is still running them)."""
        since = time.monotonic()
        pid = view.reasoner_beat[0] if view.reasoner_beat else None
        while time.monotonic() - since < REASONER_GRACE_S and not self.closing.is_set():
            beat = view.reasoner_beat
            if view.reasoner_alive and beat is not None and beat[1] > since:
                if beat[0] == pid:
                    log.info("the reasoner of %s is back (same process, pid %d): its tasks go on", view.vehicle_id,
                             pid)
                    return
                break  # a new reasoner process: the old one's tasks have nobody
            await asyncio.sleep(0.1)
        for task in await self.store.running_tasks(view.vehicle_id):
            await self.end_orphan(task, f"the reasoner of {view.vehicle_id} stopped while the task was running")

    async def end_orphan(self, task: dict[str, Any], why: str) -> None:
        """No reasoner will ever finish this task: end it so it stops blocking its vehicle and its streams end."""
        prev = task.get("status") or {}
        st = TaskStatus(vehicle_id=task["vehicle_id"], task_id=task["task_id"], command=task["command"],
                        state=TaskState.FAILED, message=why, steps=prev.get("steps", 0),
                        model_calls=prev.get("model_calls", 0), invalid_answers=prev.get("invalid_answers", 0),
                        started_ns=prev.get("started_ns", 0), ended_ns=now_ns())
        log.warning("task %s on %s: %s", task["task_id"], task["vehicle_id"], why)
        # On the task's own status key too, so the end reaches the flight's log (the recorder) and every
        # follower, not only this store: the reasoner that would have published it is gone.
        self.bus.publish(Keys(task["vehicle_id"]).task_status, st)
        await self.store.record_status(task["vehicle_id"], st.model_dump(mode="json"))
        await self._notify()

    # ---- commands

    async def abort(self, vehicles: list[str], reason: str, task_id: str | None,
                    wait_s: float, *, fleet_wide: bool = False) -> dict[str, dict[str, str]]:
        """Publish an Abort to each vehicle (or one on the fleet-wide key, which every vehicle obeys, even one
        the gateway has not seen yet); return {vehicle: {service: what it did}} for the services (executor,
        autopilot_bridge) that acknowledged within `wait_s`. Waits for every such service that is alive on
        the vehicle, so a dead executor does not hold the answer up and is visibly missing."""
        from shared.messages import Abort

        stamps: dict[str, int] = {}
        sent = time.time_ns()  # the clock of a task row's created_ns, so `phase` compares like with like
        for vid in [FLEET_ID] if fleet_wide else vehicles:
            self.abort_ns[vid] = sent
        if fleet_wide:
            msg = Abort(reason=reason, source="gateway")
            self.bus.publish(FLEET_ABORT, msg)
            stamps = dict.fromkeys(vehicles, msg.stamp_ns)
        for vid in [] if fleet_wide else vehicles:
            msg = Abort(reason=reason, source="gateway", task_id=task_id)
            stamps[vid] = msg.stamp_ns
            self.bus.publish(Keys(vid).abort, msg)

        def acked() -> dict[str, dict[str, str]]:
            out: dict[str, dict[str, str]] = {}
            for vid in vehicles:
                for a in self.view(vid).acks:
                    if a.abort_stamp_ns == stamps[vid]:
                        out.setdefault(vid, {})[a.service] = a.message
            return out

        def complete() -> bool:
            got = acked()
            for vid in vehicles:
                alive = {svc for svc, up in self.view(vid).services.items() if up and svc in ABORT_SERVICES}
                if not got.get(vid) or not alive <= set(got[vid]):
                    return False
            return True

        deadline = time.monotonic() + wait_s
        while not complete() and not self.closing.is_set():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            await self.changed.wait(remaining)
        return acked()
