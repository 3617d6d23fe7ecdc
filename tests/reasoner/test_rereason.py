"""Offline re-reasoning on a log of a real reasoner process (rules backend) recorded by a real recorder."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import numpy as np
import pytest

from services.reasoner.backends.base import Backend, ModelReply, ModelRequest
from services.reasoner.backends.rules import RulesBackend
from services.reasoner.rereason import rereason_log
from shared.bus import query_ready
from shared.mcaplog import McapReplaySource, reasoning_steps
from shared.messages import TaskRequest, TaskState, TaskStatus
from shared.sensors import color_message
from shared.tasks import recorded_end
from tests.helpers import bus_for, run_stack
from tests.reasoner.fake_world import MiniWorld, Thing, serve_executor
from tests.recorder.samples import K
from tests.recorder.test_recording import aermani

pytestmark = pytest.mark.integration

CMD = "Pick up the red cup and place it on the table"
EXPECTED = ["obj_localization", "grasp", "placement_localization", "place", "done"]


async def camera(bus) -> None:
    rgb = np.zeros((60, 80, 3), dtype=np.uint8)
    jpeg = None
    while True:
        msg = color_message(rgb, time.time_ns(), jpeg=jpeg)
        bus.publish(K.camera_color, msg)
        await asyncio.sleep(0.1)


async def run_task(stack) -> TaskStatus:
    world = MiniWorld([Thing("red cup"), Thing("table", "surface", size=(1.2, 0.8, 0.75))])
    async with bus_for(stack) as bus:
        health = bus.subscribe(K.health("recorder"), maxsize=10)
        await health.recv(timeout=60)  # the recorder is subscribed
        ticker = await serve_executor(bus, world, K, skill_delay=0.2)
        cam = asyncio.create_task(camera(bus))
        statuses = bus.subscribe(K.task_status, maxsize=100)
        try:
            await asyncio.sleep(0.5)  # let the router propagate the queryables
            accept = await query_ready(bus, K.start_task, TaskRequest(command=CMD), timeout=10)
            assert accept.accepted, accept.reason
            while True:
                st = await statuses.recv(timeout=120)
                if st.state.terminal:
                    break
            _path, ended = await recorded_end(health, st.task_id, st.steps, timeout=30)
            assert ended, "the recorder never took the task's end"
            return st
        finally:
            ticker.cancel()
            cam.cancel()


class Scripted(Backend):
    """The rules policy, except on known steps where it answers differently (and once invalidly)."""

    name = "scripted"

    def __init__(self, differ: dict[int, str], invalid_at: int) -> None:
        self.rules = RulesBackend()
        self.differ = differ
        self.invalid_at = invalid_at

    async def complete(self, request: ModelRequest) -> ModelReply:
        step = len(request.context.steps) + 1
        if step == self.invalid_at and not request.feedback:
            return ModelReply(text="I would rather not answer in JSON.", latency_s=0.01)
        if step in self.differ:
            return ModelReply(text=json.dumps({"drt": {"image_description": "x", "summary": "x", "reasoning": "x",
                                                       "action_predictions": dict.fromkeys(
                                                           request.context.skills, "nothing much")},
                                               "ste": {"skill": self.differ[step], "argument": None}}),
                              latency_s=0.01)
        return await self.rules.complete(request)


async def test_rereason_agrees_with_itself_and_finds_scripted_differences(tmp_path: Path) -> None:
    env = {"AERMANI_RECORDER_OUT_DIR": str(tmp_path / "rec"), "AERMANI_RECORDER_HEALTH_PERIOD_S": "0.5"}
    with run_stack(["reasoner", "recorder"], tmp_path, env=env) as stack:
        final = await run_task(stack)
    assert final.state is TaskState.SUCCEEDED, final.message
    [log] = sorted((tmp_path / "rec").glob("*.mcap"))
    recorded = reasoning_steps(log)
    assert [s.ste.skill for s in recorded] == EXPECTED
    assert all(s.image_stamp_ns > 0 for s in recorded)

    same = await rereason_log(log, backend="rules")
    assert [s.step for s in same.steps] == [1, 2, 3, 4, 5]
    assert same.agreement_rate == 1.0 and same.invalid_rate == 0.0 and same.differing == []
    assert all(s.observation_exact for s in same.steps), [s.observation_exact for s in same.steps]

    scripted = Scripted(differ={2: "yaw_left", 4: "forward"}, invalid_at=3)
    res = await rereason_log(log, backend_obj=scripted)
    task_id = recorded[0].task_id
    assert res.differing == [(task_id, 2), (task_id, 4)]
    assert res.agreement_rate == pytest.approx(3 / 5)
    assert res.invalid_rate == pytest.approx(1 / 6)  # one invalid answer among six calls
    assert [s.skill for s in res.steps] == ["obj_localization", "yaw_left", "placement_localization", "forward",
                                            "done"]

    # The same through the CLI, and the MCAP answer source the reasoner's replay backend can use.
    out = aermani("rereason", str(log), "--backend", "rules", "--json")
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["summary"]["agreement_rate"] == 1.0
    answers = list(McapReplaySource(log).answers())
    assert len(answers) == 5
    replayed = aermani("rereason", str(log), "--backend", "replay", "--answers", str(log))
    assert replayed.returncode == 0, replayed.stderr
    assert "agreement 100%" in replayed.stdout
    # Another variant works on the same observations (no DRT asked: the rules policy still agrees).
    other = await rereason_log(log, backend="rules", variant="no_drt")
    assert other.variant == "no_drt" and other.agreement_rate == 1.0
