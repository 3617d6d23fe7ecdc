"""Each task scored for what it asks, beyond the judge's pick and place (docs/evaluation.md, "Scoring what a task
asks"): the motions a sequential command asks for, checked from the recorded trajectory; the object a size
comparison or a conditional names, decided by the simulator from the world at the start; and whether the policy
had seen what decides it before it picked (a success on a guess is flagged).

Pure functions of a task, the episode's recorded steps and the simulator's ground truth (`JudgeResult` of op
`world`), so a report rebuilt from episodes.jsonl says the same.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict

from aermani.evaluation.records import ChoiceOutcome
from aermani.evaluation.runs import observation_from_prompt
from aermani.evaluation.tasks import ConditionalChoice, EvalTask, ExpectedMotion, SizeChoice
from shared.messages import JudgeResult, Pose, ReasoningStep, SimObjectTruth
from shared.skills import GRASP, MOTION_PRIMITIVES, OBJ_LOCALIZATION, PLACEMENT_LOCALIZATION

# A motion primitive counts as done in a direction when the vehicle moved at least half a default step that way
# (the executor's steps: 0.5 m horizontally, 0.3 m vertically, 45 deg of yaw; tests/evaluation/test_scoring.py
# keeps these at half of its settings): drift and a short step still count, a motion that did not happen does not.
MIN_HORIZONTAL_M = 0.25
MIN_VERTICAL_M = 0.15
MIN_YAW_RAD = math.radians(22.5)
APPROACH_M = 1.5
"""An approach has arrived when the vehicle came this close (horizontally) to the footprint of what it goes to: the
distance the rules baseline's approach ends at, from what it saw of the thing."""
TIE = 0.05
"""Sizes within 5 % of the extreme are a tie: either object meets the criterion."""


# --------------------------------------------------------------------------- motions


@dataclass(frozen=True)
class Move:
    """One executed motion primitive and what the vehicle did, in the body frame of its start pose."""

    index: int
    """Its position among the episode's steps."""
    step: int
    skill: str
    directions: frozenset[str]
    """The motion primitives' directions it achieved (forward, up, yaw_left, ...)."""
    text: str


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def achieved(start: Pose, end: Pose) -> tuple[frozenset[str], str]:
    """The directions a move from `start` to `end` went (body frame of `start`), and the numbers."""
    dx, dy, dz = (end.position.x - start.position.x, end.position.y - start.position.y,
                  end.position.z - start.position.z)
    c, s = math.cos(start.yaw), math.sin(start.yaw)
    fwd, lat, dyaw = dx * c + dy * s, -dx * s + dy * c, _wrap(end.yaw - start.yaw)
    out = set()
    for value, limit, plus, minus in ((fwd, MIN_HORIZONTAL_M, "forward", "backward"),
                                      (lat, MIN_HORIZONTAL_M, "left", "right"),
                                      (dz, MIN_VERTICAL_M, "up", "down"),
                                      (dyaw, MIN_YAW_RAD, "yaw_left", "yaw_right")):
        if value >= limit:
            out.add(plus)
        elif value <= -limit:
            out.add(minus)
    text = f"forward {fwd:+.2f} m, left {lat:+.2f} m, up {dz:+.2f} m, yaw {math.degrees(dyaw):+.0f} deg"
    return frozenset(out), text


def moves_of(steps: Sequence[ReasoningStep]) -> list[Move]:
    """The episode's motion primitives that have both poses, with what each achieved."""
    out = []
    for i, s in enumerate(steps):
        o = s.outcome
        if s.ste is None or s.ste.skill not in MOTION_PRIMITIVES or o is None:
            continue
        if o.start_pose is None or o.end_pose is None:
            continue
        dirs, text = achieved(o.start_pose, o.end_pose)
        out.append(Move(i, s.step, s.ste.skill, dirs, text))
    return out


def pick_index(steps: Sequence[ReasoningStep]) -> int:
    """The index of the first grasp that succeeded (the pick), or len(steps) when none did."""
    return next((i for i, s in enumerate(steps) if s.ste is not None and s.ste.skill == GRASP
                 and s.skill_state is not None and s.skill_state.value == "succeeded"), len(steps))


def footprint_distance(x: float, y: float, thing: SimObjectTruth) -> float:
    """Horizontal distance from (x, y) to a thing's footprint (its true box, turned by its yaw); 0 inside."""
    c, s = math.cos(thing.yaw), math.sin(thing.yaw)
    dx, dy = x - thing.position.x, y - thing.position.y
    u, v = abs(dx * c + dy * s) - thing.size.x / 2, abs(-dx * s + dy * c) - thing.size.y / 2
    return math.hypot(max(u, 0.0), max(v, 0.0))


def _poses(steps: Sequence[ReasoningStep], after: int, stop: int) -> list[tuple[int, Pose]]:
    """The vehicle's recorded poses from the end of step index `after` (-1: from the start) to the pick, each with
    the index of the last step that had ended when it was taken (a start pose: the step before)."""
    out = []
    for i in range(max(after, 0), stop):
        o = steps[i].outcome
        if o is None:
            continue
        if o.start_pose is not None and i > after:
            out.append((i - 1, o.start_pose))
        if o.end_pose is not None:
            out.append((i, o.end_pose))
    return out


class MotionCheck(BaseModel):
    """Whether the commanded motions happened, and how each was found (or not)."""

    model_config = ConfigDict(frozen=True)

    ok: bool
    detail: str


def _match_moves(want: ExpectedMotion, moves: list[Move], after: int, stop: int) -> tuple[int, str] | None:
    """The index of the step that completes `want` (its `times` moves in order, after step index `after`, before
    `stop`), and how; a `turn` is taken left or right, whichever completes first."""
    options = ["yaw_left", "yaw_right"] if want.skill == "turn" else [want.skill]
    best: tuple[int, str] | None = None
    for d in options:
        found = [m for m in moves if after < m.index < stop and d in m.directions][:want.times]
        if len(found) == want.times and (best is None or found[-1].index < best[0]):
            best = (found[-1].index, f"{want.text()}: " + "; ".join(f"step {m.step} {m.skill} ({m.text})"
                                                                   for m in found))
    return best


def check_motions(motions: Sequence[ExpectedMotion], steps: Sequence[ReasoningStep],
                  world: JudgeResult | None) -> MotionCheck:
    """Whether each expected motion happened, in order, before the pick (the first grasp that succeeded): a
    primitive's direction from the vehicle's displacement over a motion step (at least half a step that way), an
    approach from the vehicle's poses coming within APPROACH_M of the thing's true footprint."""
    moves, stop = moves_of(steps), pick_index(steps)
    after, found = -1, []
    for want in motions:
        if want.skill == "approach":
            thing = next((o for o in (world.objects if world else ()) if o.name == want.to), None)
            if thing is None:
                return MotionCheck(ok=False, detail=f"{want.text()}: cannot be checked: the simulator's world has "
                                                    f"no {want.to}" + ("" if world else " (no world recorded)"))
            near = [(i, footprint_distance(p.position.x, p.position.y, thing)) for i, p in _poses(steps, after, stop)]
            hit = next(((i, d) for i, d in near if d <= APPROACH_M), None)
            if hit is None:
                closest = min((d for _, d in near), default=math.inf)
                return MotionCheck(ok=False, detail=f"{want.text()} never happened before the pick: the vehicle came "
                                                    f"within {closest:.2f} m of it at best (needs {APPROACH_M} m)")
            after = max(after, hit[0])
            when = f"after step {steps[hit[0]].step}" if hit[0] >= 0 else "at the start"
            found.append(f"{want.text()}: within {hit[1]:.2f} m {when}")
            continue
        got = _match_moves(want, moves, after, stop)
        if got is None:
            done = [m for m in moves if after < m.index < stop]
            return MotionCheck(ok=False, detail=(
                f"{want.text()} never happened before the pick"
                + (f" (after {found[-1].split(':')[0]})" if found else "") + ": "
                + ("; ".join(f"step {m.step} {m.skill} ({m.text})" for m in done[:6]) if done
                   else "no motion step with poses in that stretch")))
        after = got[0]
        found.append(got[1])
    return MotionCheck(ok=True, detail="; ".join(found) or "no motion asked")


# --------------------------------------------------------------------------- choices


def decide(choice: SizeChoice | ConditionalChoice, world: JudgeResult) -> tuple[tuple[str, ...], str]:
    """The object(s) meeting the choice in `world` (the simulator's truth at the start), and why."""
    things = {o.name: o for o in world.objects}
    if isinstance(choice, SizeChoice):
        present = [things[n] for n in choice.among if n in things]
        if not present:
            return (), f"none of {', '.join(choice.among)} is in the world"
        height = choice.select in ("tallest", "shortest")

        def measure(o: SimObjectTruth) -> float:
            return o.size.z if height else o.size.x * o.size.y * o.size.z

        best = (max if choice.select in ("largest", "tallest") else min)(present, key=measure)
        answer = tuple(o.name for o in present if abs(measure(o) - measure(best)) <= TIE * measure(best))
        unit = "m" if height else "L"
        scale = 1.0 if height else 1000.0
        sizes = ", ".join(f"{o.name} {measure(o) * scale:.2f} {unit}" for o in present)
        what = "height" if height else "volume"
        return answer, f"true {what}s: {sizes}" + (" (a tie within 5 %)" if len(answer) > 1 else "")
    obj = things.get(choice.if_present)
    holds = obj is not None and (choice.on is None or obj.support == choice.on)
    if obj is None:
        why = f"no {choice.if_present} in the world"
    else:
        why = f"the {choice.if_present} rests on the {obj.support or 'floor'}"
    return ((choice.then,) if holds else (choice.otherwise,)), why + (": the condition holds" if holds
                                                                      else ": the condition does not hold")


def _norm(text: str) -> str:
    words = text.lower().split()
    return " ".join(words[1:] if words and words[0] in ("the", "a", "an") else words)


def _same(label: str, name: str) -> bool:
    """A perception label (or a localized query) names the simulator's object: the same words, an article aside
    ("table" is not the "round table")."""
    return _norm(label) == _norm(name)


def seen_before_pick(steps: Sequence[ReasoningStep], names: Sequence[str]) -> tuple[set[str], bool]:
    """Which of `names` the policy had seen before its pick (in the detections or working memory its prompts
    showed, or localized by a skill that succeeded), and whether the steps could tell at all."""
    stop = pick_index(steps)
    seen: set[str] = set()
    could_tell = False
    prev: ReasoningStep | None = None
    for s in list(steps)[:stop + 1]:  # the pick's own prompt shows what it was decided on
        history = s.prompt.get("history")
        obs = observation_from_prompt(history, prev) if history else None
        if obs is not None:
            could_tell = True
            labels = [d.label for d in obs.detections or ()] + [p[0] for p in obs.positions]
            seen |= {n for n in names if any(_same(lb, n) for lb in labels)}
        prev = s
    for s in list(steps)[:stop]:
        if (s.ste is not None and s.ste.skill in (OBJ_LOCALIZATION, PLACEMENT_LOCALIZATION) and s.ste.argument
                and s.skill_state is not None and s.skill_state.value == "succeeded"):
            could_tell = True
            label = (s.outcome.facts.target if s.outcome is not None and s.outcome.facts.target else "") or ""
            seen |= {n for n in names if _same(s.ste.argument, n) or (label and _same(label, n))}
    return seen, could_tell


def chosen_object(steps: Sequence[ReasoningStep], held: str | None) -> str | None:
    """What the policy picked: the object of the last grasp that succeeded, else what the gripper holds."""
    for s in reversed(list(steps)):
        if (s.ste is not None and s.ste.skill == GRASP and s.skill_state is not None
                and s.skill_state.value == "succeeded"):
            o = s.outcome
            return (o.held_object if o is not None and o.held_object else None) or s.ste.argument or held
    return held


def score_choice(choice: SizeChoice | ConditionalChoice, world: JudgeResult, steps: Sequence[ReasoningStep],
                 held: str | None) -> ChoiceOutcome:
    """The simulator's decision for this episode, the object chosen and whether it was chosen on what was seen."""
    answer, reason = decide(choice, world)
    if isinstance(choice, SizeChoice):
        needed = [n for n in choice.among if any(o.name == n for o in world.objects)]
    else:
        needed = [choice.on] if choice.on else [choice.if_present if answer == (choice.then,) else choice.otherwise]
    seen, could_tell = seen_before_pick(steps, needed)
    informed = (set(needed) <= seen) if could_tell or seen else None
    return ChoiceOutcome(criterion=choice.text(), answer=answer, reason=reason, chosen=chosen_object(steps, held),
                         informed=informed, needed=tuple(needed), seen=tuple(sorted(seen)))


# --------------------------------------------------------------------------- an episode


def accepted_objects(task: EvalTask, world: JudgeResult | None) -> tuple[tuple[str, ...], str]:
    """The objects the judge accepts for `task` in this world: the choice's answer when the task has one (decided
    from the world at the start), else the task's own; and, when they cannot be decided, why (empty tuple)."""
    if task.choice is None:
        return task.accepted, ""
    if world is None:
        return (), "the simulator's world could not be read at the start, so the choice cannot be decided"
    answer, reason = decide(task.choice, world)
    return answer, "" if answer else f"the choice cannot be decided in this layout: {reason}"


def score_episode(task: EvalTask, steps: Sequence[ReasoningStep], world: JudgeResult | None, held: str | None,
                  success: bool, verdict: str) -> tuple[bool, str, dict[str, Any]]:
    """The task's own scoring on top of the judge's verdict: (success, verdict, record fields). Motions that did
    not happen make a success a failure; a choice's decision and how it was chosen are recorded, a success on
    a guess said in the verdict (the judge already accepted only the choice's answer)."""
    fields: dict[str, Any] = {}
    if task.motions:
        mc = check_motions(task.motions, steps, world)
        fields.update(motions_ok=mc.ok, motions_detail=mc.detail)
        if success and not mc.ok:
            success, verdict = False, f"{verdict}; but the commanded motions did not happen: {mc.detail}"
    if task.choice is not None and world is not None:
        outcome = score_choice(task.choice, world, steps, held)
        fields["choice"] = outcome
        if success and outcome.informed is False:
            unseen = " and the ".join(n for n in outcome.needed if n not in outcome.seen)
            verdict = f"{verdict}; a success on a guess: the {outcome.chosen} was picked before the {unseen} was seen"
    return success, verdict, fields

