"""Each reasoning step records where its time went (issue 27): the observation's waits, the prompt, the model,
the executor's acceptance, the skill and its report, from the stamps the loop and the executor take."""

from __future__ import annotations

import asyncio
import dataclasses

from services.reasoner.backends.rules import RulesBackend
from services.reasoner.loop import TaskRunner, skill_times
from services.reasoner.prompt import Observation
from services.reasoner.settings import ReasonerSettings
from shared.messages import SkillAccept, SkillRequest, SkillState, SkillStatus, TaskRequest, TaskState
from tests.reasoner.fake_world import MiniWorld, MiniWorldPort, Thing

TABLE = Thing("table", "surface", headings=(0, 1, 7), size=(1.2, 0.8, 0.75))
MS = 1_000_000


class StampedWorld(MiniWorldPort):
    """Observations that waited 20 ms for a frame, 10 ms for detections and 5 ms for a state (slept, so the loop's
    own clock sees them); skills the 'executor' accepts 3 ms after the request, runs for 40 ms and reports 2 ms
    after their end."""

    async def observe(self, newer_than_ns: int) -> Observation:
        await asyncio.sleep(0.035)
        obs = await super().observe(newer_than_ns)
        return dataclasses.replace(obs, frame_wait_s=0.020, detections_wait_s=0.010, state_wait_s=0.005)

    async def run_skill(self, request: SkillRequest, timeout: float,
                        ready_timeout: float = 0.0) -> tuple[SkillAccept, SkillStatus | None]:
        import time
        sent = time.time_ns()
        await asyncio.sleep(0.045)
        accept, status = await super().run_skill(request, timeout, ready_timeout)
        assert status is not None
        return accept, status.model_copy(update={"started_ns": sent + 3 * MS, "ended_ns": sent + 43 * MS})


def test_every_step_records_its_timing_and_the_parts_fit_the_whole() -> None:
    steps: list = []
    runner = TaskRunner(TaskRequest(command="Pick up the red cup and place it on the table"), ReasonerSettings(),
                        RulesBackend(), StampedWorld(MiniWorld([Thing("red cup"), TABLE])),
                        publish_step=steps.append, publish_status=lambda _s: None)
    final = asyncio.run(runner.run(asyncio.Event()))
    assert final.state is TaskState.SUCCEEDED, final.message
    assert steps
    for rec in steps:
        t = rec.timing
        assert t is not None, rec.step
        assert t.frame_wait_s == 0.020 and t.detections_wait_s == 0.010 and t.state_wait_s == 0.005
        # the observation slept 35 ms between the previous skill's end and this step's model call
        assert t.to_model_s >= 0.035 >= t.frame_wait_s + t.detections_wait_s + t.state_wait_s
        assert t.to_model_s >= t.prompt_s > 0 and t.model_s > 0
        assert abs(t.skill_s - 0.040) < 1e-6
        assert t.accept_s >= 0.0025 and t.report_s >= 0  # sent just before the world's own `sent` stamp


def test_skill_times_from_the_executors_stamps_and_a_local_refusal() -> None:
    st = SkillStatus(goal_id="g", skill="grasp", state=SkillState.SUCCEEDED, started_ns=1_010 * MS,
                     ended_ns=1_510 * MS)
    assert skill_times(st, sent_ns=1_000 * MS, received_ns=1_512 * MS) == {
        "accept_s": 0.010, "skill_s": 0.5, "report_s": 0.002}
    # A refusal made by the loop itself (no executor stamps) costs nothing here; a clock offset never goes negative.
    refused = SkillStatus(goal_id="", skill="grasp", state=SkillState.REJECTED)
    assert skill_times(refused, 1_000 * MS, 1_001 * MS) == {"accept_s": 0.0, "skill_s": 0.001, "report_s": 0.0}
    ahead = st.model_copy(update={"started_ns": 990 * MS})
    assert skill_times(ahead, 1_000 * MS, 1_512 * MS)["accept_s"] == 0.0


def test_a_wall_clock_step_during_a_skill_does_not_inflate_its_time() -> None:
    """A full run: 24.0 s between the grasp's stamps while 13.6 s passed on the monotonic clock (the machine's
    wall clock stepped); skill_s is what was really waited, less the accept and the report."""
    st = SkillStatus(goal_id="g", skill="grasp", state=SkillState.SUCCEEDED, started_ns=1_002 * MS,
                     ended_ns=25_002 * MS)
    t = skill_times(st, sent_ns=1_000 * MS, received_ns=25_007 * MS, elapsed_s=13.6)
    assert t["accept_s"] == 0.002 and t["report_s"] == 0.005
    assert abs(t["skill_s"] - (13.6 - 0.007)) < 1e-9
    # no step: the executor's stamps stand
    assert skill_times(st, sent_ns=1_000 * MS, received_ns=25_007 * MS, elapsed_s=24.007)["skill_s"] == 24.0
