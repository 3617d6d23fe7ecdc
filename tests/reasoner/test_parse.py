"""The parser/validator: strict JSON, lenient recovery, specific rejection reasons."""

from __future__ import annotations

import json

import pytest

from services.reasoner.library import default_library
from services.reasoner.parse import parse_answer
from shared.errors import InvalidAnswer

LIB = default_library()
NAMES = [s.name for s in LIB.skills if s.policy_visible]
FULL_DRT = {"image_description": "a red cup on a table", "summary": "nothing yet",
            "action_predictions": dict.fromkeys(NAMES, "x"), "reasoning": "the cup is visible"}


def full(skill: str = "obj_localization", argument: str | None = "red cup", **drt: object) -> str:
    return json.dumps({"drt": {**FULL_DRT, **drt}, "ste": {"skill": skill, "argument": argument}})


def test_strict_full() -> None:
    p = parse_answer(full(), "full", LIB)
    assert p.ste.skill == "obj_localization" and p.ste.argument == "red cup" and not p.recovered
    assert p.drt.reasoning == "the cup is visible" and set(p.drt.action_predictions) == set(NAMES)


@pytest.mark.parametrize("raw", [
    "```json\n" + full() + "\n```",
    "Sure! Here is my answer:\n" + full() + "\nHope this helps.",
    full()[:-1] + ",}",
    full().replace('"', "'"),
])
def test_lenient_recovery(raw: str) -> None:
    p = parse_answer(raw, "full", LIB)
    assert p.ste.skill == "obj_localization" and p.ste.argument == "red cup" and p.recovered


@pytest.mark.parametrize(("given", "expected"), [("Yaw Right", "yaw_right"), ("obj localization", "obj_localization"),
                                                 ("FORWARD", "forward"), ("object_localization", "obj_localization"),
                                                 ("placement-localization", "placement_localization")])
def test_skill_name_case_and_spacing(given: str, expected: str) -> None:
    arg = "table" if "placement" in expected else "cup"
    assert parse_answer(full(given, arg), "full", LIB).ste.skill == expected


def test_flat_shape_and_skill_call_syntax() -> None:
    p = parse_answer('{"skill": "obj_localization(red cup)"}', "no_drt", LIB)
    assert (p.ste.skill, p.ste.argument) == ("obj_localization", "red cup")


@pytest.mark.parametrize(("raw", "variant", "reason"), [
    ("", "full", "empty"),
    ("I think we should fly up", "full", "No JSON object"),
    (full("fly_up", None), "full", "Unknown skill 'fly_up'"),
    (full("obj_localization", None), "full", "needs an argument (object query)"),
    (json.dumps({"drt": {"summary": "x"}, "ste": {"skill": "up"}}), "drt_v1", "Missing DRT field(s) required by the "
                                                                            "Rules: image_description"),
    (json.dumps({"drt": {k: v for k, v in FULL_DRT.items() if k != "reasoning"}, "ste": {"skill": "up"}}), "full",
     "reasoning"),
    (full(action_predictions={"up": "climbs"}), "full", "missing: yaw_left"),
    (full(action_predictions="all good"), "full", "must be an object"),
    (json.dumps({"drt": FULL_DRT}), "full", "has no skill"),
    ('{"ste": {"skill": ["up"]}}', "no_drt", "must be a string"),
    ('{"ste": {"skill": "takeoff"}}', "no_drt", "Unknown skill 'takeoff'"),
])
def test_rejections_are_specific(raw: str, variant: str, reason: str) -> None:
    with pytest.raises(InvalidAnswer) as exc:
        parse_answer(raw, variant, LIB)
    assert reason in str(exc.value)


def test_argument_to_no_argument_skill_is_ignored() -> None:
    assert parse_answer('{"ste": {"skill": "forward", "argument": "2 m"}}', "no_drt", LIB).ste.argument is None


def test_prediction_coverage_setting() -> None:
    partial = dict.fromkeys(NAMES[:-1], "x")
    with pytest.raises(InvalidAnswer):
        parse_answer(full(action_predictions=partial), "full", LIB)
    assert parse_answer(full(action_predictions=partial), "full", LIB, coverage=0.9).ste.skill == "obj_localization"


def test_react_thought_then_json() -> None:
    p = parse_answer('Thought: the cup is on my left.\nThought: turn.\nAction: {"skill": "yaw_left", "argument": null}',
                     "react", LIB)
    assert p.ste.skill == "yaw_left" and "cup is on my left" in (p.drt.reasoning or "")


@pytest.mark.parametrize(("raw", "skill", "arg"), [("yaw_left", "yaw_left", None),
                                                   ("obj_localization(red cup)", "obj_localization", "red cup"),
                                                   ("I would choose Yaw Right.", "yaw_right", None),
                                                   ("placement_localization: table", "placement_localization", "table")])
def test_unstructured_bare_names(raw: str, skill: str, arg: str | None) -> None:
    p = parse_answer(raw, "unstructured", LIB)
    assert (p.ste.skill, p.ste.argument) == (skill, arg)


def test_no_drt_accepts_extra_drt_fields() -> None:
    assert parse_answer(full("up", None), "no_drt", LIB).drt.summary == "nothing yet"
