"""The paper's Table III baseline frameworks (saycan, direct, waypoint, plan_once) over the same skill interface,
through the real loop with model backends against the local stand-in server, and the paper-faithful prompt
settings (paper_history, free_text_baselines)."""

from __future__ import annotations

import asyncio
import json

import jsonschema
import pytest

from services.reasoner.backends import make_backend
from services.reasoner.backends.base import Backend, ModelReply, ModelRequest
from services.reasoner.backends.rules import RulesBackend
from services.reasoner.baselines import restrict_library
from services.reasoner.library import default_library
from services.reasoner.loop import TaskRunner
from services.reasoner.parse import parse_answer
from services.reasoner.prompt import History, HistoryEntry, Observation, PromptCompiler
from services.reasoner.settings import ReasonerSettings
from shared import skills as S  # noqa: N812
from shared.errors import InvalidAnswer
from shared.messages import (
    BASELINES,
    Detection,
    SkillAccept,
    SkillRequest,
    TaskRequest,
    TaskState,
    WorkingMemory,
)
from tests.reasoner.fake_vlm import FakeVLMServer, strict_problems
from tests.reasoner.fake_world import MiniWorld, MiniWorldPort, Thing

CMD = "Pick up the red cup and place it on the table"
MANIPULATION = (S.OBJ_LOCALIZATION, S.GRASP, S.PLACEMENT_LOCALIZATION, S.PLACE)


def world() -> MiniWorld:
    return MiniWorld([Thing("red cup"), Thing("table", "surface", size=(1.2, 0.8, 0.75))])


class CheckedPort(MiniWorldPort):
    """A MiniWorld whose executor answers check_skill: grasp needs a localized object, place a held one."""

    def __init__(self, w: MiniWorld) -> None:
        super().__init__(w)
        self.checked: list[str] = []

    async def check_skill(self, request: SkillRequest) -> SkillAccept:
        self.checked.append(request.skill)
        if request.skill == S.GRASP and not self.world.localized:
            return SkillAccept(accepted=False, goal_id="", reason="nothing localized: run obj_localization first")
        if request.skill == S.PLACE and self.world.held is None:
            return SkillAccept(accepted=False, goal_id="", reason="nothing held")
        return SkillAccept(accepted=True, goal_id="")


@pytest.fixture(scope="module")
def vlm():
    with FakeVLMServer() as srv:
        yield srv


def run(settings: ReasonerSettings, port: MiniWorldPort, backend: Backend | None = None, command: str = CMD):
    backend = backend or make_backend(settings)
    steps: list = []

    async def go():
        try:
            return await TaskRunner(TaskRequest(command=command), settings, backend, port,
                                    publish_step=steps.append, publish_status=lambda _s: None).run(asyncio.Event())
        finally:
            await backend.aclose()

    return asyncio.run(asyncio.wait_for(go(), 120)), steps


def model_settings(kind: str, vlm: FakeVLMServer, **kw: object) -> ReasonerSettings:
    base = vlm.openai_base_url if kind == "openai" else vlm.anthropic_base_url
    return ReasonerSettings(**{"backend": kind, "base_url": base, "api_key": "none", "model": "fake-vlm",
                               "request_timeout_s": 5.0, "max_steps": 30, **kw})


@pytest.mark.parametrize("kind", ["openai", "anthropic"])
@pytest.mark.parametrize("variant", BASELINES)
def test_each_baseline_runs_end_to_end_with_a_model_backend(kind: str, variant: str, vlm: FakeVLMServer) -> None:
    n0 = len(vlm.requests)
    w = world()
    port = CheckedPort(w)
    final, steps = run(model_settings(kind, vlm, variant=variant), port)
    requests = vlm.requests[n0:]
    assert final.state.terminal and final.variant == variant and steps
    assert all(s.variant == variant for s in steps)
    assert vlm.schema_errors == []
    assert all(vlm.schemas[n0:]), "a baseline is schema-decoded in auto mode"
    if variant == "saycan":
        assert final.state is TaskState.SUCCEEDED, final.message
        assert w.placed_on == {"red cup": "table"}
        offered = {s.name for s in default_library().skills if s.policy_visible}
        for rec in steps:
            assert {c.skill for c in rec.scores} == offered  # every skill rated, each checked with the executor
            best = max((c for c in rec.scores if c.feasible), key=lambda c: c.weighted)
            assert (rec.ste.skill, rec.ste.argument) == (best.skill, best.argument)
            assert all(c.weighted == (c.score if c.feasible else 0.0) for c in rec.scores)
        assert any(not c.feasible and c.reason for rec in steps for c in rec.scores)
        assert S.GRASP in port.checked
    elif variant == "direct":
        assert final.state is TaskState.SUCCEEDED, final.message
        assert "preamble" not in steps[0].prompt
        assert all(rec.drt is not None and rec.drt.model_dump(exclude_none=True) == {} for rec in steps)
    elif variant == "waypoint":
        for part in (steps[0].prompt["skill_library"], json.dumps(vlm.schemas[n0])):
            assert not any(m in part for m in MANIPULATION), part
        assert all(rec.ste.skill in (*S.MOTION_PRIMITIVES, S.DONE) for rec in steps)
        assert not any(e.split("(")[0] in MANIPULATION for e in w.executed)
        assert not w.placed_on  # no manipulation offered: the command cannot be carried out
    else:  # plan_once
        assert final.state is TaskState.SUCCEEDED, final.message
        assert len(requests) == 1 == final.model_calls  # one plan, never re-planned
        plan = [(p.skill, p.argument) for p in steps[0].plan]
        assert [(r.ste.skill, r.ste.argument) for r in steps] == plan and plan[-1] == (S.DONE, None)
        assert all(not r.calls for r in steps[1:])


def test_plan_once_failure_ends_the_task_without_re_planning(vlm: FakeVLMServer) -> None:
    n0 = len(vlm.requests)
    w = world()
    w.fail_next[S.GRASP] = 1
    final, steps = run(model_settings("openai", vlm, variant="plan_once"), MiniWorldPort(w))
    assert final.state is TaskState.FAILED
    assert "plan step 2 grasp failed" in final.message and "does not re-plan" in final.message
    assert len(vlm.requests) - n0 == 1 and len(steps) == 2


class Scores(Backend):
    """A scripted SayCan answer: grasp rated highest (the executor refuses it: nothing is localized)."""

    kind = name = "scripted"

    async def complete(self, request: ModelRequest) -> ModelReply:
        rated = {S.GRASP: 0.9, S.YAW_RIGHT: 0.2, S.DONE: 0.6}
        args = {S.OBJ_LOCALIZATION: "red cup", S.PLACEMENT_LOCALIZATION: "table"}
        scores = [{"skill": s, "argument": args.get(s), "score": rated.get(s, 0.1)} for s in request.context.skills]
        return ModelReply(text=json.dumps({"scores": scores}), latency_s=0.0)


def test_saycan_weights_scores_by_the_executors_feasibility() -> None:
    w = world()
    port = CheckedPort(w)
    final, steps = run(ReasonerSettings(variant="saycan", max_steps=1), port, Scores())
    rec = steps[0]
    grasp = next(c for c in rec.scores if c.skill == S.GRASP)
    assert grasp.score == 0.9 and not grasp.feasible and grasp.weighted == 0.0 and "localized" in grasp.reason
    assert rec.ste.skill == S.DONE  # 0.6 x 1 beats 0.9 x 0 and 0.2 x 1
    assert w.executed == [S.TAKEOFF, S.DONE] and final.state is TaskState.SUCCEEDED


def test_rules_backend_refuses_the_baselines_with_the_reason() -> None:
    for variant in BASELINES:
        w = world()
        final, steps = run(ReasonerSettings(variant=variant), MiniWorldPort(w), RulesBackend())
        assert final.state is TaskState.FAILED and "does not emulate" in final.message and variant in final.message
        assert not steps and w.executed == []  # refused before takeoff


def test_baseline_answers_are_read_strictly() -> None:
    lib = default_library()
    names = [s.name for s in lib.skills if s.policy_visible]
    args = {S.OBJ_LOCALIZATION: "cup", S.PLACEMENT_LOCALIZATION: "table"}
    full = [{"skill": n, "argument": args.get(n), "score": 0.1} for n in names]
    parsed = parse_answer(json.dumps({"scores": full}), "saycan", lib)
    assert len(parsed.scores) == len(names)
    with pytest.raises(InvalidAnswer, match="missing: done"):
        parse_answer(json.dumps({"scores": full[:-1] if names[-1] == S.DONE else
                                 [c for c in full if c["skill"] != S.DONE]}), "saycan", lib)
    with pytest.raises(InvalidAnswer, match="number"):
        parse_answer(json.dumps({"scores": [{**full[0], "score": "high"}, *full[1:]]}), "saycan", lib)
    with pytest.raises(InvalidAnswer, match="end with done"):
        parse_answer(json.dumps({"plan": [{"skill": "yaw_left", "argument": None}]}), "plan_once", lib)
    with pytest.raises(InvalidAnswer, match="needs an argument"):
        parse_answer(json.dumps({"plan": [{"skill": S.OBJ_LOCALIZATION, "argument": None},
                                          {"skill": S.DONE, "argument": None}]}), "plan_once", lib)
    direct = parse_answer('{"skill": "yaw_left", "argument": null, "reasoning": "turn"}', "direct", lib)
    assert direct.ste.skill == S.YAW_LEFT and direct.drt.reasoning is None


@pytest.mark.parametrize("variant", BASELINES)
def test_baseline_schemas_are_strict_and_fit_the_stand_ins_answers(variant: str) -> None:
    from tests.reasoner.fake_vlm import shaped_answer
    from tests.reasoner.prompt_reader import answer_for_prompt

    lib = restrict_library(variant, default_library())  # as the loop does
    compiled = PromptCompiler(variant, lib).compile(CMD, History(), Observation())
    assert compiled.schema is not None and strict_problems(compiled.schema) == []
    jsonschema.Draft202012Validator.check_schema(compiled.schema)
    answer = shaped_answer(answer_for_prompt(compiled.text), compiled.schema)
    jsonschema.validate(json.loads(answer), compiled.schema)
    parse_answer(answer, variant, lib)


def test_paper_history_holds_only_each_steps_drt_and_action() -> None:
    obs = Observation(detections=(Detection(label="red cup"),), memory=WorkingMemory(held_object="blue box"))
    entry = HistoryEntry(1, S.OBJ_LOCALIZATION, "red cup", "succeeded", "localized red cup at (1, 2, 3)",
                         "red cup", "searched once", "the cup is ahead", image_description="a cup on a table",
                         prediction="finds the cup")
    ours = History()
    paper = History(paper=True)
    for h in (ours, paper):
        h.append(entry)
    text = paper.render(obs)
    assert text.splitlines()[0] == "#1 obj_localization(red cup) -> succeeded"
    for part in ("a cup on a table", "searched once", "finds the cup", "the cup is ahead"):
        assert part in text
    for absent in ("Perception sees now", "Working memory", "Now:", "blue box", "executor:", "(1, 2, 3)"):
        assert absent not in text and absent in ours.render(obs)
    assert History(paper=True).render(obs) == "No skill executed yet."
    long = History(max_chars=500, paper=True)
    for i in range(40):
        long.append(HistoryEntry(i + 1, S.YAW_LEFT, None, "succeeded", reasoning="keep turning " * 5))
    cut = long.render(obs)
    assert len(cut) <= 500 and cut.startswith("(") and "#40 yaw_left" in cut


def test_paper_history_setting_reaches_the_prompt(vlm: FakeVLMServer) -> None:
    final, steps = run(model_settings("openai", vlm, paper_history=True), CheckedPort(world()))
    assert steps and all("Perception sees now" not in s.prompt["history"] for s in steps)
    assert "your reasoning:" in steps[-1].prompt["history"]


def test_free_text_baselines_sends_no_schema_for_unstructured_and_react(vlm: FakeVLMServer) -> None:
    lib = default_library()
    for variant in ("unstructured", "react"):
        assert PromptCompiler(variant, lib).schema is not None
        assert PromptCompiler(variant, lib, free_text_baselines=True).schema is None
    assert PromptCompiler("full", lib, free_text_baselines=True).schema is not None
    n0 = len(vlm.requests)
    final, steps = run(model_settings("openai", vlm, variant="react", free_text_baselines=True, max_steps=3),
                       CheckedPort(world()))
    assert vlm.schemas[n0:] and not any(vlm.schemas[n0:])
    assert all(not c.structured for s in steps for c in s.calls)
