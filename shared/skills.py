"""Spellings of the built-in skill names that code refers to (the loop's own takeoff and hold, the rules
baseline, the paper's metrics).

These are not the library: a skill is one module in `services/executor/skills/` with its name, argument,
preconditions and Skill Library description; the executor serves the library on `executor/skills`, and
the prompt, the validator and the rules baseline read it from there.
"""

from __future__ import annotations

import json
import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from shared.messages import SkillLibrary

# Motion primitives (paper Table II): fixed body-frame steps.
YAW_LEFT = "yaw_left"
YAW_RIGHT = "yaw_right"
FORWARD = "forward"
BACKWARD = "backward"
LEFT = "left"
RIGHT = "right"
UP = "up"
DOWN = "down"
MOTION_PRIMITIVES = (YAW_LEFT, YAW_RIGHT, FORWARD, BACKWARD, LEFT, RIGHT, UP, DOWN)
# How each flies: the body-frame direction of a translation (x forward, y left, z up; times the step the Skill
# Library states) and the sense of a turn (+1 counter-clockwise). The executor flies them so; the reasoner's
# speculative step predicts where one ends from them.
STEP_AXES: dict[str, tuple[float, float, float]] = {
    FORWARD: (1.0, 0.0, 0.0), BACKWARD: (-1.0, 0.0, 0.0), LEFT: (0.0, 1.0, 0.0), RIGHT: (0.0, -1.0, 0.0),
    UP: (0.0, 0.0, 1.0), DOWN: (0.0, 0.0, -1.0)}
TURNS: dict[str, float] = {YAW_LEFT: 1.0, YAW_RIGHT: -1.0}


def motion_end(skill: str, x: float, y: float, z: float, yaw: float, step: float) -> tuple[float, float, float, float]:
    """Where the motion primitive `skill` ends from (x, y, z, yaw) (world ENU, m, yaw in rad): a turn (TURNS) turns
    by `step` degrees in place, a step (STEP_AXES) moves `step` metres along its body-frame axis; KeyError for any
    other skill. The yaw is not wrapped. The executor flies to it; the reasoner's speculative step predicts it."""
    if skill in TURNS:
        return x, y, z, yaw + TURNS[skill] * math.radians(step)
    fx, fy, fz = STEP_AXES[skill]
    c, s = math.cos(yaw), math.sin(yaw)
    return x + step * (c * fx - s * fy), y + step * (s * fx + c * fy), z + step * fz, yaw

# Perception-driven routines (paper Table III).
OBJ_LOCALIZATION = "obj_localization"  # argument: object query, e.g. "red cup"
GRASP = "grasp"  # argument: optional object label; uses the latest localization in working memory
PLACEMENT_LOCALIZATION = "placement_localization"  # argument: surface query, e.g. "table"
PLACE = "place"  # no argument; uses the latest placement estimate in working memory

# Policy control: the policy declares the task complete.
DONE = "done"

# Operator-only skills (not offered to the model).
TAKEOFF = "takeoff"
LAND = "land"
HOLD = "hold"
OPERATOR_SKILLS = (TAKEOFF, LAND, HOLD)

# Opposite motions, for the action redundancy ratio (oscillatory corrections).
OPPOSITE = {
    YAW_LEFT: YAW_RIGHT, YAW_RIGHT: YAW_LEFT, FORWARD: BACKWARD, BACKWARD: FORWARD,
    LEFT: RIGHT, RIGHT: LEFT, UP: DOWN, DOWN: UP,
}


# The built-in Skill Library, for offline tools with no executor to ask (`aermani vlm check`, re-reasoning a log
# that lacks its library, tests). The executor serves the live one on executor/skills; this file is the same
# library at default settings, written from the executor's registry by `python -m services.executor.registry
# --write`; the executor's tests fail when it is stale. Skills of AERMANI_EXECUTOR_SKILL_MODULES are not in it.
LIBRARY_FILE = "skill_library.json"


def builtin_library() -> SkillLibrary:
    """The Skill Library a default executor serves (its built-in skills at default settings)."""
    from importlib import resources

    from shared.messages import SkillLibrary, SkillSpec

    data = json.loads(resources.files("shared").joinpath(LIBRARY_FILE).read_text(encoding="utf-8"))
    return SkillLibrary(skills=tuple(SkillSpec.model_validate(s) for s in data["skills"]))


def library_json(library: SkillLibrary) -> str:
    """The file's text for `library`: its skills only (no stamps or versions), stable for diffs."""
    return json.dumps({"skills": [s.model_dump(mode="json") for s in library.skills]}, indent=1) + "\n"
