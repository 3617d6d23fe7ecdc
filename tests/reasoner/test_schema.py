"""The answer schema comes from the live skill library and the variant, and is strict-mode clean."""

from __future__ import annotations

import json

import jsonschema
import pytest

from services.reasoner.library import default_library
from services.reasoner.parse import parse_answer
from services.reasoner.schema import answer_schema
from shared.messages import VARIANTS, SkillLibrary, SkillSpec
from tests.reasoner.fake_vlm import strict_problems

LIB = default_library()


def with_extra_skill() -> SkillLibrary:
    """The executor's library with one more skill, as a new skill module would register it."""
    extra = SkillSpec(name="spray", category="manipulation", description="Spray the queried surface.",
                      argument="surface query", argument_required=True)
    return SkillLibrary(skills=(*LIB.skills, extra))


@pytest.mark.parametrize("variant", VARIANTS)
def test_schema_is_strict_mode_clean_and_enumerates_the_live_library(variant: str) -> None:
    lib = with_extra_skill()
    schema = answer_schema(variant, lib)
    jsonschema.Draft202012Validator.check_schema(schema)
    assert strict_problems(schema) == []
    text = json.dumps(schema)
    assert '"spray"' in text and '"takeoff"' not in text  # policy skills only, the new one included


def test_argument_rules_are_in_the_schema() -> None:
    v = jsonschema.Draft202012Validator(answer_schema("no_drt", with_extra_skill()))

    def ok(skill: str, arg: object) -> bool:
        return v.is_valid({"ste": {"skill": skill, "argument": arg}})

    assert ok("yaw_left", None) and not ok("yaw_left", "2 m")            # no argument
    assert ok("spray", "table") and not ok("spray", None) and not ok("spray", "  ")  # required
    assert ok("grasp", None) and ok("grasp", "red cup")                   # optional
    assert not ok("fly_to_target", None)


def test_full_schema_requires_a_prediction_per_skill_and_parses() -> None:
    schema = answer_schema("full", LIB)
    names = [s.name for s in LIB.skills if s.policy_visible]
    answer = {"drt": {"image_description": "a cup", "summary": "start", "reasoning": "visible",
                      "action_predictions": dict.fromkeys(names, "x")},
              "ste": {"skill": "obj_localization", "argument": "red cup"}}
    jsonschema.validate(answer, schema)
    assert parse_answer(json.dumps(answer), "full", LIB).ste.argument == "red cup"
    del answer["drt"]["action_predictions"]["place"]
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(answer, schema)


def test_react_schema_form_parses_with_its_thought() -> None:
    raw = json.dumps({"thought": "the cup is ahead", "action": {"skill": "forward", "argument": None}})
    jsonschema.validate(json.loads(raw), answer_schema("react", LIB))
    p = parse_answer(raw, "react", LIB)
    assert p.ste.skill == "forward" and p.drt.reasoning == "the cup is ahead"
