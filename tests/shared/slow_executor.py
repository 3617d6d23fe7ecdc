"""A process that serves the skill action like the executor but never finishes a goal: the victim of the
server-loss test (started with `python -m tests.shared.slow_executor <endpoint>`)."""

from __future__ import annotations

import asyncio
import sys

from shared.bus import Bus
from shared.keys import Keys
from shared.messages import CancelGoal, CancelReply, SkillAccept, SkillRequest, SkillState, SkillStatus


async def main(endpoint: str) -> None:
    bus = await Bus.open(connect=[endpoint])
    keys = Keys("am1")

    async def run(req: SkillRequest) -> SkillAccept:
        bus.publish(keys.skill_status, SkillStatus(goal_id="g-1", skill=req.skill, state=SkillState.RUNNING,
                                                   task_id=req.task_id, step=req.step))
        return SkillAccept(accepted=True, goal_id="g-1")

    async def cancel(req: CancelGoal) -> CancelReply:
        return CancelReply(accepted=False, reason="never")

    bus.serve(keys.run_skill, run)
    bus.serve(keys.cancel_skill, cancel)
    bus.declare_token(keys.alive("executor"))
    print("ready", flush=True)
    await asyncio.Event().wait()


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1]))
