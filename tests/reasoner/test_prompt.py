"""The prompt compiler: each variant has exactly its parts; the History stays under its budget."""

from __future__ import annotations

import json

import pytest

from services.reasoner.library import default_library
from services.reasoner.prompt import (
    DRT_FIELDS,
    SECTION_TITLES,
    History,
    HistoryEntry,
    Observation,
    PromptCompiler,
)
from shared.messages import VARIANTS, Detection, Vec3, WorkingMemory

CMD = "pick up the red cup and place it on the table"
EXPECTED_PARTS = {
    "unstructured": {"command", "skill_library"},
    **{v: {"command", "preamble", "history", "skill_library", "rules"} for v in
       ("no_drt", "drt_v1", "drt_v2", "drt_v3", "full", "react")},
}


def obs(image: bool = True) -> Observation:
    return Observation(image_jpeg=b"\xff\xd8jpeg" if image else None, image_stamp_ns=5,
                       detections=(Detection(label="red cup", size=Vec3(x=0.1, y=0.1, z=0.1)),),
                       memory=WorkingMemory(held_object=None, visible=("red cup",)))


@pytest.mark.parametrize("variant", VARIANTS)
def test_variant_has_exactly_its_parts(variant: str) -> None:
    p = PromptCompiler(variant, default_library()).compile(CMD, History(), obs())
    assert set(p.parts) == EXPECTED_PARTS[variant]
    assert p.has_image and p.image_jpeg == b"\xff\xd8jpeg"
    assert CMD in p.text
    for name, title in SECTION_TITLES.items():
        assert (f"# {title}\n" in p.text) == (name in EXPECTED_PARTS[variant] and variant != "unstructured")
    rules = p.parts.get("rules", "")
    for f in ("image_description", "summary", "action_predictions", "reasoning"):
        assert (f'"{f}"' in rules) == (f in DRT_FIELDS[variant]), (variant, f)
    if variant == "react":
        assert "Thought:" in rules and '"skill"' in rules
    if variant == "no_drt":
        assert '"drt"' not in rules and '"ste"' in rules
    if variant == "unstructured":
        assert "Preamble" not in p.text and "History" not in p.text and "yaw_left" in p.text
        assert "operator" not in p.parts["skill_library"] and "takeoff" not in p.parts["skill_library"]


def test_no_image_when_no_frame() -> None:
    p = PromptCompiler("full", default_library()).compile(CMD, History(), obs(image=False))
    assert not p.has_image


def test_full_rules_example_is_json_covering_every_skill() -> None:
    rules = PromptCompiler("full", default_library()).compile(CMD, History(), obs()).parts["rules"]
    start, end = rules.index("{"), rules.index("\nThe \"drt\"")
    example = json.loads(rules[start:end])
    names = [s.name for s in default_library().skills if s.policy_visible]
    assert list(example["drt"]["action_predictions"]) == names
    assert set(example["ste"]) == {"skill", "argument"}


def test_history_recent_full_older_condensed() -> None:
    h = History(full_steps=2, max_chars=5000)
    for i in range(1, 6):
        h.append(HistoryEntry(i, "forward", None, "succeeded", "moved", "", f"summary {i}", f"reason {i}"))
    text = h.render(obs())
    assert "#1 forward -> succeeded" in text and "your reasoning: reason 5" in text
    assert "reason 1" not in text and "reason 4" in text and "reason 3" not in text


def test_history_200_steps_stays_under_budget() -> None:
    budget = 3000
    h = History(full_steps=6, max_chars=budget)
    compiler = PromptCompiler("full", default_library())
    fixed = None
    for i in range(1, 201):
        h.append(HistoryEntry(i, "obj_localization", "red cup " * 3, "failed", "not visible " * 10,
                              "nothing " * 10, "summary " * 30, "reasoning " * 30))
        p = compiler.compile(CMD, h, obs())
        assert len(p.parts["history"]) <= budget
        rest = len(p.text) - len(p.parts["history"])
        fixed = fixed or rest
        assert rest == fixed  # only the History varies, so the whole prompt is bounded too
    assert "#200 obj_localization" in p.parts["history"]
    assert "earlier steps omitted" in p.parts["history"]


def test_outcome_code_and_facts_in_one_fixed_form() -> None:
    from services.reasoner.prompt import outcome_text
    from shared.messages import OutcomeCode, SkillFacts, SkillOutcome

    missed = SkillOutcome(code=OutcomeCode.MISSED, facts=SkillFacts(attempts=2, offset_m=0.031, target="red cup"))
    assert outcome_text(missed) == "missed (target red cup, attempts 2, offset 0.031 m, holding none)"
    h = History()
    h.append(HistoryEntry(1, "grasp", "red cup", "failed", "the fingers closed on air", outcome=missed))
    h.append(HistoryEntry(2, "forward", None, "succeeded", "moved",
                          outcome=SkillOutcome(code=OutcomeCode.SUCCEEDED, facts=SkillFacts(distance_m=0.5))))
    text = h.render(obs())
    assert "   outcome: missed (target red cup, attempts 2, offset 0.031 m, holding none)" in text
    assert "   outcome: succeeded (distance 0.500 m, holding none)" in text
    assert h.entries[0].condensed() == ("#1 grasp(red cup) -> failed; outcome: missed (target red cup, attempts 2, "
                                        "offset 0.031 m, holding none)")
    assert h.entries[1].condensed() == "#2 forward -> succeeded"
