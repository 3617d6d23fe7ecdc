"""The one action protocol of aermani, used for tasks (gateway, CLI, evaluation -> reasoner) and skills
(reasoner, CLI, evaluation -> executor), after ROS 2 actions.

A client sends a goal on the action's goal queryable and gets it accepted (with a goal id) or rejected
(with a reason); the server then publishes feedback and, last, one terminal result on the action's status
topic; a cancel request goes to the cancel queryable. `ActionClient.send_goal` returns a `GoalHandle`
whose `result()` waits for the terminal status, `feedback` holds the statuses seen so far, and `cancel()`
asks the server to stop. The client subscribes the status topic before it sends the goal and routes
statuses to handles by goal id, keeping nothing once a goal has ended. A subscription reaches the server
through the router in the background, so a goal that ends at once (a task refused before takeoff) can publish
all its statuses before the server hears of the subscriber: until the subscription has delivered a status of
the goal, the client asks the result queryable for the goal's latest status (after ROS 2's get_result),
first after `RECOVER_FIRST_S`, then at intervals doubling up to `RECOVER_MAX_S`; a status older than the
last one delivered (a reply and a sample cross in flight) is dropped.

`ActionServer` is the other half, after rclpy's: its goal callback accepts or rejects a goal (it builds the
accept message, so the server decides the goal id), the execute callback runs an accepted goal with a
`ServerGoalHandle` that publishes its feedback and, last, its terminal result; the cancel callback decides a
cancel of a running goal (by default the execute task is cancelled), and a cancel of a goal that is not
running is refused with a reason without reaching the callback. Every server and every test fake uses it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from shared.bus import Bus, Subscription, query_ready
from shared.errors import AermaniError, NotFound, ServerLost
from shared.keys import (
    ALIVE_TOKEN,
    EXECUTOR_CANCEL_SKILL,
    EXECUTOR_RUN_SKILL,
    EXECUTOR_SKILL_RESULT,
    EXECUTOR_SKILL_STATUS,
    REASONER_CANCEL_TASK,
    REASONER_START_TASK,
    REASONER_TASK_RESULT,
    REASONER_TASK_STATUS,
    Query,
    Topic,
)
from shared.messages import (
    CancelGoal,
    CancelReply,
    GoalRef,
    SkillAccept,
    SkillRequest,
    SkillStatus,
    TaskAccept,
    TaskRequest,
    TaskStatus,
)

log = logging.getLogger("aermani.action")

G = TypeVar("G")
A = TypeVar("A")
S = TypeVar("S")

RECOVER_FIRST_S = 0.5
"""After an accepted goal, how long the client waits for the first status through its subscription before it asks
the result queryable."""
RECOVER_MAX_S = 10.0
"""Then it asks at doubling intervals up to this, until the subscription delivers a status of the goal or the
goal ends (a recovered status that is not the end proves nothing about the subscription)."""
ENDED_KEPT = 256
"""How many ended goals a server keeps the result of, for the result queryable."""


@dataclass(frozen=True)
class ActionSpec(Generic[G, A, S]):
    """One action: its goal, cancel, status and result keys, and where each message keeps the goal id."""

    name: str
    goal: Query[G, A]
    cancel: Query[CancelGoal, CancelReply]
    status: Topic[S]
    result: Query[GoalRef, S]
    accept_id: Callable[[A], str]
    status_id: Callable[[S], str]
    request_id: Callable[[G], str]
    terminal: Callable[[S], bool]


SKILL_ACTION: ActionSpec[SkillRequest, SkillAccept, SkillStatus] = ActionSpec(
    "skill", EXECUTOR_RUN_SKILL, EXECUTOR_CANCEL_SKILL, EXECUTOR_SKILL_STATUS, EXECUTOR_SKILL_RESULT,
    accept_id=lambda a: a.goal_id, status_id=lambda s: s.goal_id, request_id=lambda r: "",
    terminal=lambda s: s.state.terminal)
TASK_ACTION: ActionSpec[TaskRequest, TaskAccept, TaskStatus] = ActionSpec(
    "task", REASONER_START_TASK, REASONER_CANCEL_TASK, REASONER_TASK_STATUS, REASONER_TASK_RESULT,
    accept_id=lambda a: a.task_id, status_id=lambda s: s.task_id, request_id=lambda r: r.task_id,
    terminal=lambda s: s.state.terminal)


@dataclass
class GoalHandle(Generic[A, S]):
    """A goal sent by an `ActionClient`: its acceptance, the statuses seen so far, its terminal result."""

    client: ActionClient[Any, A, S]
    accept: A
    goal_id: str
    accepted: bool
    reason: str
    feedback: list[S] = field(default_factory=list)
    _done: asyncio.Future[S] | None = None
    _updated: asyncio.Event = field(default_factory=asyncio.Event)
    _heard: bool = False
    """A status of this goal came through the subscription: it reaches the server, nothing more to recover."""
    recovered: int = 0
    """Statuses that came from the result queryable because the subscription missed them."""

    async def result(self, timeout: float | None = None) -> S | None:
        """The terminal status, or None when `timeout` passes first (or the goal was rejected). Raises
        ServerLost as soon as the server's liveliness token disappears while the goal runs (a dead executor
        is noticed within Zenoh's lease, not at the goal's timeout)."""
        if not self.accepted or self._done is None:
            return None
        try:
            return await asyncio.wait_for(asyncio.shield(self._done), timeout)
        except TimeoutError:
            return None
        finally:
            if self._done.done():
                self.client._forget(self.goal_id)

    async def next_feedback(self, timeout: float | None = None) -> S | None:
        """Wait for the next status of this goal (feedback or result); None on timeout."""
        seen = len(self.feedback)
        self._updated.clear()
        if len(self.feedback) > seen:
            return self.feedback[-1]
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._updated.wait(), timeout)
        if len(self.feedback) == seen and self._done is not None and self._done.done():
            lost = self._done.exception()
            if lost is not None:
                raise lost  # ServerLost: no more feedback will come
        return self.feedback[-1] if len(self.feedback) > seen else None

    async def cancel(self, reason: str = "cancelled", source: str = "client", timeout: float = 5.0) -> CancelReply:
        """Ask the server to cancel this goal; the terminal status still arrives through `result()`."""
        return await self.client.cancel(self.goal_id, reason=reason, source=source, timeout=timeout)

    def close(self) -> None:
        """Stop following this goal (its statuses are no longer kept)."""
        self.client._forget(self.goal_id)


class ActionClient(Generic[G, A, S]):
    """Client side of one action on one vehicle. Open it (`async with` or `start()`) before sending goals."""

    def __init__(self, bus: Bus, spec: ActionSpec[G, A, S], vehicle_id: str, *, maxsize: int = 1000) -> None:
        self.bus = bus
        self.spec = spec
        self.vehicle_id = vehicle_id
        self.maxsize = maxsize
        self._handles: dict[str, GoalHandle[A, S]] = {}
        self._early: dict[str, list[S]] = {}  # statuses that overtook the accept reply
        self._sub: Subscription[S] | None = None
        self._pump: asyncio.Task[None] | None = None
        self._watch: asyncio.Task[None] | None = None
        self._alive: asyncio.Queue[tuple[str, bool]] | None = None
        self._recovering: set[asyncio.Task[None]] = set()

    async def __aenter__(self) -> ActionClient[G, A, S]:
        self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def start(self) -> None:
        if self._sub is None:
            self._sub = self.bus.subscribe(self.spec.status.bind(self.vehicle_id), maxsize=self.maxsize)
            self._pump = asyncio.create_task(self._route(), name=f"action.{self.spec.name}.{self.vehicle_id}")
            token = ALIVE_TOKEN.bind(self.vehicle_id, service=self.spec.goal.server)
            self._alive = self.bus.watch_liveliness(str(token), history=False, maxsize=16)
            self._watch = asyncio.create_task(self._server_gone(self._alive, str(token)),
                                              name=f"action.{self.spec.name}.{self.vehicle_id}.alive")

    async def close(self) -> None:
        for task in (self._pump, self._watch, *self._recovering):
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        if self._sub is not None:
            self._sub.close()
        if self._alive is not None:  # clients live per request in places (gateway, evaluation): no leak
            self.bus.unwatch_liveliness(self._alive)
        self._sub = self._pump = self._watch = self._alive = None

    async def _server_gone(self, events: asyncio.Queue[tuple[str, bool]], token: str) -> None:
        """Fail every running goal with ServerLost when the server's liveliness token disappears."""
        while True:
            _key, alive = await events.get()
            if alive:
                continue
            for handle in list(self._handles.values()):
                if handle._done is not None and not handle._done.done():
                    handle._done.set_exception(ServerLost(
                        f"the {self.spec.goal.server} of {self.vehicle_id} stopped while {self.spec.name} goal "
                        f"{handle.goal_id} was running (its liveliness token {token} disappeared)"))
                    handle._done.exception()  # retrieved here too: no "never retrieved" warning if unawaited
                    handle._updated.set()

    async def _route(self) -> None:
        assert self._sub is not None
        while True:
            st = await self._sub.recv()
            gid = self.spec.status_id(st)
            handle = self._handles.get(gid)
            if handle is None:
                if gid in self._early or len(self._early) < 64:
                    self._early.setdefault(gid, []).append(st)
                continue
            handle._heard = True
            self._deliver(handle, st)

    def _deliver(self, handle: GoalHandle[A, S], st: S) -> None:
        if handle.feedback:
            last = handle.feedback[-1]
            if st == last or getattr(st, "stamp_ns", 0) < getattr(last, "stamp_ns", 0):
                return  # the same status both ways, or an older one overtaken by a reply of the result queryable
        handle.feedback.append(st)
        handle._updated.set()
        if self.spec.terminal(st) and handle._done is not None and not handle._done.done():
            handle._done.set_result(st)

    def _forget(self, goal_id: str) -> None:
        self._handles.pop(goal_id, None)
        self._early.pop(goal_id, None)

    async def send_goal(self, goal: G, *, timeout: float = 10.0, ready_timeout: float = 0.0) -> GoalHandle[A, S]:
        """Send `goal`; returns its handle, accepted or rejected. With `ready_timeout` > 0, waits that long
        for a server to appear (start-up, supervised restart) before giving up with NoResponder."""
        self.start()
        target = self.spec.goal.bind(self.vehicle_id)
        if ready_timeout > 0:
            accept = await query_ready(self.bus, target, goal, timeout=timeout, ready_timeout=ready_timeout)
        else:
            accept = await self.bus.query(target, goal, timeout=timeout)
        accepted = bool(getattr(accept, "accepted", False))
        gid = self.spec.accept_id(accept) or self.spec.request_id(goal)
        handle: GoalHandle[A, S] = GoalHandle(self, accept, gid, accepted, str(getattr(accept, "reason", "")))
        if accepted:
            handle._done = asyncio.get_running_loop().create_future()
            self._handles[gid] = handle
            for st in self._early.pop(gid, []):
                handle._heard = True
                self._deliver(handle, st)
            if not handle._heard:
                task = asyncio.create_task(self._recover(handle), name=f"action.{self.spec.name}.{gid}.recover")
                self._recovering.add(task)
                task.add_done_callback(self._recovering.discard)
        self._early.clear()  # anything else that arrived early belongs to goals nobody here follows
        return handle

    async def _recover(self, handle: GoalHandle[A, S]) -> None:
        """Until the subscription delivers a status of `handle`'s goal, ask the server for its latest one."""
        target = self.spec.result.bind(self.vehicle_id)
        delay = RECOVER_FIRST_S

        def following() -> bool:
            return (not handle._heard and handle._done is not None and not handle._done.done()
                    and self._handles.get(handle.goal_id) is handle)

        while following():
            await asyncio.sleep(delay)
            delay = min(2 * delay, RECOVER_MAX_S)
            if not following():
                return
            try:
                st = await self.bus.query(target, GoalRef(goal_id=handle.goal_id), timeout=5.0)
            except AermaniError as exc:  # no status yet, an older server without it, a refusal, a bad reply
                log.debug("%s goal %s: no status from %s: %s", self.spec.name, handle.goal_id, target, exc)
                continue
            if following() and self.spec.status_id(st) == handle.goal_id:
                if not handle.recovered:
                    log.info("%s goal %s: its status came from %s (the subscription had not reached the server "
                             "yet)", self.spec.name, handle.goal_id, target.key)
                n = len(handle.feedback)
                self._deliver(handle, st)
                handle.recovered += len(handle.feedback) - n

    async def cancel(self, goal_id: str, *, reason: str = "cancelled", source: str = "client",
                     timeout: float = 5.0) -> CancelReply:
        return await self.bus.query(self.spec.cancel.bind(self.vehicle_id),
                                    CancelGoal(goal_id=goal_id, reason=reason, source=source), timeout=timeout)


class ServerGoalHandle(Generic[G, S]):
    """A goal an `ActionServer` accepted: its request, whether a cancel was asked, and how to report on it."""

    def __init__(self, server: ActionServer[G, Any, S], goal_id: str, request: G) -> None:
        self.server = server
        self.goal_id = goal_id
        self.request = request
        self.cancel_request: CancelGoal | None = None
        """The cancel a client sent (None until one arrives): an execute callback that polls reads it."""
        self.task: asyncio.Task[None] | None = None
        """The execute callback's task (None without an execute callback)."""
        self.active = True
        """Until its terminal status was published."""
        self.last: S | None = None
        """The latest status published (what the result queryable answers while the goal runs)."""

    @property
    def cancel_requested(self) -> bool:
        return self.cancel_request is not None

    def publish(self, status: S) -> None:
        """Publish a status of this goal: feedback, or its terminal result (which ends the goal here)."""
        self.last = status
        self.server.publish(status)
        if self.server.spec.terminal(status):
            self.active = False
            self.server._end(self.goal_id, status)


GoalCallback = Callable[[G], Awaitable[A]]
ExecuteCallback = Callable[[ServerGoalHandle[G, S]], Awaitable[None]]
CancelCallback = Callable[[ServerGoalHandle[G, S], CancelGoal], Awaitable[CancelReply]]


class ActionServer(Generic[G, A, S]):
    """Server side of one action on one vehicle: serves the goal, cancel and result queryables (`start()`)."""

    def __init__(self, bus: Bus, spec: ActionSpec[G, A, S], vehicle_id: str, *, goal_callback: GoalCallback[G, A],
                 execute_callback: ExecuteCallback[G, S] | None = None,
                 cancel_callback: CancelCallback[G, S] | None = None) -> None:
        self.bus = bus
        self.spec = spec
        self.vehicle_id = vehicle_id
        self.goal_callback = goal_callback
        self.execute_callback = execute_callback
        self.cancel_callback = cancel_callback
        self.goals: dict[str, ServerGoalHandle[G, S]] = {}
        """The running goals by id (a goal leaves when its terminal status is published)."""
        self.ended: OrderedDict[str, S] = OrderedDict()
        """The results of the last `ENDED_KEPT` goals, by id."""
        self._started = False

    def start(self) -> ActionServer[G, A, S]:
        """Serve the goal, cancel and result queryables (once)."""
        if not self._started:
            self.bus.serve(self.spec.goal.bind(self.vehicle_id), self._on_goal)
            self.bus.serve(self.spec.cancel.bind(self.vehicle_id), self._on_cancel)
            self.bus.serve(self.spec.result.bind(self.vehicle_id), self._on_result)
            self._started = True
        return self

    def publish(self, status: S) -> None:
        """Publish a status on the action's status topic (a rejection's status has no handle)."""
        self.bus.publish(self.spec.status.bind(self.vehicle_id), status)

    def _end(self, goal_id: str, result: S | None = None) -> None:
        self.goals.pop(goal_id, None)
        if result is not None:
            self.ended[goal_id] = result
            while len(self.ended) > ENDED_KEPT:
                self.ended.popitem(last=False)

    async def _on_result(self, req: GoalRef) -> S:
        handle = self.goals.get(req.goal_id)
        if handle is not None:  # running: never an earlier goal's result under the same id (a reused task id)
            if handle.last is not None:
                return handle.last
            raise NotFound(f"{self.spec.name} goal {req.goal_id} on vehicle {self.vehicle_id} has published no "
                           "status yet")
        if req.goal_id in self.ended:
            return self.ended[req.goal_id]
        raise NotFound(f"{self.spec.name} goal {req.goal_id} on vehicle {self.vehicle_id} is unknown (or ended "
                       "long ago)")

    async def _on_goal(self, request: G) -> A:
        accept = await self.goal_callback(request)
        if not bool(getattr(accept, "accepted", False)):
            return accept
        goal_id = self.spec.accept_id(accept) or self.spec.request_id(request)
        handle: ServerGoalHandle[G, S] = ServerGoalHandle(self, goal_id, request)
        self.goals[goal_id] = handle
        self.ended.pop(goal_id, None)  # a reused id (a task's) names this goal from now on
        if self.execute_callback is not None:
            # Runs once the accept reply is on its way; a status that overtakes it waits in the client.
            handle.task = asyncio.create_task(self._execute(handle), name=f"action.{self.spec.name}.{goal_id}")
        return accept

    async def _execute(self, handle: ServerGoalHandle[G, S]) -> None:
        assert self.execute_callback is not None
        try:
            await self.execute_callback(handle)
        except asyncio.CancelledError:
            if handle.active:
                log.warning("%s goal %s was cancelled before it reported a result", self.spec.name, handle.goal_id)
            raise
        except Exception:
            log.exception("%s goal %s: the execute callback failed", self.spec.name, handle.goal_id)
        finally:
            if handle.active:  # it never reported its end: nobody may wait for it forever
                log.error("%s goal %s ended without a terminal status", self.spec.name, handle.goal_id)
                self._end(handle.goal_id)

    async def _on_cancel(self, req: CancelGoal) -> CancelReply:
        handle = self.goals.get(req.goal_id)
        if handle is None or not handle.active:
            return CancelReply(accepted=False, reason=f"{self.spec.name} goal {req.goal_id} is not running on "
                                                      f"vehicle {self.vehicle_id} (unknown or already ended); "
                                                      "nothing was cancelled")
        handle.cancel_request = req
        if self.cancel_callback is not None:
            return await self.cancel_callback(handle, req)
        if handle.task is not None:
            handle.task.cancel()
        return CancelReply(accepted=True)


def skill_client(bus: Bus, vehicle_id: str) -> ActionClient[SkillRequest, SkillAccept, SkillStatus]:
    """The skill action (executor) of one vehicle."""
    return ActionClient(bus, SKILL_ACTION, vehicle_id)


def task_client(bus: Bus, vehicle_id: str) -> ActionClient[TaskRequest, TaskAccept, TaskStatus]:
    """The task action (reasoner) of one vehicle."""
    return ActionClient(bus, TASK_ACTION, vehicle_id)
