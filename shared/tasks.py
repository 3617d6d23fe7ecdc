"""Following a task from outside the reasoner (the demo, the CLI, evaluation): submit it through the task
action (`shared.action`), collect its reasoning steps, wait for its terminal status; and the one episode
judge that asks the simulator's ground truth whether the task's end state holds."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from shared.action import GoalHandle, task_client
from shared.bus import Bus, Subscription, query_ready
from shared.errors import ServerLost
from shared.keys import Keys
from shared.messages import Health, JudgeRequest, JudgeResult, ReasoningStep, TaskAccept, TaskRequest, TaskStatus


async def submit_task(bus: Bus, keys: Keys, request: TaskRequest, timeout: float = 30.0) -> TaskAccept:
    """Send the task goal, waiting up to `timeout` for the reasoner to serve it (its liveliness token appears
    before its queryables are declared). Returns the accept/reject answer without following the task."""
    async with task_client(bus, keys.vehicle_id) as client:
        handle = await client.send_goal(request, ready_timeout=timeout)
        handle.close()
        return handle.accept


class StepCollector:
    """The reasoning steps of one task, in the order they arrive (subscribed before the goal is sent)."""

    def __init__(self, bus: Bus, keys: Keys, on_step: Callable[[ReasoningStep], None] = lambda s: None) -> None:
        self.sub: Subscription[ReasoningStep] = bus.subscribe(keys.reasoning_step, maxsize=10_000,
                                                              overflow="drop_newest")
        self.on_step = on_step
        self.task_id = ""
        self.steps: list[ReasoningStep] = []
        self.foreign = 0

    def drain(self) -> None:
        """Move what is queued into `steps` (steps of other tasks are counted in `foreign`)."""
        while (s := self.sub.recv_nowait()) is not None:
            if s.task_id == self.task_id:
                self.steps.append(s)
                self.on_step(s)
            else:
                self.foreign += 1

    async def until(self, count: int, timeout: float) -> None:
        """Wait (bounded) until `count` steps of the task are in: steps are published before the terminal
        status, but a loaded machine may deliver them later."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        self.drain()
        while len(self.steps) < count and loop.time() < deadline:
            await asyncio.sleep(0.05)
            self.drain()
        self.steps.sort(key=lambda s: s.step)

    def close(self) -> None:
        self.sub.close()


REFUSED_BEFORE_TAKEOFF = "command refused before takeoff"
"""How a task's failure message starts when the policy refused the command before anything flew: the
policy's answer (a failure to count), not a stack problem to retry."""

@dataclass
class Followed:
    """What following one task gave: the accept answer, the terminal status (None when none came in time),
    the task's steps in order, and how many steps of other tasks arrived meanwhile."""

    accept: TaskAccept
    final: TaskStatus | None
    steps: list[ReasoningStep]
    foreign: int = 0
    error: str = ""
    """Why no terminal status came, when known (the reasoner stopped mid-task)."""


async def follow_task(bus: Bus, keys: Keys, request: TaskRequest, *, on_step: Callable[[ReasoningStep], None] =
                      lambda s: None, on_status: Callable[[TaskStatus], None] = lambda s: None,
                      timeout: float = 3600.0, ready_timeout: float = 30.0, retry_rejected_s: float = 0.0,
                      ) -> Followed:
    """Submit `request` and stream its steps until the terminal status. A rejection is retried for
    `retry_rejected_s` seconds (the previous task of the vehicle may still be ending)."""
    steps = StepCollector(bus, keys, on_step)
    steps.task_id = request.task_id
    loop = asyncio.get_running_loop()
    try:
        async with task_client(bus, keys.vehicle_id) as client:
            await asyncio.sleep(0.2)  # let the subscriptions reach the router before the first step
            give_up = loop.time() + retry_rejected_s
            while True:
                handle: GoalHandle[TaskAccept, TaskStatus] = await client.send_goal(
                    request, ready_timeout=ready_timeout)
                if handle.accepted or loop.time() >= give_up:
                    break
                await asyncio.sleep(1.0)
            if not handle.accepted:
                return Followed(handle.accept, None, steps.steps)
            try:
                final = await _follow(handle, steps, on_status, timeout)
            except ServerLost as exc:  # the reasoner died: no terminal status will come
                return Followed(handle.accept, None, steps.steps, steps.foreign, error=str(exc))
            if final is not None:
                await steps.until(final.steps, 5.0)
            return Followed(handle.accept, final, steps.steps, steps.foreign)
    finally:
        steps.close()


async def _follow(handle: GoalHandle[TaskAccept, TaskStatus], steps: StepCollector,
                  on_status: Callable[[TaskStatus], None], timeout: float) -> TaskStatus | None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    seen = 0
    while True:
        st = await handle.next_feedback(timeout=min(1.0, max(0.0, deadline - loop.time())))
        steps.drain()
        for s in handle.feedback[seen:]:
            on_status(s)
        seen = len(handle.feedback)
        if st is not None and st.state.terminal:
            return st
        if loop.time() >= deadline:
            return None


@dataclass
class Verdict:
    """The judge's answer for one episode."""

    success: bool
    message: str
    result: JudgeResult


async def ask_judge(bus: Bus, keys: Keys, req: JudgeRequest, *, timeout: float = 10.0,
                    settle_timeout: float = 15.0) -> JudgeResult:
    """Ask the simulator's judge; while its answer is only waiting on a duration (`pending_s`: an object at
    rest but not yet for the task's rest time, a lift not yet held for its hold time), ask again as that time
    passes, up to `settle_timeout` wall seconds. The judge's simulated clock runs at the simulator's speed
    factor, so the wait between asks is at most `pending_s` wall seconds (less when the simulator is faster)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + settle_timeout
    while True:
        j = await query_ready(bus, keys.sim_judge, req, timeout=timeout)
        if j.ok or j.pending_s is None or loop.time() >= deadline:
            return j
        await asyncio.sleep(min(max(j.pending_s, 0.05), 0.5, max(0.0, deadline - loop.time())))


async def judge_episode(bus: Bus, keys: Keys, accepted: Sequence[str], destination: str | None, *,
                        timeout: float = 10.0, settle_timeout: float = 15.0) -> Verdict:
    """The one episode judge, as the paper scores a trial: one of the `accepted` objects placed on the
    `destination`, or, for a task without a destination, one of them picked (lifted clear and held) at the end.
    The criteria are the task's, laid out with its scenario (`Scenario.criteria`), not chosen here; a verdict
    that only waits on a rest or hold time is asked again as that time passes (`ask_judge`)."""
    if destination:
        first: JudgeResult | None = None
        for obj in accepted:
            req = JudgeRequest(op="on_surface", object=obj, surface=destination)
            j = await ask_judge(bus, keys, req, timeout=timeout, settle_timeout=settle_timeout)
            if j.ok:
                return Verdict(True, j.message, j)
            first = first or j
        assert first is not None, "judge_episode needs at least one accepted object"
        return Verdict(False, first.message, first)
    j = await ask_judge(bus, keys, JudgeRequest(op="held"), timeout=timeout, settle_timeout=settle_timeout)
    want = " or ".join(accepted)
    if j.held in accepted:
        return Verdict(j.ok, j.message if j.ok else f"{j.message}: not picked", j)
    return Verdict(False, f"holding {j.held}, expected {want}" if j.held else f"{j.message}, expected {want}", j)


async def recorded_end(recorder_health: Subscription[Health], task_id: str, last_step: int = 0, *,
                       timeout: float = 10.0, first_timeout: float = 3.0) -> tuple[str | None, bool]:
    """Wait until the recorder says its log holds the end of `task_id` and its steps up to `last_step` (its
    `health/recorder` details `tasks`; Zenoh orders nothing across keys, so a step may come after the end), so a
    stack stopped next loses nothing. Returns (the log's path, whether all of it is in); (None, False) when no
    recorder reports within `first_timeout`."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    path: str | None = None
    h = recorder_health.latest_nowait()
    if h is None:
        try:
            h = await recorder_health.recv(timeout=first_timeout)
        except TimeoutError:
            return None, False
    while True:
        path = h.details.get("path") or path
        entry = (h.details.get("tasks") or {}).get(task_id) or {}
        if entry.get("ended") and int(entry.get("steps") or 0) >= last_step:
            return path, True
        left = deadline - loop.time()
        if left <= 0:
            return path, False
        try:
            h = await recorder_health.recv(timeout=left)
        except TimeoutError:
            return path, False
