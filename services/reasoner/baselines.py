"""The paper's Table III baseline frameworks, mapped onto the same skill interface as AERMANI-VLM.

Each is a prompt variant (`AERMANI_REASONER_VARIANT` or a task's `variant`) that any model backend answers:

- `saycan` (SayCan-style): the model scores every skill of the library (one usefulness score per candidate
  skill and argument); the loop weights each score by the executor's feasibility check (`check_skill`: 1 when
  the executor would accept it now, else 0) and runs the highest weighted one. The scores are recorded in the
  step (`ReasoningStep.scores`).
- `direct` (RT-2-style direct action): the image, the command and the current state in, the skill out; no
  preamble, no reasoning trace.
- `waypoint` (UAV-VLN-style): language to waypoints, each waypoint one motion primitive of the library; no
  perception or manipulation skill is offered (`restrict_library`).
- `plan_once` (UAV-VLA-style): the model is asked once, at the first step, for the whole plan (a list of
  skills ending with `done`); the loop runs it step by step without asking again, and the first step that
  does not succeed ends the task failed with its reason.

This module holds what differs from the DRT/STE variants: preambles, Rules, the answer reading (scores and
plans) and the library restriction; their answer schemas are in schema.py (`baseline_schema`). The loop
(loop.py) does the weighting and the plan.
"""

from __future__ import annotations

import math
from typing import Any

from services.reasoner.library import policy_skills
from shared import skills as S  # noqa: N812
from shared.errors import InvalidAnswer
from shared.messages import BASELINES, SkillLibrary

MAX_PLAN_STEPS = 40
"""Longest plan the plan-once baseline takes (a pick-and-place with motions needs about ten)."""

PREAMBLES = {
    "saycan": (
        "You are the high-level planner of an aerial manipulator (a multirotor with a two-finger gripper and an "
        "RGB-D camera). At each step you receive the current camera image and this prompt and you rate how useful "
        "each skill of the Skill Library would be as the next step toward completing the command. The skill with "
        "the highest rating that the robot can execute now runs; its outcome is added to the History and you "
        "are asked again."
    ),
    "waypoint": (
        "You are the navigation policy of a multirotor with a forward-looking camera. At each step you receive "
        "the current camera image and this prompt and you give the next waypoint as ONE motion primitive of the "
        "Skill Library (a fixed body-frame step). Answer done when the vehicle is where the command asks."
    ),
    "plan_once": (
        "You are the mission planner of an aerial manipulator (a multirotor with a two-finger gripper and an "
        "RGB-D camera). You receive the current camera image and this prompt ONCE, at the start of the task, and "
        "you write the whole plan: the list of skills from the Skill Library to execute in order. The plan runs "
        "without asking you again; a step that fails ends the task. To pick an object: localize it with "
        "obj_localization, then grasp. To place it: localize the surface with placement_localization, then "
        "place. End the plan with done."
    ),
}


def restrict_library(variant: str, library: SkillLibrary) -> SkillLibrary:
    """The library the variant offers: the motion primitives and `done` for `waypoint`, all of it otherwise."""
    if variant != "waypoint":
        return library
    keep = [s for s in library.skills if not s.policy_visible or s.name in (*S.MOTION_PRIMITIVES, S.DONE)
            or s.category == "motion"]
    return library.model_copy(update={"skills": keep})


def _argument_rule(library: SkillLibrary) -> str:
    return ("argument is the object query for obj_localization (e.g. \"red cup\"), the surface query for "
            "placement_localization (e.g. \"table\"), optionally the object label for grasp, and null otherwise"
            if any(s.argument is not None for s in policy_skills(library)) else "argument is always null")


def rules_text(variant: str, library: SkillLibrary) -> str:
    """The Rules part of a baseline variant."""
    names = [s.name for s in policy_skills(library)]
    arg = _argument_rule(library)
    if variant == "saycan":
        return "\n".join([
            "Answer with exactly one JSON object and nothing else, in this format:",
            '{"scores": [{"skill": "<skill name>", "argument": "<string or null>", "score": <number 0 to 1>}, ...]}',
            f"- Rate EVERY skill at least once: {', '.join(names)}.",
            "- score is how useful executing that skill with that argument now is for the command (1: the right "
            "next step, 0: useless).",
            f"- {arg}. A skill may appear more than once with different arguments.",
        ])
    if variant == "direct":
        return "\n".join([
            "Answer with the skill only: exactly one JSON object {\"skill\": <skill name>, \"argument\": <string "
            "or null>} and nothing else (no explanation).",
            f"- skill must be one of: {', '.join(names)}.",
            f"- {arg}.",
        ])
    if variant == "waypoint":
        return "\n".join([
            "Answer with exactly one JSON object and nothing else: {\"ste\": {\"skill\": <motion primitive or "
            "done>, \"argument\": null}}: the next waypoint as one motion primitive.",
            f"- skill must be exactly one of: {', '.join(names)}.",
            "- Answer done when the vehicle is where the command asks.",
        ])
    if variant == "plan_once":
        return "\n".join([
            "Answer with exactly one JSON object and nothing else, in this format:",
            '{"plan": [{"skill": "<skill name>", "argument": "<string or null>"}, ...]}',
            f"- each skill must be one of: {', '.join(names)}; {arg}.",
            f"- The plan runs in order without re-planning; at most {MAX_PLAN_STEPS} steps; its last step is done.",
        ])
    raise ValueError(f"not a baseline variant: {variant!r}")


def is_baseline(variant: str) -> bool:
    return variant in BASELINES


def read_scores(obj: dict, check: Any) -> list[tuple[str, str | None, float]]:
    """(skill, argument, score) of a SayCan answer object, each candidate validated by `check(skill, argument)`
    (which returns the normalised (skill, argument) or raises InvalidAnswer). Raises InvalidAnswer with the
    reason."""
    raw = obj.get("scores")
    if isinstance(raw, dict):  # {"yaw_left": 0.1, ...} is a common shape: no arguments then
        raw = [{"skill": k, "argument": None, "score": v} for k, v in raw.items()]
    if not isinstance(raw, list) or not raw:
        raise InvalidAnswer("The answer needs \"scores\": a list of {\"skill\", \"argument\", \"score\"} objects, "
                            "one per skill.")
    out: list[tuple[str, str | None, float]] = []
    for item in raw[:200]:
        if not isinstance(item, dict):
            raise InvalidAnswer("Each entry of \"scores\" must be an object {\"skill\", \"argument\", \"score\"}.")
        score = item.get("score")
        if isinstance(score, bool) or not isinstance(score, (int, float)) or not math.isfinite(score):
            raise InvalidAnswer(f"The score of {str(item.get('skill'))[:40]!r} must be a number from 0 to 1.")
        skill, arg = check(item.get("skill"), item.get("argument"))
        out.append((skill, arg, min(1.0, max(0.0, float(score)))))
    return out


def read_plan(obj: dict, check: Any) -> list[tuple[str, str | None]]:
    """(skill, argument) steps of a plan-once answer object, validated by `check`; the last one is done."""
    raw = obj.get("plan")
    if not isinstance(raw, list) or not raw:
        raise InvalidAnswer("The answer needs \"plan\": a list of {\"skill\", \"argument\"} objects ending with done.")
    if len(raw) > MAX_PLAN_STEPS:
        raise InvalidAnswer(f"The plan has {len(raw)} steps, more than {MAX_PLAN_STEPS}; write a shorter plan.")
    steps = []
    for item in raw:
        if isinstance(item, str):
            item = {"skill": item, "argument": None}
        if not isinstance(item, dict):
            raise InvalidAnswer("Each step of \"plan\" must be an object {\"skill\", \"argument\"}.")
        steps.append(check(item.get("skill"), item.get("argument")))
    if steps[-1][0] != S.DONE:
        raise InvalidAnswer("The plan must end with done.")
    if any(s == S.DONE for s, _ in steps[:-1]):
        raise InvalidAnswer("done may only be the last step of the plan.")
    return steps
