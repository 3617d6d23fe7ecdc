"""A speculative next step: while skill k flies, the model is asked for step k+1 on the observation that skill k's
predicted outcome implies; the answer is used only when skill k ended that way and the policy's inputs after it
agree with the assumed ones (issue 27).

What is predicted, and only for skills whose outcome follows from what is known before they run:
- a motion primitive (forward, yaw_left, ...) ends `succeeded` with the vehicle moved by the step the Skill
  Library states (`distance` in m, `angle` in deg) from where it was;
- `obj_localization(X)` of an X perception detects now ends `succeeded` with X's estimate at that detection's
  centroid, and X in working memory there.
Everything else (the detections, what is held, the other remembered objects) is assumed unchanged. A grasp, a
place, a placement localization or `done` is never speculated on: their outcomes are what the step is for.

The check after the skill ends compares what a policy reads (`PolicyContext`, the rules baseline's whole input and
the structured part of a VLM's prompt) between the assumed and the fresh observation, field by field: the last
step's outcome code and facts, the vehicle's pose, the labels detected and their distances, what is held and
remembered. Numbers agree within `Tolerance`; names must be equal. The image is not compared: the detections stand
in for it, as the issue asks ("same detections within a tolerance").
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, replace

from services.reasoner.backends.base import PastStep, PolicyContext, Seen
from services.reasoner.prompt import History, HistoryEntry, Observation
from shared import skills as S  # noqa: N812
from shared.messages import (
    MemoryObject,
    ObjectEstimate,
    OutcomeCode,
    Pose,
    SkillFacts,
    SkillLibrary,
    SkillOutcome,
    SkillToExecute,
    Vec3,
)


@dataclass(frozen=True)
class Tolerance:
    """How far the fresh observation may be from the assumed one for a speculative answer to stand."""

    position_m: float = 0.15
    """Vehicle position, each remembered object's position, an estimate's position."""
    yaw_deg: float = 10.0
    """Vehicle heading."""
    distance_m: float = 0.15
    """Each detection's distance from the vehicle."""
    remembered_m: float = 0.3
    """Each remembered thing's position in working memory: coarse detection centroids, which for a piece of
    furniture move with the part of it in view."""


@dataclass
class Assumed:
    """Step k's outcome as predicted, and the observation after it: what step k+1 is asked on."""

    entry: HistoryEntry
    obs: Observation
    history: History


def _param(library: SkillLibrary, skill: str, name: str) -> float | None:
    for spec in library.skills:
        if spec.name == skill:
            for p in spec.parameters:
                if p.name == name and isinstance(p.value, (int, float)) and not isinstance(p.value, bool):
                    return float(p.value)
    return None


def _moved(pose: Pose, skill: str, library: SkillLibrary) -> Pose | None:
    """Where the motion primitive `skill` ends from `pose`, by the step its library entry states (as the executor
    flies it: shared.skills.motion_end)."""
    turn = skill in S.TURNS
    step = _param(library, skill, "angle" if turn else "distance")
    if step is None or not (turn or skill in S.STEP_AXES):
        return None
    p = pose.position
    x, y, z, yaw = S.motion_end(skill, p.x, p.y, p.z, pose.yaw, step)
    if turn:
        return Pose(position=p, yaw=math.remainder(yaw, 2 * math.pi))
    return Pose(position=Vec3(x=x, y=y, z=z), yaw=yaw)


def assume(history: History, obs: Observation, library: SkillLibrary, ste: SkillToExecute, step: int,
           prediction: str, summary: str, reasoning: str) -> Assumed | None:
    """Step `step` (skill `ste`) ended as predicted: its History entry and the observation after it; None for a
    skill whose outcome cannot be predicted from what is known now (see the module's docstring)."""
    state = obs.state
    if state is None:
        return None
    here = Pose(position=state.position, yaw=state.yaw)
    held = obs.memory.held_object if obs.memory is not None else None
    memory = obs.memory
    estimate: ObjectEstimate | None = None
    if ste.skill in S.TURNS or ste.skill in S.STEP_AXES:
        there = _moved(here, ste.skill, library)
        if there is None:
            return None
        state = state.model_copy(update={"position": there.position, "yaw": there.yaw})
    elif ste.skill == S.OBJ_LOCALIZATION and ste.argument:
        seen = [d for d in obs.detections if d.label == ste.argument and d.centroid is not None]
        if len(seen) != 1 or seen[0].centroid is None:
            return None  # not detected (or not one of it): the localization's outcome is the question
        where = seen[0].centroid
        there = here
        estimate = ObjectEstimate(query=ste.argument, found=True, label=ste.argument, pose=Pose(position=where),
                                  size=seen[0].size)
        if memory is not None:
            kept = tuple(o for o in memory.objects if o.label != ste.argument)
            memory = memory.model_copy(update={"objects": (*kept, MemoryObject(
                label=ste.argument, query=ste.argument, position=where, size=seen[0].size))})
    else:
        return None
    # The facts the executor reports with such a success: a localization names its target.
    target = ste.argument if ste.skill == S.OBJ_LOCALIZATION else None
    outcome = SkillOutcome(code=OutcomeCode.SUCCEEDED, facts=SkillFacts(holding=held, target=target), start_pose=here,
                           end_pose=there, held_object=held, estimate=estimate)
    entry = HistoryEntry(step, ste.skill, ste.argument, "succeeded", f"(predicted) {prediction}".strip(), "",
                         summary, reasoning, outcome, prediction=prediction)
    after = replace(obs, state=state, memory=memory, frame_wait_s=0.0, detections_wait_s=0.0, state_wait_s=0.0)
    return Assumed(entry, after, history.extended(entry))


def _close(a: float | None, b: float | None, tol: float) -> bool:
    return (a is None) == (b is None) and (a is None or b is None or abs(a - b) <= tol)


def _close_xyz(a: tuple[float, ...] | None, b: tuple[float, ...] | None, tol: float) -> bool:
    return (a is None) == (b is None) and (a is None or b is None or math.dist(a[:3], b[:3]) <= tol)


def _pose_problem(a: tuple[float, float, float] | None, b: tuple[float, float, float] | None,
                  tol: Tolerance, what: str) -> str | None:
    if (a is None) != (b is None):
        return f"{what}: known in one, not in the other"
    if a is None or b is None:
        return None
    off = math.dist(a[:2], b[:2])
    turn = abs(math.degrees(math.remainder(a[2] - b[2], 2 * math.pi)))
    if off > tol.position_m or turn > tol.yaw_deg:
        return f"{what} {off:.2f} m / {turn:.0f} deg from the assumed one"
    return None


def _step_problem(a: PastStep, b: PastStep, tol: Tolerance) -> str | None:
    if (a.skill, a.argument, a.state, a.code) != (b.skill, b.argument, b.state, b.code):
        return f"{b.skill} ended {b.code}, not {a.code}"
    if (a.facts.holding, a.facts.target) != (b.facts.holding, b.facts.target):
        return (f"{b.skill} ended holding {b.facts.holding} with target {b.facts.target}, not holding "
                f"{a.facts.holding} with target {a.facts.target}")
    problem = _pose_problem(a.pose, b.pose, tol, f"{b.skill}'s end pose")
    if problem:
        return problem
    if not _close_xyz(a.found_at, b.found_at, tol.position_m) or not _close(a.surface_z, b.surface_z,
                                                                            tol.position_m):
        return f"{b.skill}'s estimate is not where the detection was"
    return None


def _seen_problem(a: list[Seen], b: list[Seen], tol: Tolerance) -> str | None:
    if Counter((s.label, s.category) for s in a) != Counter((s.label, s.category) for s in b):
        gone = sorted({s.label for s in a} ^ {s.label for s in b})
        return f"detections differ ({', '.join(gone) or 'their counts'})"
    def key(s: Seen) -> tuple[str, str, float]:
        return s.label, s.category, s.distance if s.distance is not None else -1.0
    for x, y in zip(sorted(a, key=key), sorted(b, key=key), strict=True):
        if not _close(x.distance, y.distance, tol.distance_m):
            return f"the {y.label} is {y.distance} m away, not {x.distance} m"
    return None


def height_problem(assumed_z: float | None, fresh: Observation, tol: Tolerance = Tolerance()) -> str | None:
    """The vehicle's height against the assumed one (an `up` or `down` that did not climb as far): the prompt
    shows it, and PolicyContext's pose has none."""
    z = fresh.state.position.z if fresh.state is not None else None
    if (assumed_z is None) != (z is None):
        return "the vehicle's height is known in one, not in the other"
    if assumed_z is not None and z is not None and abs(z - assumed_z) > tol.position_m:
        return f"the vehicle is at {z:.2f} m, not {assumed_z:.2f} m"
    return None


def disagreement(assumed: PolicyContext, fresh: PolicyContext, tol: Tolerance = Tolerance()) -> str | None:
    """None when a policy reads the same from both (within `tol`); else what differs, for the log."""
    if len(assumed.steps) != len(fresh.steps) or not fresh.steps:
        return "the History differs in length"
    problem = _step_problem(assumed.steps[-1], fresh.steps[-1], tol)
    if problem:
        return problem
    if assumed.held != fresh.held:
        return f"holding {fresh.held}, not {assumed.held}"
    problem = _pose_problem(assumed.pose, fresh.pose, tol, "the vehicle")
    if problem:
        return problem
    problem = _seen_problem(assumed.visible, fresh.visible, tol)
    if problem:
        return problem
    if set(assumed.known_objects) != set(fresh.known_objects) or \
            set(assumed.known_placements) != set(fresh.known_placements):
        return "working memory holds other objects or placements"
    if assumed.positions.keys() != fresh.positions.keys():
        return "other things are remembered"
    for label, (x, y) in fresh.positions.items():
        if math.dist((x, y), assumed.positions[label]) > tol.remembered_m:
            return f"the {label} is remembered elsewhere"
    return None
