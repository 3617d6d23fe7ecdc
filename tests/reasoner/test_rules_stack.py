"""The rules baseline on the real stack (simulator, bridge, perception, executor, reasoner as processes): a command
naming an object that is not in the room ends "not found" before the step cap after the vehicle has flown through
the room, and a command it cannot understand is refused before takeoff (the vehicle is never armed)."""

from __future__ import annotations

import asyncio
import math
import re

import pytest

from aermani.launcher import available_services
from shared.bus import query_ready
from shared.keys import Keys
from shared.messages import Scenario, TaskRequest, TaskState
from shared.tasks import follow_task
from tests.helpers import arun, bus_for, run_stack

pytestmark = [pytest.mark.integration, pytest.mark.slow]
NEEDED = ["sim", "autopilot_bridge", "perception", "executor", "reasoner"]
if not set(available_services()) >= set(NEEDED):
    pytest.skip("the full stack is not in this checkout", allow_module_level=True)

MAX_STEPS = 80
ENV = {"AERMANI_REASONER_BACKEND": "rules", "AERMANI_SIM_SPEED_FACTOR": "4", "AERMANI_SIM_FPS": "5",
       "AERMANI_REASONER_MAX_STEPS": str(MAX_STEPS)}
_AT = re.compile(r"now at \((-?[\d.]+), (-?[\d.]+), (-?[\d.]+)\)")


async def _run(stack, command: str, t_max: float) -> tuple:
    """Reset the room (a red cup and a table; no unicorn), run the command, and watch whether the vehicle armed."""
    keys = Keys(stack.procs[0].vehicle_id)
    async with bus_for(stack) as bus:
        reset = await query_ready(bus, keys.sim_reset, Scenario(seed=3, target_object="red cup", destination="table"),
                                  timeout=60)
        assert reset.ok, reset.message
        states = bus.subscribe(keys.autopilot_state, maxsize=100)
        armed: list[bool] = []

        async def watch() -> None:
            while True:
                armed.append((await states.recv()).armed)

        watcher = asyncio.create_task(watch())
        try:
            followed = await follow_task(bus, keys, TaskRequest(command=command, t_max_s=t_max), timeout=t_max + 60)
            await asyncio.sleep(1.0)
        finally:
            watcher.cancel()
        assert armed, "no vehicle state received"
        return followed, any(armed)


def test_absent_object_ends_not_found_after_flying_through_the_room(tmp_path) -> None:
    with run_stack(NEEDED, tmp_path, env=ENV, timeout=180) as stack:
        followed, armed = arun(_run(stack, "Could you find the unicorn and put it on the table?", 900), timeout=1100)
    final, steps = followed.final, followed.steps
    assert final is not None and final.state is TaskState.FAILED, final
    assert final.message.startswith("not found"), final.message
    assert final.steps < MAX_STEPS and "steps; vehicle held" not in final.message
    assert armed
    skills = [s.ste.skill for s in steps if s.ste]
    assert skills[-1] == "done" and "grasp" not in skills
    # It flew through the room (not only turned in place): positions reported by the motions changed.
    where = [tuple(float(v) for v in m.groups()) for s in steps if (m := _AT.search(s.skill_message or ""))]
    assert where, "no motion reported a position"
    spread = max(math.dist(a[:2], b[:2]) for a in where for b in where)
    print(f"{final.steps} steps, farthest apart {spread:.1f} m: {final.message}")
    assert spread >= 1.5, where
    assert skills.count("forward") >= 3


def test_ununderstood_command_is_refused_before_takeoff(tmp_path) -> None:
    with run_stack(NEEDED, tmp_path, env=ENV, timeout=180) as stack:
        followed, armed = arun(_run(stack, "Sing me a song", 120), timeout=300)
    final = followed.final
    assert followed.accept.accepted
    assert final is not None, f"no terminal status ({followed.error or 'none came'})"
    assert final.state is TaskState.FAILED, final
    assert final.message.startswith("command refused before takeoff") and "Sing me a song" in final.message
    assert final.steps == 0 and followed.steps == [] and final.model_calls == 0
    assert not armed  # the vehicle never armed: no takeoff, no skill
