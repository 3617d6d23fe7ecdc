"""A process that serves the skill action like the executor but never finishes a goal: the victim of the
server-loss test (started with `python -m tests.shared.slow_executor <endpoint>`)."""

from __future__ import annotations

import asyncio
import sys

from shared.action import SKILL_ACTION, ActionServer, ServerGoalHandle
from shared.bus import Bus
from shared.keys import Keys
from shared.messages import CancelGoal, CancelReply, SkillAccept, SkillRequest, SkillState, SkillStatus


async def main(endpoint: str) -> None:
    bus = await Bus.open(connect=[endpoint])
    keys = Keys("am1")

    async def accept(req: SkillRequest) -> SkillAccept:
        return SkillAccept(accepted=True, goal_id="g-1")

    async def execute(handle: ServerGoalHandle[SkillRequest, SkillStatus]) -> None:
        req = handle.request
        handle.publish(SkillStatus(goal_id=handle.goal_id, skill=req.skill, state=SkillState.RUNNING,
                                   task_id=req.task_id, step=req.step))
        await asyncio.Event().wait()  # never ends: the test kills this process

    async def cancel(handle: ServerGoalHandle[SkillRequest, SkillStatus], req: CancelGoal) -> CancelReply:
        return CancelReply(accepted=False, reason="never")

    ActionServer(bus, SKILL_ACTION, keys.vehicle_id, goal_callback=accept, execute_callback=execute,
                 cancel_callback=cancel).start()
    bus.declare_token(keys.alive("executor"))
    print("ready", flush=True)
    await asyncio.Event().wait()


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1]))
