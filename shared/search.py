"""How far a search of the room goes before its object counts as not there: one definition for the rules
baseline's exploration (services/reasoner/backends/rules.py) and the evaluation's bound on a not-found task
(aermani/evaluation/tasks.py, `"expect": "not_found"`), so the policy's budget and the bound cannot disagree.

The coverage: a scan in place where the search began (SCAN_TURNS yaw steps of 45 deg, the whole circle), then a
flight to each of VIEWPOINTS viewpoints EXPLORE_RADIUS_M ahead, left, behind and right of that start (at most
TRANSIT_LIMIT motion steps each: the 2.8 m between two neighbouring viewpoints is 6 steps of 0.5 m and up to 3
turns) and a scan there; after each scan but the last, one direct look (a localization on a fresh frame). With
the camera's 4 m of useful depth, viewpoints 2 m around a start inside the 8 m x 8 m room see all of it.
"""

from __future__ import annotations

SCAN_TURNS = 7
"""Yaw steps of one scan: 8 headings 45 deg apart, the whole circle."""
VIEWPOINTS = 4
"""Viewpoints of the exploration around where the search began: ahead, left, behind, right."""
EXPLORE_RADIUS_M = 2.0
"""Their distance from where the search began, metres."""
TRANSIT_LIMIT = 9
"""Motion steps toward one viewpoint before scanning from wherever the vehicle got to."""
FIRST_LOOK = 1
"""The direct look that opens a search (perception's list lags at take-off)."""

SEARCH_STEPS = (FIRST_LOOK + (VIEWPOINTS + 1) * SCAN_TURNS + VIEWPOINTS * TRANSIT_LIMIT + VIEWPOINTS)
"""Reasoning steps of a whole search of the room, the first look to the last scan (76): the rules baseline says
"not found" when it has covered them (or spent them), and a not-found task allows them."""
NOT_FOUND_MAX_STEPS = SEARCH_STEPS + 1 + 3
"""The default bound on a not-found task's reasoning steps (80): the whole search, the `done` that says not found,
and 3 steps of slack (a detour toward a misdetection seen earlier). A line whose command asks for motions first
raises its own `not_found_max_steps` by them. The reasoner's default step cap (`max_steps`, 80) is not below it
(tests/evaluation/test_tasks.py), so the cap never ends such a task first."""
