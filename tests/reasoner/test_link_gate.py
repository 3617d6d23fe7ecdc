"""The reasoner's link gate (issue 18): while the vehicle's state is missing, old (a silent or dead bridge
leaves its last state behind, still showing `link_ok`), or shows a lost link, no skill is issued and no step
is spent; the task continues when the link is back, or holds and fails with the reason after `link_wait_s`."""

from __future__ import annotations

import asyncio
import dataclasses

from services.reasoner.backends.rules import RulesBackend
from services.reasoner.loop import TaskRunner
from services.reasoner.prompt import Observation
from services.reasoner.settings import ReasonerSettings
from shared.messages import SkillAccept, SkillRequest, SkillStatus, TaskRequest, TaskState
from tests.reasoner.fake_world import MiniWorld, MiniWorldPort, Thing

TABLE = Thing("table", "surface", headings=(0, 1, 7), size=(1.2, 0.8, 0.75))
COMMAND = "Pick up the red cup and place it on the table"


class SilentBridgeWorld(MiniWorldPort):
    """After the take-off, the vehicle state stops arriving: observations carry the last state, ageing; after
    `silent_observations` observations it arrives again (never, if None)."""

    def __init__(self, world: MiniWorld, silent_observations: int | None) -> None:
        super().__init__(world)
        self.silent_left = silent_observations
        self.gated = 0
        self.holds: list[str] = []

    async def observe(self, newer_than_ns: int) -> Observation:
        obs = await super().observe(newer_than_ns)
        if self.world.executed == ["takeoff"] and (self.silent_left is None or self.silent_left > 0):
            self.gated += 1
            if self.silent_left is not None:
                self.silent_left -= 1
            return dataclasses.replace(obs, state_age_s=3.0 + 0.5 * self.gated)
        return obs

    async def run_skill(self, request: SkillRequest, timeout: float) -> tuple[SkillAccept, SkillStatus | None]:
        if request.skill == "hold":
            self.holds.append(request.task_id or "")
        return await super().run_skill(request, timeout)


def _run(port: SilentBridgeWorld, **settings: object):
    steps: list = []
    runner = TaskRunner(TaskRequest(command=COMMAND), ReasonerSettings(max_steps=40, **settings), RulesBackend(),
                        port, publish_step=steps.append, publish_status=lambda _s: None)
    return asyncio.run(runner.run(asyncio.Event())), steps


def test_a_silent_bridge_stops_the_skills_then_the_task_holds_and_fails_with_the_reason() -> None:
    w = MiniWorld([Thing("red cup"), TABLE])
    port = SilentBridgeWorld(w, silent_observations=None)
    final, steps = _run(port, link_wait_s=1.0, state_stale_s=2.0)
    assert final.state is TaskState.FAILED
    assert "no vehicle state from the autopilot bridge for" in final.message, final.message
    assert w.executed == ["takeoff", "hold"], "a skill other than the gate's hold ran while the state was stale"
    assert port.gated >= 2 and port.holds, "the gate neither waited nor held"
    assert steps == [], "a step was spent while waiting for the link (the take-off comes before the first step)"


def test_the_task_continues_when_the_state_comes_back() -> None:
    w = MiniWorld([Thing("red cup"), TABLE])
    port = SilentBridgeWorld(w, silent_observations=3)
    final, _ = _run(port, link_wait_s=30.0, state_stale_s=2.0)
    assert final.state is TaskState.SUCCEEDED, final.message
    assert port.gated == 3 and not port.holds
    assert w.placed_on == {"red cup": "table"}
