"""The fleet-wide abort key is obeyed like the vehicle's own: the running skill stops and the vehicle holds."""

from __future__ import annotations

import asyncio

from shared.keys import FLEET_ABORT
from shared.messages import Abort, SkillState
from tests.executor.rig import rig
from tests.helpers import arun, wait_until


def test_executor_obeys_the_fleet_abort():
    async def main():
        async with rig(translation_speed=0.3) as r:
            acks = r.bus.subscribe(r.keys.abort_ack, maxsize=10)
            acc = await r.request("left")
            assert acc.accepted
            await wait_until(lambda: abs(r.vehicle.vel[1]) > 0.1 or abs(r.vehicle.vel[0]) > 0.1, 10, what="moving")
            abort = Abort(reason="fleet test", source="test")
            r.bus.publish(FLEET_ABORT, abort)
            ack = await acks.recv(timeout=5)
            assert ack.abort_stamp_ns == abort.stamp_ns and "holding" in ack.message
            st = await r.terminal(acc.goal_id, 10)
            assert st.state == SkillState.ABORTED and "fleet test" in st.message
            assert "hold" in r.vehicle.commands
            await asyncio.sleep(0.3)
            assert abs(r.vehicle.vel[0]) < 0.05 and abs(r.vehicle.vel[1]) < 0.05

    arun(main())
