"""The envelope at the bridge: the simulator and the bridge as real processes over real UDP, commands sent
straight to autopilot/command (bypassing the executor, as an intruder or a buggy tool would). Out-of-envelope
commands and an in-air disarm without the kill flag are refused with reasons, the vehicle does not move, and
the bridge's log names who sent each command."""

from __future__ import annotations

import asyncio
import math

import pytest

from shared.messages import DisarmCommand, GotoCommand, TakeoffCommand, Vec3
from tests.autopilot_bridge.test_integration import ENV, command, sim_ready, start_state, take_off
from tests.helpers import bus_for, run_stack, wait_until

pytestmark = pytest.mark.integration


async def test_out_of_envelope_commands_and_in_air_disarm_are_refused_at_the_bridge(tmp_path) -> None:
    async def body(stack):
        async with bus_for(stack) as bus:
            bus.name = "envelope-test-intruder"
            await sim_ready(bus)
            state, task = await start_state(bus)
            res = await command(bus, TakeoffCommand(altitude=10.0))
            assert not res.ok and "above the maximum 2.40 m" in res.message, res.message
            assert not state.value.armed, "a refused takeoff must not arm"

            s0 = await take_off(bus, state)
            here = s0.position
            refusals = {
                "geofence": GotoCommand(position=Vec3(x=10.0, y=here.y, z=1.5), yaw=0.0),
                "ceiling": GotoCommand(position=Vec3(x=here.x, y=here.y, z=10.0), yaw=0.0),
                "floor": GotoCommand(position=Vec3(x=here.x, y=here.y, z=0.05), yaw=0.0),
                "speed": GotoCommand(position=Vec3(x=here.x + 0.5, y=here.y, z=1.5), yaw=0.0, max_speed=8.0),
            }
            expected = {"geofence": "outside the geofence (x must stay in [-3.80, 3.80])",
                        "ceiling": "outside the geofence (z must stay in [0.00, 2.50])",
                        "floor": "below the minimum 0.20 m",
                        "speed": "above the limit 1.00 m/s"}
            for name, cmd in refusals.items():
                res = await command(bus, cmd)
                assert not res.ok and expected[name] in res.message, (name, res.message)

            res = await command(bus, DisarmCommand())
            assert not res.ok and "in the air" in res.message and "kill=true" in res.message, res.message
            res = await command(bus, DisarmCommand(force=True))
            assert not res.ok and "kill=true" in res.message, "force alone must not disarm in the air"

            # Nothing moved: still armed, airborne, where it was.
            await asyncio.sleep(1.0)
            now = await state.wait(5.0)
            assert now.armed and now.offboard_ok
            assert math.dist(now.position.as_tuple(), here.as_tuple()) < 0.15, (now.position, here)

            # The emergency kill is obeyed (and logged as such).
            res = await command(bus, DisarmCommand(kill=True))
            assert res.ok, res.message
            await wait_until(lambda: state.value is not None and not state.value.armed, 30, what="killed")
            task.cancel()

        log = stack.find("autopilot_bridge").log_path.read_text()
        assert log.count("REFUSED") >= 7, log[-3000:]
        assert "envelope-test-intruder (zid " in log
        refused_goto = [ln for ln in log.splitlines() if "REFUSED" in ln and '"kind":"goto"' in ln]
        assert len(refused_goto) == 4 and all("envelope-test-intruder" in ln for ln in refused_goto)
        assert "KILL: disarm with kill=true from envelope-test-intruder" in log

    with run_stack(["sim", "autopilot_bridge"], tmp_path, env=ENV) as stack:
        await body(stack)

