"""`rules`: the deterministic non-VLM baseline policy, answering in the same DRT/STE JSON as a VLM.

It reads the same context the prompt is built from (command, history, working memory, perception's
detections, the vehicle pose), never the pixels nor the simulator, and re-derives its plan from that
context at every step, so it is stateless. What happened at each step it learns from the step's outcome
code, facts and measured poses, never from the executor's message (rewording a message changes nothing).
The command is read by `rules_parse`
(synonyms, polite and indirect requests, relative clauses, counts and amounts of motion, conditionals,
negated distractors, size comparisons, categories); a command it cannot understand is refused before
takeoff (`RulesBackend.refusal`). Then:

- the command's motions first, in order ("approach the counter" flies there);
- the target: named, chosen by a conditional, by measured size, or as the nearest member of a category,
  never an excluded one; localize, grasp, then the destination: localize a spot, place;
- not in view: look toward where it was seen earlier, else explore (scan in place, then fly to viewpoints
  around where the search began and scan there); after covering them, `done` with a "not found" failure.

Without a destination ("pick up the tissue box", "bring it here", "bring me a snack") the task ends
with `done` after a successful grasp, holding the object: "here" is where the operator is, and the
operator takes it from the hovering vehicle (a landing with a held object is the operator's call).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field

from services.reasoner.backends.base import (
    Backend,
    ModelReply,
    ModelRequest,
    PastStep,
    PolicyContext,
    Seen,
    register,
)
from services.reasoner.backends.rules_parse import (
    APPROACH,
    CATEGORY_WORDS,
    SIZE_WORDS,
    SNACKS,
    Plan,
    parse_command,
    singular,
)
from services.reasoner.drt import DRT_FIELDS
from shared import skills as S  # noqa: N812 - reads like the paper tables
from shared.messages import BASELINES, OutcomeCode
from shared.search import EXPLORE_RADIUS_M, SCAN_TURNS, SEARCH_STEPS, TRANSIT_LIMIT

__all__ = ["CATEGORY_WORDS", "SNACKS", "Plan", "RulesBackend", "RulesPolicy", "parse_command", "render_answer"]

SEEN_FOV_HALF_DEG = 30  # a remembered thing within this of the heading is in view (camera: +-42 deg)
SCAN_LIMIT = 8  # consecutive yaw steps (one full turn at 45 deg) before trying something else
APPROACH_RADIUS = 1.5  # "approach the counter" ends within this horizontal distance of what was seen of it
# Turn first when further off the heading than this (> half the 45 deg yaw step, or it oscillates).
APPROACH_FACING_DEG = 30
APPROACH_LIMIT = 12  # motion steps an "approach" may take before the policy decides from where it is
SURFACE_RETRY_RADIUS = 2.0  # after a failed placement_localization, fly this close to the surface first
ON_SURFACE_XY = 0.35  # a released object this close to its placement spot (and at its height) rests there
EXPLORE_RADIUS = EXPLORE_RADIUS_M  # viewpoints of the exploration: this far from where the search began
EXPLORE_ARRIVED = 0.6  # a viewpoint counts as reached (or visited earlier) within this horizontal distance
# Steps of one search (since it began) after which the thing is reported not found: the whole coverage
# (shared/search.py), the same number the evaluation's not-found tasks are bounded by.
EXPLORE_BUDGET = SEARCH_STEPS
_MOTION_SKILLS = (S.YAW_LEFT, S.YAW_RIGHT, S.FORWARD, S.BACKWARD, S.LEFT, S.RIGHT, S.UP, S.DOWN)
_APPROACH = APPROACH  # motion token: fly to the named thing, as many steps as it takes
DEFAULT_REACH = 1.0  # an out_of_reach refusal that does not say its reach (an older log): assume this, metres
# A place that reported one of these let the object go: succeeded, or released but not at rest on the spot.
_RELEASED = (OutcomeCode.SUCCEEDED, OutcomeCode.UNSTABLE)
NOT_FOUND = "not found"
"""Start of the failure reason when the room was explored without finding the target (or destination)."""
FALLEN = "fallen over"
"""Start of the failure reason when place left the object fallen over (no skill stands it up again)."""
FAILURES = (NOT_FOUND, FALLEN)  # a `done` whose reasoning starts so ends the task failed
_singular = singular


@dataclass
class Decision:
    """One decision of the policy: the skill, its argument, why; `failure` set when a `done` ends the task as
    failed (the command was not understood, or the target was not found after exploring the room)."""

    skill: str
    argument: str | None
    reasoning: str
    failure: str | None = None


def _matches(label: str, query: str) -> bool:
    label, query = label.lower(), query.lower()
    if label == query or query in label or label in query:
        return True
    words = [_singular(w) for w in query.split() if w not in ("the", "a", "an")]
    lwords = {_singular(w) for w in label.split()}
    return bool(words) and all(w in lwords for w in words)


def _excluded(label: str, plan: Plan) -> bool:
    for ex in plan.excluded:
        words = CATEGORY_WORDS.get(ex, (ex,))
        if any(w in label.lower() for w in words):
            return True
    return False


class RulesPolicy:
    """Decides the next skill from a PolicyContext. Pure: the same context gives the same answer."""

    def decide(self, ctx: PolicyContext) -> tuple[str, str | None, str]:
        """(skill, argument, reasoning)."""
        d = self.decide_full(ctx)
        return d.skill, d.argument, d.reasoning

    def decide_full(self, ctx: PolicyContext) -> Decision:
        """The decision with its failure verdict: a `done` that ends the task as failed carries the reason."""
        plan = parse_command(ctx.command, ctx.skills)
        if not plan.understood:
            return Decision(S.DONE, None, f"I cannot carry out this command: {plan.reason}.",
                            failure=f"refused: {plan.reason}")
        skill, arg, why = self._decide(ctx, plan)
        if plan.note and all(s.skill in S.OPERATOR_SKILLS for s in ctx.steps):
            why = f"{plan.note} {why}"  # the first step says how an unsure reading was made (issue 33)
        failure = why if skill == S.DONE and why.startswith(FAILURES) else None
        return Decision(skill, arg, why, failure)

    def _decide(self, ctx: PolicyContext, plan: Plan) -> tuple[str, str | None, str]:
        steps = ctx.steps
        # 1. The motions the command spells out, in order (a motion that fails twice is skipped).
        first_free, pending = self._motions_left(ctx, plan, steps)
        if pending is not None:
            return pending
        rest = steps[first_free:]
        if any(s.skill == S.PLACE and s.state == "succeeded" for s in rest):
            return S.DONE, None, "The object has been placed on the destination: the command is complete."
        holding = ctx.held
        if holding is None:
            # Working memory may lag the last step (it is read without waiting for a newer copy): a grasp that
            # succeeded since the last release means holding. A place refused while the executor's own facts
            # said it held nothing is newer than that and settles it.
            for s in reversed(rest):
                if _released(s) or (s.skill == S.PLACE and (s.code == OutcomeCode.SLIPPED or (
                        s.state == "rejected" and s.facts.holding is None))):
                    break  # (slipped: it left the fingers on place's way down, so nothing is held)
                if s.skill == S.GRASP and s.state == "succeeded":
                    holding = "object"
                    break
        if not holding:
            after = self._after_release(ctx, plan, rest)
            if after is not None:
                return after
            return self._pick(ctx, plan, rest)
        if plan.destination is None:
            return S.DONE, None, (f"Holding the {holding} and the command names no destination: the task ends "
                                  "with the object held for the operator.")
        return self._place(ctx, plan, rest, holding)

    def _motions_left(self, ctx: PolicyContext, plan: Plan,
                      steps: list[PastStep]) -> tuple[int, tuple[str, str | None, str] | None]:
        """Replays the history against the command's motions: (index of the first step after them, the next
        motion to run or None when they are all done)."""
        i, k, fails, approach_steps = 0, 0, 0, 0
        motions = plan.motions
        while k < len(motions):
            m = motions[k]
            if i < len(steps) and steps[i].skill in S.OPERATOR_SKILLS:
                i += 1  # takeoff and the like are the operator's, not the command's motions
                continue
            if m.startswith(_APPROACH):
                what = m[len(_APPROACH):]
                if i < len(steps) and steps[i].skill in _MOTION_SKILLS and approach_steps < APPROACH_LIMIT:
                    # A past approach step: it ended the approach when it reported a pose close enough.
                    pose = steps[i].pose
                    i, approach_steps = i + 1, approach_steps + 1
                    if pose is not None and self._approach_to(ctx, what, approach_steps, pose, steps[:i]) is None:
                        k, approach_steps = k + 1, 0
                    continue
                if i >= len(steps):
                    nxt = self._approach_to(ctx, what, approach_steps, ctx.pose, steps)
                    if nxt is not None:
                        return i, nxt
                k, approach_steps = k + 1, 0  # arrived, gave up, or the policy moved on to other skills
                continue
            if i >= len(steps):
                return i, (m, None, f"The command asks for these motions first: {', '.join(motions)}; "
                                    f"{k} done, so next is {m}.")
            s = steps[i]
            i += 1
            if s.skill == m:
                if s.state == "succeeded":
                    k, fails = k + 1, 0
                else:
                    fails += 1
                    if fails >= 2:
                        k, fails = k + 1, 0
        return i, None

    def _approach_to(self, ctx: PolicyContext, what: str, taken: int, pose: tuple[float, float, float] | None,
                     done: list[PastStep], exact: bool = False,
                     radius: float = APPROACH_RADIUS) -> tuple[str, str | None, str] | None:
        """The next step of "approach the <what>" from `pose`: turn toward it, fly closer until within
        `radius`; None when there (or when it cannot get closer)."""
        if taken >= APPROACH_LIMIT:
            return None
        blocked = 0
        for s in reversed(done[len(done) - taken:] if taken else []):
            if s.skill != S.FORWARD or s.state == "succeeded":
                break
            blocked += 1
        if blocked >= 2:
            return None  # the way is blocked (once may be a stale depth image right after take-off): decide here

        def same(name: str) -> bool:  # surfaces need the exact name: "table" is not the "round table"
            return name.lower() == what.lower() if exact else _matches(name, what)

        pos = next((xy for name, xy in ctx.positions.items() if same(name)), None)
        if pos is None or pose is None:
            near = next((v for v in ctx.visible if same(v.label)), None)
            if near is not None:
                # In view but not placed in the world (no pose or memory): judge by its reported distance, or
                # take one step toward it when even that is unknown.
                if near.distance is not None:
                    return None if near.distance <= radius else (
                        S.FORWARD, None, f"Approach the {what}: it is {near.distance:.1f} m away, fly closer.")
                return (S.FORWARD, None, f"Approach the {what}: it is in view, fly closer.") if taken == 0 else None
            if taken < SCAN_LIMIT:
                return S.YAW_LEFT, None, f"Approach the {what}: I have not seen it yet, so turn to look for it."
            return None
        x, y, yaw = pose
        dist = math.hypot(pos[0] - x, pos[1] - y)
        if dist <= radius:
            return None
        bearing = math.atan2(pos[1] - y, pos[0] - x) - yaw
        bearing = math.atan2(math.sin(bearing), math.cos(bearing))
        if abs(bearing) > math.radians(APPROACH_FACING_DEG):
            turn = S.YAW_LEFT if bearing > 0 else S.YAW_RIGHT
            return turn, None, (f"Approach the {what}: it is {dist:.1f} m away at {math.degrees(bearing):.0f} deg "
                                "from my heading, turn toward it.")
        return S.FORWARD, None, f"Approach the {what}: it is {dist:.1f} m ahead, fly closer (until {radius} m)."

    def _after_release(self, ctx: PolicyContext, plan: Plan,
                       rest: list[PastStep]) -> tuple[str, str | None, str] | None:
        """`place` let the object go but reported failure (not seen afterwards, or off the spot): look where it
        is. On the destination is done; anywhere else it is picked up again (the normal pick phase). Fallen over
        (the place's facts say so) ends the task failed."""
        idx = next((i for i in range(len(rest) - 1, -1, -1) if _released(rest[i])), None)
        if idx is None or not plan.destination:
            return None
        place = rest[idx]
        if place.code == OutcomeCode.UNSTABLE and place.facts.upright is False:
            # It lies where it fell: picked up again it would hang and be set down the same way, and this
            # gripper has no skill that stands an object up.
            what = place.facts.target or plan.destination
            return S.DONE, None, (f"{FALLEN}: the released object lies on its side (place reports it fallen over, "
                                  f"near the {what}); no skill of mine can stand it up again, so the command "
                                  "cannot be completed.")
        spot = next((s for s in reversed(rest[:idx]) if s.skill == S.PLACEMENT_LOCALIZATION
                     and s.state == "succeeded"), None)
        grasped = next((s for s in reversed(rest[:idx]) if s.skill == S.GRASP and s.state == "succeeded"), None)
        label = (grasped.facts.target or grasped.argument if grasped else None) or plan.target or "object"
        after = rest[idx + 1:]
        # An unstable place measured where the object came to rest; a later localization supersedes it.
        seen_at = place.found_at if place.code == OutcomeCode.UNSTABLE else None
        for s in after:
            if s.skill == S.OBJ_LOCALIZATION and s.state == "succeeded":
                seen_at = s.found_at or seen_at
        if seen_at is not None and spot is not None and spot.found_at is not None:
            sx, sy = spot.found_at[0], spot.found_at[1]
            surface_z = spot.surface_z if spot.surface_z is not None else spot.found_at[2]
            d = math.hypot(seen_at[0] - sx, seen_at[1] - sy)
            if d <= ON_SURFACE_XY and surface_z - 0.05 <= seen_at[2] <= surface_z + 0.4:
                return S.DONE, None, (f"The released {label} rests at ({seen_at[0]:.2f}, {seen_at[1]:.2f}, "
                                      f"{seen_at[2]:.2f}), {d:.2f} m from the placement spot on the "
                                      f"{plan.destination}: the command is complete.")
            return None  # somewhere else: pick it up again
        if any(s.skill == S.OBJ_LOCALIZATION for s in after):
            return None  # not found where it was released: search for it like any target
        return S.OBJ_LOCALIZATION, label, (f"place released the {label} but could not confirm it "
                                           f"({place.code}); look for it where it was released.")

    # ---- phases

    def _target(self, ctx: PolicyContext, plan: Plan, rest: list[PastStep]) -> tuple[str | None, str]:
        """(label or query to localize, why); label None when nothing fits yet."""
        choice = _TargetChoice(ctx, plan, rest)
        for part in (choice.by_choice, choice.by_size, choice.by_category, choice.by_name):
            found = part()
            if found is not None:
                return found
        return None, "The command names no object I can identify."

    def _pick(self, ctx: PolicyContext, plan: Plan, rest: list[PastStep]) -> tuple[str, str | None, str]:
        target, why = self._target(ctx, plan, rest)
        query = target or plan.target or (plan.choices[-1] if plan.choices else None)
        if target is None:
            label = query or (f"{plan.selector} {plan.group or 'object'}" if plan.selector else plan.category)
            return self._search(ctx, rest, query, S.OBJ_LOCALIZATION, why, label)
        last = rest[-1] if rest else None
        approach = self._approach(ctx, rest, S.GRASP, target)
        if approach is not None:
            return approach
        if not any(_matches(v.label, target) for v in ctx.visible) and target not in ctx.known_objects:
            # Chosen from what was seen earlier: face it before asking perception.
            turn = self._toward_remembered(ctx, rest, target, S.OBJ_LOCALIZATION)
            if turn is not None and turn[0] != S.OBJ_LOCALIZATION:
                return turn[0], turn[1], f"{why} {turn[2]}"
        if last and last.skill == S.OBJ_LOCALIZATION and last.state == "succeeded":
            return S.GRASP, target, f"{why} It was just localized, so grasp it."
        if last and last.skill == S.OBJ_LOCALIZATION and last.state != "succeeded" and last.argument == target:
            turn = self._toward_remembered(ctx, rest, target, S.OBJ_LOCALIZATION)
            if turn is not None and turn[0] != S.OBJ_LOCALIZATION:
                return turn[0], turn[1], f"{why} Localization failed ({last.code}). {turn[2]}"
            fails = _trailing_failures(rest, S.OBJ_LOCALIZATION)
            if fails % 2 == 1:
                return S.FORWARD, None, f"{why} Localization failed ({last.code}); move closer."
            return S.YAW_LEFT, None, f"{why} Localization failed again; re-align the view."
        return S.OBJ_LOCALIZATION, target, f"{why} Localize it before grasping."

    def _place(self, ctx: PolicyContext, plan: Plan, rest: list[PastStep], holding: str) -> tuple[str, str | None, str]:
        dest = plan.destination or ""
        # Surfaces need the exact name: "table" must not be taken for the "round table" next to it.
        seen = any(v.label.lower() == dest for v in ctx.visible) or any(k.lower() == dest for k in ctx.known_placements)
        last = rest[-1] if rest else None
        approach = self._approach(ctx, rest, S.PLACE, dest)
        if approach is not None:
            return approach
        if last and last.skill == S.PLACEMENT_LOCALIZATION and last.state == "succeeded":
            return S.PLACE, None, f"Holding the {holding}; the {dest} placement pose is localized, so place it."
        fails = _trailing_failures(rest, S.PLACEMENT_LOCALIZATION)
        if fails and fails <= 4:
            # Too far to find a plane on it (or seen past an edge): fly to where it was seen, then retry.
            since = next((len(rest) - 1 - i for i in range(len(rest) - 1, -1, -1)
                          if rest[i].skill == S.PLACEMENT_LOCALIZATION), 0)
            known = ctx.pose is not None and any(n.lower() == dest for n in ctx.positions)
            closer = self._approach_to(ctx, dest, since, ctx.pose, rest, exact=True,
                                       radius=SURFACE_RETRY_RADIUS) if known else None
            if closer is not None:
                skill, arg, how = closer
                return skill, arg, f"Placement localization failed ({_short(rest)}). {how}"
            if since > 0 and seen:
                return S.PLACEMENT_LOCALIZATION, dest, f"Holding the {holding}; closer to the {dest} now: localize " \
                                                       "the placement spot again."
        if last and last.skill == S.PLACEMENT_LOCALIZATION and last.state != "succeeded":
            fails = _trailing_failures(rest, S.PLACEMENT_LOCALIZATION)
            if fails % 2 == 1:
                return S.FORWARD, None, f"Placement localization failed ({last.code}); move closer."
            return S.YAW_LEFT, None, "Placement localization failed again; re-align the view."
        if not seen:
            return self._search(ctx, rest, dest, S.PLACEMENT_LOCALIZATION,
                                f"Holding the {holding}; the {dest} is not detected now.")
        return S.PLACEMENT_LOCALIZATION, dest, f"Holding the {holding} and the {dest} is detected: localize the " \
                                               "placement spot."

    def _approach(self, ctx: PolicyContext, rest: list[PastStep], skill: str,
                  label: str) -> tuple[str, str | None, str] | None:
        """After `skill` was refused as out of reach: turn toward the localized spot and fly closer, then retry."""
        idx = next((i for i in range(len(rest) - 1, -1, -1) if rest[i].skill in (skill, S.OBJ_LOCALIZATION,
                                                                                  S.PLACEMENT_LOCALIZATION)), None)
        if idx is None or rest[idx].skill != skill or rest[idx].state == "succeeded":
            return None
        refused = rest[idx]
        if refused.code != OutcomeCode.OUT_OF_REACH:
            return None
        reach = refused.facts.reach_m or DEFAULT_REACH
        far = f"{refused.facts.distance_m:.2f} m away" if refused.facts.distance_m is not None else "too far"
        moves = rest[idx + 1:]
        arg = label if skill == S.GRASP else None
        pos = next((xy for name, xy in ctx.positions.items() if _matches(name, label)), None)
        if pos is None or ctx.pose is None:
            if sum(1 for s in moves if s.skill == S.FORWARD) < 2:
                return S.FORWARD, None, f"The {label} is out of reach ({far}, reach {reach:.2f} m); fly closer."
            return skill, arg, f"Approached the {label}; try {skill} again."
        x, y, yaw = ctx.pose
        dist = math.hypot(pos[0] - x, pos[1] - y)
        bearing = math.atan2(pos[1] - y, pos[0] - x) - yaw
        bearing = math.atan2(math.sin(bearing), math.cos(bearing))
        if dist <= 0.8 * reach or len(moves) >= 12:
            return skill, arg, f"The {label} is now {dist:.1f} m away, within reach ({reach:.1f} m): {skill}."
        if abs(bearing) > math.radians(35):
            turn = S.YAW_LEFT if bearing > 0 else S.YAW_RIGHT
            return turn, None, (f"The {label} is {dist:.1f} m away at {math.degrees(bearing):.0f} deg: turn toward "
                                "it before flying closer.")
        return S.FORWARD, None, f"The {label} is {dist:.1f} m away (reach {reach:.1f} m) and ahead: fly closer."

    def _search(self, ctx: PolicyContext, rest: list[PastStep], query: str | None, localize: str,
                why: str, label: str | None = None) -> tuple[str, str | None, str]:
        if query and not any(s.skill not in S.OPERATOR_SKILLS for s in ctx.steps):
            # Perception's list at the first step still comes from frames taken during take-off (tables seen
            # from below, their tops hidden); the executor localizes on a fresh frame, so ask it before turning.
            return localize, query, f"{why} Just took off: ask perception about the current view before scanning."
        remembered = self._toward_remembered(ctx, rest, query, localize)
        if remembered is not None:
            skill, arg, how = remembered
            return skill, arg, f"{why} {how}"
        window = _search_window(rest)
        return explore(ctx, window, query, localize, why, label)

    @staticmethod
    def _toward_remembered(ctx: PolicyContext, rest: list[PastStep], query: str | None,
                           localize: str) -> tuple[str, str | None, str] | None:
        """Working memory says where the thing was seen earlier: turn toward it instead of scanning, then
        localize it. Gives up (back to scanning) after a localization there has failed twice."""
        if not query or ctx.pose is None:
            return None
        exact = localize == S.PLACEMENT_LOCALIZATION  # "table" must not match "round table"
        pos = next((xy for name, xy in ctx.positions.items()
                    if (name.lower() == query.lower() if exact else _matches(name, query))), None)
        if pos is None or _trailing_failures(rest, localize) >= 2:
            return None
        x, y, yaw = ctx.pose
        bearing = math.atan2(pos[1] - y, pos[0] - x) - yaw
        bearing = math.atan2(math.sin(bearing), math.cos(bearing))
        if abs(bearing) > math.radians(SEEN_FOV_HALF_DEG):
            turn = S.YAW_LEFT if bearing > 0 else S.YAW_RIGHT
            return turn, None, (f"It was seen earlier at ({pos[0]:.1f}, {pos[1]:.1f}), "
                                f"{math.degrees(bearing):.0f} deg from my heading: turn toward it.")
        return localize, query, f"It was seen earlier at ({pos[0]:.1f}, {pos[1]:.1f}), ahead of me now: localize it."


@dataclass
class _TargetChoice:
    """The ways the target object is chosen (a conditional's choice, a size comparison, the nearest of a category,
    the named one), each None when the command does not choose that way; all read the context, the plan, the
    steps since the command's motions and the objects in view that the command does not exclude."""

    ctx: PolicyContext
    plan: Plan
    rest: list[PastStep]
    visible: list[Seen] = field(init=False)

    def __post_init__(self) -> None:
        self.visible = [v for v in self.ctx.visible if v.category == "object" and not _excluded(v.label, self.plan)]

    def by_choice(self) -> tuple[str | None, str] | None:
        """A conditional ("if you see an orange, pick it up; otherwise grab the banana") picks one choice."""
        choices = self.plan.choices
        if not choices:
            return None
        # Decided from what is seen where the command says to look (after its motions), once: the first
        # successful localization of either choice settles it; a failed look for the first means "otherwise".
        for s in self.rest:
            if s.skill == S.OBJ_LOCALIZATION and s.argument in choices and s.state == "succeeded":
                return s.argument, f"I already chose the {s.argument} for the conditional."
        first, other = choices
        if any(s.skill == S.OBJ_LOCALIZATION and s.argument == first for s in self.rest):
            return other, f"I looked for a {first} here and did not find one, so grab the {other}."
        if any(_matches(v.label, first) for v in self.visible) or first in self.ctx.known_objects:
            return first, f"I see a {first}, so the condition holds: pick the {first}."
        return other, f"I do not see a {first}, so the command says to grab the {other}."

    def by_size(self) -> tuple[str | None, str] | None:
        """A size comparison ("the larger box") picks among the group's members in view, or by a name."""
        selector, group = self.plan.selector, self.plan.group or ""
        if not selector:
            return None
        def in_group(name: str) -> bool:
            return not group or _matches(name, group) or group in name

        # Sizes are compared while both are in view; once chosen, a turn that hides the other one (or the
        # choice itself) must not flip the decision to "the larger of the one I see".
        for s in self.rest:
            if s.skill == S.OBJ_LOCALIZATION and s.argument and in_group(s.argument):
                return s.argument, f"I already chose the {s.argument} as the {selector} {group or 'one'}."
        cands = [v for v in self.visible if in_group(v.label)]
        sized = [v for v in cands if v.volume is not None]
        if len(sized) >= 2:
            # Their classes' catalogued sizes when perception knows them and they differ (a box measured at 2 m
            # behind another is measured short: dev clutter/000 took a cracker box for larger than a cardboard
            # box of twice its volume); otherwise, two of one class, as measured.
            known = {v.catalog_volume for v in sized}
            catalogued = None not in known and len(known) > 1
            pick = (max if selector == "larger" else min)(
                sized, key=lambda v: (v.catalog_volume if catalogued else v.volume) or 0.0)
            return pick.label, (f"Of the {len(sized)} {group or 'object'} candidates I compare "
                                f"{'their catalogued sizes' if catalogued else 'sizes'}: the {selector} is the "
                                f"{pick.label}.")
        # Only one in view: a name that says its size ("large box") settles it, in view or seen earlier;
        # one whose name says the opposite is not taken for want of the other.
        want, avoid = SIZE_WORDS[selector], SIZE_WORDS["smaller" if selector == "larger" else "larger"]
        names = [v.label for v in cands] + [n for n in self.ctx.positions if in_group(n)]
        named = next((n for n in names if set(n.lower().split()) & want), None)
        if named:
            return named, f"The {named} is the {selector} {group or 'one'} by its name."
        # The only one in view (or, none in view, the only one seen) is taken after a full scan here has shown
        # no other (dev clutter/044 took the first box it saw, one look into the scan, and the larger stood
        # elsewhere).
        if sum(s.skill in (S.YAW_LEFT, S.YAW_RIGHT) for s in self.rest) >= SCAN_TURNS:
            seen = [n for n in self.ctx.positions if group and in_group(n) and not _excluded(n, self.plan)]
            lone, how = ((sized[0].label, "I detect, after a full scan") if len(sized) == 1
                         else (seen[0], "a full scan showed me") if not sized and len(seen) == 1 else (None, ""))
            if lone is not None and not set(lone.lower().split()) & avoid:
                return lone, f"The {lone} is the only {group or 'candidate'} {how}."
        return None, f"I need both {group or 'candidate'}s in view to compare sizes."

    def by_category(self) -> tuple[str | None, str] | None:
        """A category ("a snack") picks its nearest member in view, else one in working memory."""
        category = self.plan.category
        if not category:
            return None
        words = CATEGORY_WORDS[category]
        cands = [v for v in self.visible if any(w in v.label.lower() for w in words)]
        if cands:
            pick = min(cands, key=lambda v: v.distance if v.distance is not None else 1e9)
            return pick.label, f"The {pick.label} is a {category}, and the nearest one I detect."
        known = [k for k in self.ctx.known_objects
                 if any(w in k.lower() for w in words) and not _excluded(k, self.plan)]
        if known:
            return known[0], f"The {known[0]} in working memory is a {category}."
        return None, f"No {category} is detected yet."

    def by_name(self) -> tuple[str | None, str] | None:
        """A named object: one in view that matches the name, else one in working memory."""
        target = self.plan.target
        if not target:
            return None
        for v in self.visible:
            if _matches(v.label, target):
                return v.label, f"The {v.label} matches '{target}' and is detected."
        for k in self.ctx.known_objects:
            if _matches(k, target):
                return k, f"The {k} is in working memory."
        return None, f"The {target} is not detected yet."


def _search_window(rest: list[PastStep]) -> list[PastStep]:
    """The steps of the current search: since the last grasp or release (or since the command's motions)."""
    start = 0
    for i, s in enumerate(rest):
        if (s.skill == S.GRASP and s.state == "succeeded") or _released(s):
            start = i + 1
    return rest[start:]


@dataclass
class _Explorer:
    """The exploration's progress, replayed from the search's steps: leg 0 scans where the search began; leg k
    flies to viewpoint k (EXPLORE_RADIUS ahead, left, behind, right of that start) and scans there."""

    points: list[tuple[float, float]]
    leg: int = 0
    phase: str = "scan"
    n: int = 0
    blocked: int = 0

    def settle(self, pose: tuple[float, float, float] | None, been: list[tuple[float, float]]) -> None:
        """Phase changes that need no step: a finished scan moves on to the next viewpoint (skipping one the
        vehicle has already been at), an arrival, a blocked way or a spent transit budget starts the scan."""
        while True:
            if self.phase == "scan" and self.n >= SCAN_TURNS:
                self.leg, self.phase, self.n, self.blocked = self.leg + 1, "transit", 0, 0
                continue
            if self.phase != "transit" or self.leg > len(self.points):
                return
            wp = self.points[self.leg - 1]
            if self.n == 0 and any(math.dist(p, wp) <= EXPLORE_ARRIVED for p in been):
                self.leg += 1  # been there already (passed it on the way): the next viewpoint
                continue
            here = pose is not None and math.dist(pose[:2], wp) <= EXPLORE_ARRIVED
            if here or self.blocked >= 2 or self.n >= TRANSIT_LIMIT:
                self.phase, self.n = "scan", 0
            return

    def consume(self, step: PastStep) -> None:
        if self.phase == "scan":
            self.n += step.skill in (S.YAW_LEFT, S.YAW_RIGHT)
            return
        self.n += 1
        if step.skill == S.FORWARD:
            self.blocked = 0 if step.state == "succeeded" else self.blocked + 1

    @property
    def finished(self) -> bool:
        return self.leg > len(self.points)

    def next(self, pose: tuple[float, float, float] | None) -> tuple[str, str]:
        if self.phase == "scan":
            where = "where the search began" if self.leg == 0 else f"viewpoint {self.leg}/{len(self.points)}"
            return S.YAW_LEFT, f"Scan {where} ({self.n + 1}/{SCAN_TURNS})."
        wp = self.points[self.leg - 1]
        if pose is None:
            return S.FORWARD, f"Fly on to viewpoint {self.leg}/{len(self.points)}."
        dist = math.hypot(wp[0] - pose[0], wp[1] - pose[1])
        bearing = math.atan2(wp[1] - pose[1], wp[0] - pose[0]) - pose[2]
        bearing = math.atan2(math.sin(bearing), math.cos(bearing))
        where = f"viewpoint {self.leg}/{len(self.points)} at ({wp[0]:.1f}, {wp[1]:.1f}), {dist:.1f} m away"
        if abs(bearing) > math.radians(APPROACH_FACING_DEG):
            return (S.YAW_LEFT if bearing > 0 else S.YAW_RIGHT), f"Explore: turn toward {where}."
        return S.FORWARD, f"Explore: fly toward {where}."


def _poses(window: list[PastStep], now: tuple[float, float, float] | None) -> list[tuple[float, float, float] | None]:
    """The vehicle's pose before each step of the window (from the motions' reports), then the pose now."""
    known = [s.pose if s.skill in _MOTION_SKILLS else None for s in window]
    first = next((p for p in known if p is not None), now)
    out: list[tuple[float, float, float] | None] = [first]
    for p in known:
        out.append(p if p is not None else out[-1])
    out[-1] = now if now is not None else out[-1]
    return out


def explore(ctx: PolicyContext, window: list[PastStep], query: str | None, localize: str,
            why: str, label: str | None = None) -> tuple[str, str | None, str]:
    """The next exploration step when `query` is not in view, replayed from the search's own steps: scan in
    place, then fly to viewpoints around where the search began and scan from each; after the last (or after
    EXPLORE_BUDGET steps) `done` with a "not found" reason. Deterministic; reads only the context."""
    poses = _poses(window, ctx.pose)
    origin = poses[0]
    if origin is None:
        points = [(EXPLORE_RADIUS * math.cos(a), EXPLORE_RADIUS * math.sin(a)) for a in (0.0, 1.57, 3.14, -1.57)]
    else:
        points = [(origin[0] + EXPLORE_RADIUS * math.cos(origin[2] + a),
                   origin[1] + EXPLORE_RADIUS * math.sin(origin[2] + a)) for a in (0.0, math.pi / 2, math.pi,
                                                                                    -math.pi / 2)]
    ex = _Explorer(points)
    been: list[tuple[float, float]] = []
    for i, step in enumerate(window):
        pose = poses[i]
        ex.settle(pose, been)
        if step.skill in _MOTION_SKILLS:
            ex.consume(step)
        if pose is not None:
            been.append(pose[:2])
    ex.settle(poses[-1], been)
    what = query or label or "object the command asks for"
    if ex.finished or len(window) >= EXPLORE_BUDGET:
        moved = max((math.dist(p[:2], origin[:2]) for p in poses if p is not None), default=0.0) if origin else 0.0
        reached = len(points) if ex.finished else min(ex.leg, len(points))
        return S.DONE, None, (f"{NOT_FOUND}: the {what} was not detected after scanning where the search began and "
                              f"flying to {reached} viewpoint(s) around it ({len(window)} steps, up to {moved:.1f} m "
                              "from the start); the task ends failed.")
    last = window[-1] if window else None
    if (query and ex.phase == "transit" and ex.n == 0 and last is not None
            and last.skill in (S.YAW_LEFT, S.YAW_RIGHT)):
        return localize, query, f"{why} A full scan here did not detect it; ask perception directly."
    skill, how = ex.next(poses[-1])
    return skill, None, f"{why} {how}"


def _short(rest: list[PastStep]) -> str:
    last = next((s for s in reversed(rest) if s.state != "succeeded"), None)
    return f"{last.skill} {last.code}" if last else ""


def _released(s: PastStep) -> bool:
    """A place that opened the gripper, whatever it reported: the object is no longer held."""
    return s.skill == S.PLACE and s.code in _RELEASED


def _trailing_failures(rest: list[PastStep], skill: str) -> int:
    n = 0
    for s in reversed(rest):
        if s.skill == skill:
            if s.state == "succeeded":
                break
            n += 1
    return n


_PREDICT = {
    S.YAW_LEFT: "the view turns left; new objects may come into view",
    S.YAW_RIGHT: "the view turns right; new objects may come into view",
    S.FORWARD: "moves closer to what is ahead",
    S.BACKWARD: "retreats and widens the view",
    S.LEFT: "shifts left",
    S.RIGHT: "shifts right",
    S.UP: "climbs; more of the scene is visible",
    S.DOWN: "descends toward manipulation height",
    S.OBJ_LOCALIZATION: "estimates the 3D pose of the queried object if it is visible",
    S.GRASP: "grasps the localized object if one is in working memory",
    S.PLACEMENT_LOCALIZATION: "finds a free placement spot on the queried surface if visible",
    S.PLACE: "releases the held object at the localized placement pose",
    S.DONE: "ends the task",
}


def render_answer(ctx: PolicyContext, skill: str, argument: str | None, reasoning: str) -> str:
    """The decision as the variant's answer text: JSON DRT/STE, `Thought:`+JSON (react), or a bare skill."""
    if ctx.variant == "unstructured":
        return f"{skill}({argument})" if argument else skill
    ste = {"skill": skill, "argument": argument}
    if ctx.variant == "react":
        return f"Thought: {reasoning}\nAction: {json.dumps(ste)}"
    seen = ", ".join(v.label for v in ctx.visible) or "nothing recognised"
    last = ctx.steps[-1] if ctx.steps else None
    full = {
        "image_description": f"Perception reports: {seen}.",
        "summary": (f"{len(ctx.steps)} skills executed; last {last.skill} -> {last.state}. "
                    if last else "No skill executed yet. ") + f"Holding: {ctx.held or 'nothing'}.",
        "action_predictions": {n: _PREDICT.get(n, "runs the skill") for n in ctx.skills},
        "reasoning": reasoning,
    }
    out: dict = {}
    fields = DRT_FIELDS.get(ctx.variant, ())
    if fields:
        out["drt"] = {f: full[f] for f in fields}
    out["ste"] = ste
    return json.dumps(out)


@register
class RulesBackend(Backend):
    """Backend wrapping the deterministic non-VLM rules policy (reads the prompt's context, never pixels)."""

    kind = "rules"
    summary = "the deterministic non-VLM baseline policy (reads the prompt's context, never pixels)"
    name = "rules"

    def __init__(self) -> None:
        self.policy = RulesPolicy()

    def refusal(self, command: str, skills: list[str]) -> str | None:
        """Why the command cannot be carried out (it names no object, no motion and no task verb), else None."""
        plan = parse_command(command, skills)
        return None if plan.understood else plan.reason

    def unsupported(self, variant: str) -> str | None:
        """The Table III baselines (saycan, direct, waypoint, plan_once) are frameworks for a model: the rules
        policy does not emulate them, so they are refused rather than answered in a form that is not theirs."""
        if variant in BASELINES:
            return (f"the rules backend does not emulate the {variant} baseline framework; run it with a model "
                    "backend (openai, anthropic)")
        return None

    async def complete(self, request: ModelRequest) -> ModelReply:
        t0 = time.perf_counter()
        d = self.policy.decide_full(request.context)
        text = render_answer(request.context, d.skill, d.argument, d.reasoning)
        return ModelReply(text=text, latency_s=time.perf_counter() - t0, failure=d.failure)
