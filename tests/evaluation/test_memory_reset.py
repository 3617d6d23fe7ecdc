"""The executor's working memory follows a world reset on the real stack (sim, autopilot bridge, perception and
executor as processes over real Zenoh): the simulator's reset notice empties it, with no process restart, so
the evaluation never restarts the executor between episodes."""

from __future__ import annotations

import asyncio
import time

import pytest

from shared.messages import WorkingMemory
from tests.executor.test_integration import KEYS, Client
from tests.helpers import bus_for, run_stack

pytestmark = [pytest.mark.integration, pytest.mark.slow]


async def _memory_where(sub, pred, timeout: float = 20.0) -> WorkingMemory:
    """The first published memory (the newest already received counts) that satisfies `pred`."""
    deadline = time.monotonic() + timeout
    latest = sub.latest_nowait()
    while latest is None or not pred(latest):
        latest = await sub.recv(timeout=max(0.1, deadline - time.monotonic()))
    return latest


def test_sim_reset_clears_the_executors_working_memory_without_a_restart(tmp_path):
    with run_stack(["sim", "autopilot_bridge", "perception", "executor"], tmp_path,
                   env={"AERMANI_SIM_SPEED_FACTOR": "3"}) as stack:
        executor = stack.find("executor", "am1")
        pid = executor.proc.pid

        async def go() -> None:
            async with bus_for(stack) as bus:
                memory = bus.subscribe(KEYS.memory, maxsize=50)
                c = Client(bus)
                await c.reset(seed=1, target_object="red cup", destination="table")
                await c.takeoff()
                await c.search("obj_localization", "red cup")
                await c.ok("land")
                before = await _memory_where(memory, lambda m: any(o.label == "red cup" for o in m.objects))
                assert before.executed, "the skills run are in memory"
                await asyncio.sleep(1.0)
                still = memory.latest_nowait() or before
                assert any(o.label == "red cup" for o in still.objects), "memory is kept while the world stays"
                await c.reset(seed=7, target_object="red cup", destination="table")
                after = await _memory_where(memory, lambda m: not m.objects and not m.executed)
                assert after.held_object is None and not after.placements

        asyncio.run(asyncio.wait_for(go(), 400))
        assert executor.proc.pid == pid and executor.proc.poll() is None and not executor.exit_codes
