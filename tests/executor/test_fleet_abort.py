"""The fleet-wide abort key is obeyed like the vehicle's own: the running skill stops and the vehicle holds."""

from __future__ import annotations

import asyncio

from shared.keys import FLEET_ABORT
from shared.messages import Abort, SkillState
from tests.executor.rig import rig
from tests.helpers import matched, wait_until


async def test_executor_obeys_the_fleet_abort():
    async with rig(translation_speed=0.3) as r:
        acks = r.bus.subscribe(r.keys.abort_ack, maxsize=10)
        await matched(r.executor.bus, r.keys.abort_ack)
        await matched(r.bus, FLEET_ABORT)
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


async def test_a_command_the_bridge_stopped_for_an_abort_ends_the_skill_aborted():
    """The bridge can get an abort before the executor does (one message, several subscribers, any order): the
    command it stops answers `aborted`, and the skill ends ABORTED, not FAILED, with no abort of its own."""
    from shared.messages import AutopilotResult

    async with rig(airborne_at=None) as r:
        plain = r.vehicle.handle

        async def bridge_first(cmd) -> AutopilotResult:
            if cmd.kind == "takeoff":
                return AutopilotResult(ok=False, command="takeoff", aborted=True,
                                       message="takeoff stopped: aborted by gateway: operator")
            return await plain(cmd)

        r.vehicle.handle = bridge_first  # type: ignore[method-assign]
        st = await r.run_skill("takeoff")
        assert st.state == SkillState.ABORTED, st.message
        assert "aborted by gateway: operator" in st.message

        async def refused(cmd) -> AutopilotResult:  # the same refusal without the flag is a plain failure
            return AutopilotResult(ok=False, command=cmd.kind, message="takeoff refused: not armable")

        r.vehicle.handle = refused  # type: ignore[method-assign]
        st = await r.run_skill("takeoff")
        assert st.state == SkillState.FAILED, st.message
