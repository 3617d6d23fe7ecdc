"""A task cancel that arrives while the skill goal's accept reply is still on its way: the executor starts a goal,
and publishes it running, before its reply reaches the reasoner (Zenoh orders nothing across keys). The reasoner
must wait for that reply and cancel the goal it names, not hold with "no skill was running" while the skill goes
on (a fresh-clone run failed `test_cancel_a_task_mid_grasp_stops_the_grasp_and_holds` on this window). Real
Zenoh over loopback, the reasoner's own BusWorld, an ActionServer whose reply is held back."""

from __future__ import annotations

import asyncio

import pytest

from services.reasoner.service import BusWorld
from services.reasoner.settings import ReasonerSettings
from shared.action import SKILL_ACTION, ActionServer, ServerGoalHandle
from shared.bus import Bus
from shared.keys import Keys
from shared.messages import CancelGoal, CancelReply, SkillAccept, SkillRequest, SkillState, SkillStatus

pytestmark = pytest.mark.integration
VID = "am1"


class LateReply:
    """A skill server that publishes a goal running, then holds its accept reply until `reply` is set."""

    def __init__(self, bus: Bus) -> None:
        self.reply = asyncio.Event()
        self.cancels: list[CancelGoal] = []
        self.action = ActionServer(bus, SKILL_ACTION, VID, goal_callback=self.on_goal,
                                   cancel_callback=self.on_cancel).start()
        bus.declare_token(Keys(VID).alive("executor"))

    async def on_goal(self, req: SkillRequest) -> SkillAccept:
        self.action.publish(SkillStatus(goal_id="g-1", skill=req.skill, state=SkillState.RUNNING, message="started",
                                        task_id=req.task_id, step=req.step))
        await self.reply.wait()
        return SkillAccept(accepted=True, goal_id="g-1")

    async def on_cancel(self, h: ServerGoalHandle[SkillRequest, SkillStatus], req: CancelGoal) -> CancelReply:
        self.cancels.append(req)
        h.publish(SkillStatus(goal_id=h.goal_id, skill=h.request.skill, state=SkillState.ABORTED,
                              message=f"cancelled: {req.reason}", task_id=h.request.task_id, step=h.request.step))
        return CancelReply(accepted=True)


async def test_a_cancel_before_the_accept_reply_cancels_that_goal(router: str) -> None:
    sbus, cbus = await Bus.open(connect=[router]), await Bus.open(connect=[router])
    try:
        server = LateReply(sbus)
        world = BusWorld(cbus, ReasonerSettings(vehicle_id=VID))
        watch = cbus.subscribe(Keys(VID).skill_status, maxsize=50)
        pump = asyncio.create_task(world.pump())
        key = Keys(VID).skill_status
        for _ in range(3000):  # until both status subscriptions reach the server through the router
            if sbus.has_subscribers(key):
                break
            await asyncio.sleep(0.01)
        run = asyncio.create_task(world.run_skill(SkillRequest(skill="grasp", task_id="t-1", step=4), timeout=60,
                                                  ready_timeout=30))
        first = await watch.recv(timeout=30)
        assert first.state == SkillState.RUNNING and first.goal_id == "g-1"
        assert world.running is None  # the window: running on the executor, no accept here yet
        cancel = asyncio.create_task(world.cancel_skill("t-1", "operator stop"))
        for _ in range(20):  # let the cancel reach its first wait before the reply is released
            await asyncio.sleep(0)
        assert not cancel.done()
        server.reply.set()
        stopped = await asyncio.wait_for(cancel, 30)
        assert stopped is not None and stopped.goal_id == "g-1" and stopped.state == SkillState.ABORTED, stopped
        assert [c.goal_id for c in server.cancels] == ["g-1"] and server.cancels[0].reason == "operator stop"
        accept, end = await asyncio.wait_for(run, 30)
        assert accept.accepted and end is not None and end.state == SkillState.ABORTED
        pump.cancel()
    finally:
        await cbus.close()
        await sbus.close()
