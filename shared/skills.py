"""Spellings of the built-in skill names that code refers to (the loop's own takeoff and hold, the rules
baseline, the paper's metrics).

These are not the library: a skill is one module in `services/executor/skills/` with its name, argument,
preconditions and Skill Library description; the executor serves the library on `executor/skills`, and
the prompt, the validator and the rules baseline read it from there.
"""

from __future__ import annotations

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
