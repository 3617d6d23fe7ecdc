"""The reasoner as a real process on real Zenoh, against an executor stand-in served on the bus."""

from __future__ import annotations

import asyncio

import pytest

from shared.keys import Keys
from shared.messages import Abort, TaskRequest, TaskState
from shared.tasks import submit_task
from tests.helpers import arun, bus_for, run_stack
from tests.reasoner.fake_vlm import FakeVLMServer
from tests.reasoner.fake_world import MiniWorld, Thing, serve_executor

pytestmark = pytest.mark.integration
KEYS = Keys("am1")
CMD = "Pick up the red cup and place it on the table"


def world() -> MiniWorld:
    return MiniWorld([Thing("red cup"), Thing("table", "surface", size=(1.2, 0.8, 0.75))])


async def run_task(stack, w: MiniWorld, request: TaskRequest, *, skill_delay: float = 0.0, on_running=None):
    async with bus_for(stack) as bus:
        ticker = await serve_executor(bus, w, KEYS, skill_delay=skill_delay)
        steps = bus.subscribe(KEYS.reasoning_step, maxsize=1000)
        statuses = bus.subscribe(KEYS.task_status, maxsize=100)
        try:
            await asyncio.sleep(0.5)  # let the router propagate the new queryables and subscriptions
            accept = await submit_task(bus, KEYS, request)
            assert accept.accepted, accept.reason
            if on_running is not None:
                await on_running(bus)
            while True:
                st = await statuses.recv(timeout=120)
                if st.state.terminal:
                    break
            await asyncio.sleep(0.3)
            got = []
            while steps.qsize():
                got.append(await steps.recv(timeout=1))
            return st, got
        finally:
            ticker.cancel()


def test_rules_task_over_the_bus_and_one_task_at_a_time(tmp_path) -> None:
    w = world()
    with run_stack(["reasoner"], tmp_path) as stack:
        async def second_rejected(bus) -> None:
            other = await bus.query(KEYS.start_task, TaskRequest(command="pick up the apple"), timeout=10)
            assert not other.accepted and "already runs" in other.reason

        final, steps = arun(run_task(stack, w, TaskRequest(command=CMD), skill_delay=0.3,
                                     on_running=second_rejected))
    assert final.state is TaskState.SUCCEEDED, final.message
    assert w.placed_on == {"red cup": "table"} and w.executed[0] == "takeoff"
    assert [s.ste.skill for s in steps] == ["obj_localization", "grasp", "placement_localization", "place", "done"]
    assert all(s.prompt.keys() == {"command", "preamble", "history", "skill_library", "rules"} for s in steps)
    assert all(s.image_stamp_ns == 0 for s in steps)  # no camera in this stack: no image sent
    assert steps[2].outcome is not None and steps[1].skill_state.value == "succeeded"


def test_abort_stops_the_task(tmp_path) -> None:
    w = MiniWorld([Thing("table", "surface")])  # the cup is never found: the task would scan forever
    with run_stack(["reasoner"], tmp_path) as stack:
        async def abort(bus) -> None:
            await asyncio.sleep(1.0)
            bus.publish(KEYS.abort, Abort(reason="test abort", source="test"))

        final, _steps = arun(run_task(stack, w, TaskRequest(command="find the purple cup"), skill_delay=0.2,
                                      on_running=abort))
    assert final.state is TaskState.ABORTED and "test abort" in final.message


@pytest.mark.parametrize("kind", ["openai", "anthropic"])
def test_vlm_backend_process_with_injected_faults(tmp_path, kind: str) -> None:
    with FakeVLMServer() as vlm:
        vlm.faults.extend(["invalid_json", None, "500", None, "unknown_skill"])
        env = {"AERMANI_REASONER_BACKEND": kind, "AERMANI_REASONER_API_KEY": "none",
               "AERMANI_REASONER_MODEL": "fake-vlm", "AERMANI_REASONER_REQUEST_TIMEOUT_S": "5",
               "AERMANI_REASONER_BASE_URL": vlm.openai_base_url if kind == "openai" else vlm.anthropic_base_url}
        w = world()
        with run_stack(["reasoner"], tmp_path, env=env) as stack:
            final, steps = arun(run_task(stack, w, TaskRequest(command=CMD)))
    assert final.state is TaskState.SUCCEEDED, final.message
    assert final.backend == f"{kind}:fake-vlm"
    assert [s.retries for s in steps[:3]] == [1, 0, 1]
    assert final.invalid_answers == 2 and final.model_calls == sum(len(s.calls) for s in steps)
