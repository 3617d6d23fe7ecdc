"""Extension point: a skill registered from a test module shows up in the executor's served library, the
prompt's Skill Library, the validator's required action predictions and the rules baseline's choices,
with no other file changed."""

from __future__ import annotations

import json

import pytest

from services.executor.registry import REGISTRY
from services.reasoner.backends.base import PolicyContext
from services.reasoner.backends.rules import RulesPolicy
from services.reasoner.library import policy_skills
from services.reasoner.parse import parse_answer
from services.reasoner.prompt import History, Observation, PromptCompiler
from shared.errors import InvalidAnswer
from tests.executor.rig import rig

MODULE = "tests.extensions.inspect_skill"


@pytest.fixture()
def no_leak():
    yield
    REGISTRY.pop("inspect_below", None)


def _full_answer(library, skill: str, drop: str | None = None) -> str:
    names = [s.name for s in policy_skills(library)]
    drt = {"image_description": "a table from above", "summary": "hovering above the table",
           "action_predictions": {n: "moves or looks" for n in names if n != drop}, "reasoning": "inspect first"}
    return json.dumps({"drt": drt, "ste": {"skill": skill, "argument": None}})


async def test_skill_from_a_test_module_reaches_every_consumer(no_leak):
    async def main():
        async with rig(skill_modules=[MODULE]) as r:
            lib = await r.bus.query(r.keys.skills, None, timeout=5)
            spec = next(s for s in lib.skills if s.name == "inspect_below")
            assert spec.policy_visible and spec.category == "motion"
            assert f"{r.executor.settings.min_altitude:g} m" in spec.description
            st = await r.run_skill("inspect_below")
            assert st.state.value == "succeeded", st.message
            return lib

    lib = await main()
    # The prompt's Skill Library part lists it with its parameter.
    prompt = PromptCompiler("full", lib).compile("inspect below the table", History(), Observation())
    assert "- inspect_below: Drop to" in prompt.parts["skill_library"]
    # The validator requires an action prediction for it, and accepts it as the skill to execute.
    with pytest.raises(InvalidAnswer, match="inspect_below"):
        parse_answer(_full_answer(lib, "forward", drop="inspect_below"), "full", lib)
    parsed = parse_answer(_full_answer(lib, "inspect_below"), "full", lib)
    assert parsed.ste.skill == "inspect_below"
    # The rules baseline chooses it when the command names it.
    ctx = PolicyContext(command="inspect below, then move forward", variant="full",
                        skills=[s.name for s in policy_skills(lib)])
    skill, arg, _why = RulesPolicy().decide(ctx)
    assert (skill, arg) == ("inspect_below", None)


def test_unknown_skill_module_is_a_clear_configuration_error():
    from services.executor.registry import build_library
    from services.executor.settings import ExecutorSettings
    from shared.errors import ConfigError

    with pytest.raises(ConfigError, match="AERMANI_EXECUTOR_SKILL_MODULES"):
        build_library(ExecutorSettings(skill_modules=["tests.extensions.nowhere"]))
