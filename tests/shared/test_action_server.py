"""The ActionServer against the ActionClient on real Zenoh over loopback: accept, reject, feedback, result,
cancel of a running goal, cancel of an unknown goal, and a goal whose execute callback crashes."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator

import pytest

from shared.action import SKILL_ACTION, ActionClient, ActionServer, GoalHandle, ServerGoalHandle, skill_client
from shared.bus import Bus
from shared.errors import RemoteError
from shared.keys import Keys
from shared.messages import CancelGoal, CancelReply, GoalRef, SkillAccept, SkillRequest, SkillState, SkillStatus

pytestmark = pytest.mark.integration
VID = "am1"


class Server:
    """A skill server whose goals run until released (`go`) or cancelled, every step visible to the test."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.go = asyncio.Event()
        self.cancels: list[CancelGoal] = []
        self.n = 0
        self.action = ActionServer(bus, SKILL_ACTION, VID, goal_callback=self.on_goal, execute_callback=self.execute,
                                   cancel_callback=self.on_cancel).start()
        bus.declare_token(Keys(VID).alive("executor"))

    async def on_goal(self, req: SkillRequest) -> SkillAccept:
        self.n += 1
        if req.skill == "refused":
            return SkillAccept(accepted=False, goal_id=f"g-{self.n}", reason="refused: no such skill here")
        return SkillAccept(accepted=True, goal_id=f"g-{self.n}")

    def status(self, h: ServerGoalHandle[SkillRequest, SkillStatus], state: SkillState, msg: str) -> SkillStatus:
        return SkillStatus(goal_id=h.goal_id, skill=h.request.skill, state=state, message=msg,
                           task_id=h.request.task_id, step=h.request.step)

    async def execute(self, h: ServerGoalHandle[SkillRequest, SkillStatus]) -> None:
        if h.request.skill == "crash":
            raise RuntimeError("broken skill")
        h.publish(self.status(h, SkillState.RUNNING, "started"))
        try:
            await self.go.wait()
        except asyncio.CancelledError:
            h.publish(self.status(h, SkillState.ABORTED, f"cancelled: {h.cancel_request.reason}"
                                  if h.cancel_request else "cancelled"))
            raise
        h.publish(self.status(h, SkillState.RUNNING, "halfway"))
        h.publish(self.status(h, SkillState.SUCCEEDED, "done"))

    async def on_cancel(self, h: ServerGoalHandle[SkillRequest, SkillStatus], req: CancelGoal) -> CancelReply:
        self.cancels.append(req)
        assert h.task is not None
        h.task.cancel()
        return CancelReply(accepted=True)


@contextlib.asynccontextmanager
async def _pair(router: str) -> AsyncIterator[tuple[Bus, Bus]]:
    """A server's bus and a client's, on one router, closed at the end."""
    async with await Bus.open(connect=[router]) as sbus, await Bus.open(connect=[router]) as cbus:
        yield sbus, cbus


async def _subscribed(sbus: Bus) -> None:
    """Until the client's status subscription has reached the server through the router: a status published
    before that is lost (Zenoh routes by declarations), which no test may race."""
    key = Keys(VID).skill_status
    for _ in range(3000):
        if sbus.has_subscribers(key):
            return
        await asyncio.sleep(0.01)
    raise AssertionError("the client's status subscription never reached the server")


async def _first(goal: GoalHandle[SkillAccept, SkillStatus]) -> SkillStatus | None:
    """The goal's first status, whether it overtook the accept reply (then it is already in `feedback`) or not."""
    if not goal.feedback:
        await goal.next_feedback(timeout=30)
    return goal.feedback[0] if goal.feedback else None


async def test_accept_feedback_result(router: str) -> None:
    async with _pair(router) as (sbus, cbus):
        server = Server(sbus)
        async with skill_client(cbus, VID) as client:
            await _subscribed(sbus)
            goal = await client.send_goal(SkillRequest(skill="forward", task_id="t-1", step=1), ready_timeout=30)
            assert goal.accepted and goal.goal_id == "g-1"
            first = await _first(goal)
            assert first is not None and first.message == "started"
            assert server.action.goals.keys() == {"g-1"}
            server.go.set()
            result = await goal.result(timeout=30)
            assert result is not None and result.state == SkillState.SUCCEEDED and result.message == "done"
            assert [s.message for s in goal.feedback] == ["started", "halfway", "done"]
            assert server.action.goals == {}  # a goal leaves the server with its terminal status


async def test_reject_starts_nothing(router: str) -> None:
    async with _pair(router) as (sbus, cbus):
        server = Server(sbus)
        async with skill_client(cbus, VID) as client:
            goal = await client.send_goal(SkillRequest(skill="refused"), ready_timeout=30)
            assert not goal.accepted and goal.reason == "refused: no such skill here"
            assert await goal.result(timeout=0.1) is None
            assert server.action.goals == {}


async def test_cancel_a_running_goal(router: str) -> None:
    async with _pair(router) as (sbus, cbus):
        server = Server(sbus)
        async with skill_client(cbus, VID) as client:
            await _subscribed(sbus)
            goal = await client.send_goal(SkillRequest(skill="forward", task_id="t-2"), ready_timeout=30)
            assert (await _first(goal)) is not None  # running
            reply = await goal.cancel(reason="operator stop", source="test")
            assert reply.accepted
            result = await goal.result(timeout=30)
            assert result is not None and result.state == SkillState.ABORTED
            assert result.message == "cancelled: operator stop"
            assert [c.source for c in server.cancels] == ["test"]
            # Once ended, a second cancel is refused without reaching the callback.
            again = await client.cancel(goal.goal_id)
            assert not again.accepted and "not running" in again.reason and len(server.cancels) == 1


async def test_cancel_of_an_unknown_goal_is_refused(router: str) -> None:
    async with _pair(router) as (sbus, cbus):
        server = Server(sbus)
        async with skill_client(cbus, VID) as client:
            await client.send_goal(SkillRequest(skill="refused"), ready_timeout=30)  # the server is up
            reply = await client.cancel("g-nope", reason="x")
            assert not reply.accepted
            assert reply.reason.startswith("skill goal g-nope is not running on vehicle am1")
            assert server.cancels == []


async def test_a_crashed_execute_callback_leaves_no_running_goal(router: str) -> None:
    async with _pair(router) as (sbus, cbus):
        server = Server(sbus)
        async with skill_client(cbus, VID) as client:
            goal = await client.send_goal(SkillRequest(skill="crash"), ready_timeout=30)
            assert goal.accepted
            for _ in range(3000):  # the execute task starts with the accept: poll until it has ended
                if not server.action.goals:
                    break
                await asyncio.sleep(0.01)
            assert server.action.goals == {}
            reply = await client.cancel(goal.goal_id)
            assert not reply.accepted


class DeafClient(ActionClient[SkillRequest, SkillAccept, SkillStatus]):
    """A client whose status subscription hears nothing: what a client sees while its subscription has not yet
    reached the server through the router (Zenoh propagates declarations in the background)."""

    async def _route(self) -> None:
        assert self._sub is not None
        while True:
            await self._sub.recv()


async def test_statuses_the_subscription_missed_come_from_the_result_queryable(router: str) -> None:
    """Stop 40's CI: a task refused at once published both its statuses before the client's subscription reached
    the reasoner, and the client waited 180 s for an end that had come and gone. The client now asks the
    result queryable until its subscription delivers a status of the goal."""
    async with _pair(router) as (sbus, cbus):
        server = Server(sbus)
        server.go.set()  # goals end at once: started, halfway, done
        async with DeafClient(cbus, SKILL_ACTION, VID) as client:
            goal = await client.send_goal(SkillRequest(skill="forward", task_id="t-9"), ready_timeout=30)
            assert goal.accepted
            result = await goal.result(timeout=30)
            assert result is not None and result.state == SkillState.SUCCEEDED and result.message == "done"
            assert goal.recovered >= 1 and not goal._heard
            assert not client._recovering  # nothing keeps asking once the goal ended


async def test_the_result_queryable_answers_the_latest_status_and_refuses_an_unknown_goal(router: str) -> None:
    async with _pair(router) as (sbus, cbus):
        Server(sbus)
        async with skill_client(cbus, VID) as client:
            await _subscribed(sbus)
            goal = await client.send_goal(SkillRequest(skill="forward", task_id="t-8"), ready_timeout=30)
            assert (await _first(goal)) is not None
            running = await cbus.query(Keys(VID).skill_result, GoalRef(goal_id=goal.goal_id), timeout=10)
            assert running.state is SkillState.RUNNING and running.message == "started"
            with pytest.raises(RemoteError, match="skill goal g-nope on vehicle am1 is unknown"):
                await cbus.query(Keys(VID).skill_result, GoalRef(goal_id="g-nope"), timeout=10)
            assert goal.recovered == 0  # the subscription heard the goal: nothing came from the queryable
            reply = await goal.cancel(reason="done testing")
            assert reply.accepted
            ended = await goal.result(timeout=30)
            assert ended is not None
            assert await cbus.query(Keys(VID).skill_result, GoalRef(goal_id=goal.goal_id), timeout=10) == ended


def test_a_status_older_than_the_last_delivered_is_dropped() -> None:
    """A reply of the result queryable and a sample of the subscription can cross in flight: the goal's feedback
    never goes back in time, and the same status heard both ways is kept once."""
    client = skill_client(None, VID)  # type: ignore[arg-type]  # _deliver touches no bus
    handle: GoalHandle[SkillAccept, SkillStatus] = GoalHandle(client, SkillAccept(accepted=True, goal_id="g"), "g",
                                                              True, "")
    older = SkillStatus(goal_id="g", skill="forward", state=SkillState.RUNNING, message="started", stamp_ns=10)
    newer = SkillStatus(goal_id="g", skill="forward", state=SkillState.RUNNING, message="halfway", stamp_ns=20)
    for st in (newer, older, newer):
        client._deliver(handle, st)
    assert [s.message for s in handle.feedback] == ["halfway"]
