"""The paper's metrics (Section IV-C): SR, ARR, RS, IAR, RT (median, p95) and TT, from episode records.

Definitions, exactly as computed here (docs/evaluation.md repeats them):

- SR = successful episodes / episodes x 100. An episode succeeds when the task's own end state is `succeeded`
  (the policy declared it done before T_max) AND the simulator's ground-truth judge agrees (for a size or
  conditional task, on the object the simulator decided) AND the motions the task asks for happened before the
  pick (aermani/evaluation/scoring.py); the report shows the counts apart.
- Actions of an episode: the skills the policy chose and the executor ran (a step with an STE and a skill
  state), except `done`, which moves nothing. n_total = number of actions.
- An action is redundant (counted once even if several rules match) when it is
  1. an oscillatory correction: a motion primitive undone by one of the next two motion primitives of the
     episode, judged by net displacement: the vehicle's displacement over the later motion cancels the
     earlier one's (position within `pos_tol`, yaw within `yaw_tol`) and the earlier one did move the vehicle.
     Both are redundant. Where a pose is missing, the later motion must be the earlier one's OPPOSITE
     (shared/skills.py);
  2. part of a zero-net-displacement sequence: two or more consecutive motion primitives (no other action
     between) that bring the vehicle back to where it started, position within `pos_tol` metres and yaw
     within `yaw_tol` radians. Poses come from the skills' outcomes (the trajectory log); when a pose is
     missing, the sequence is dead-reckoned with generic, incommensurate step sizes, so it counts only if it
     cancels whatever the primitives' step sizes are;
  3. a repeated localization with no motion between: obj_localization or placement_localization with the
     same (case- and space-normalized) argument as an earlier one of the same kind, with no motion
     primitive, grasp or place in between that the executor ran (a rejected skill moved nothing): the view
     did not change, so the answer cannot;
  4. a futile loop: a skill that failed (failed, rejected or timed out) repeated with the same argument and
     failing again, with no change of state since the earlier failure (no action succeeded between, the held
     object is the same, and, where poses are known, the vehicle is where that failure left it). The repeats
     are redundant, not the first attempt.
- ARR = mean over successful episodes of n_redundant / n_total, x 100 (the paper's tables are in percent).
- RS = mean number of reasoning cycles (reasoning steps) per episode over all episodes.
- IAR = invalid answers / all model queries x 100 (every call of every step, re-prompts included). Per
  episode the larger of the recorded calls and the terminal status's counters is taken, so an invalid answer
  whose step ended in a transport error (and a lost step sample) still counts.
- RT = median and 95th percentile (linear interpolation) of the model latency per query, seconds.
- TT = mean end-to-end time of successful episodes, seconds (reasoner start to terminal status), on the wall
  clock (which mixes simulated time sped up by the speed factor with real waits: model calls, perception) and in
  simulated seconds (the simulator's clock, read from the judge just before the start and just after the end).
- Collisions: every entry of the simulator judge's `collisions` since the reset, per episode, by kind: an entry
  `vehicle-<thing>` is an airframe contact with furniture, walls or the ceiling (services/sim/physics.py); any
  other entry (gripper strikes, knocked or dropped objects) is counted under the kind its name starts with (the
  text before a ':', else before the first '-'), so kinds the simulator adds are counted without a change here.
  Reported as the total, airframe and other, the mean per episode, the episodes with any and the count per kind.

Episodes the harness could not run (harness_error) are left out of every metric and counted in `not_run`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict

from aermani.evaluation.grounding import violation_rate
from aermani.evaluation.records import EpisodeRecord
from aermani.evaluation.runs import episode_grounding
from shared.messages import Pose, ReasoningStep
from shared.skills import (
    DONE,
    GRASP,
    MOTION_PRIMITIVES,
    OBJ_LOCALIZATION,
    OPPOSITE,
    PLACE,
    PLACEMENT_LOCALIZATION,
)
from shared.stats import percentile

LOCALIZATIONS = (OBJ_LOCALIZATION, PLACEMENT_LOCALIZATION)
# Actions that change the view or the scene, so a localization after them is not a repeat.
VIEW_CHANGING = (*MOTION_PRIMITIVES, GRASP, PLACE)
OSCILLATION_WINDOW = 2
FAILING = ("failed", "rejected", "timeout")
POS_TOL = 0.10
YAW_TOL = 0.15
# Generic, pairwise incommensurate step sizes for dead reckoning: a sequence that cancels with these
# cancels for any step sizes (coincidental cancellation would need an algebraic relation between them).
_GENERIC_STEP = {"forward": math.sqrt(2), "left": math.sqrt(3), "up": math.sqrt(5), "yaw": 1.0 / math.e}


@dataclass(frozen=True)
class Action:
    """One executed skill, as ARR sees it."""

    skill: str
    argument: str | None = None
    start_pose: Pose | None = None
    end_pose: Pose | None = None
    state: str | None = None
    held: str | None = None


def actions_of(steps: Iterable[ReasoningStep]) -> list[Action]:
    """The executed actions of an episode (see the module docstring)."""
    out = []
    for s in steps:
        if s.ste is None or s.skill_state is None or s.ste.skill == DONE:
            continue
        o = s.outcome
        out.append(Action(s.ste.skill, s.ste.argument, o.start_pose if o else None, o.end_pose if o else None,
                          s.skill_state.value, o.held_object if o else None))
    return out


def _norm(arg: str | None) -> str:
    return " ".join((arg or "").lower().split())


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _displacement(a: Action) -> tuple[float, float, float, float] | None:
    """World-frame (dx, dy, dz, dyaw) of one action from its start and end poses; None without both."""
    if a.start_pose is None or a.end_pose is None:
        return None
    p0, p1 = a.start_pose.position, a.end_pose.position
    return p1.x - p0.x, p1.y - p0.y, p1.z - p0.z, _wrap(a.end_pose.yaw - a.start_pose.yaw)


def _undoes(first: Action, later: Action, pos_tol: float, yaw_tol: float) -> bool:
    """Whether `later` undoes `first`: by net displacement when both have poses, else by name."""
    d0, d1 = _displacement(first), _displacement(later)
    if d0 is None or d1 is None:
        return later.skill == OPPOSITE[first.skill]
    moved = math.hypot(*d0[:3]) > pos_tol or abs(d0[3]) > yaw_tol
    net = (d0[0] + d1[0], d0[1] + d1[1], d0[2] + d1[2])
    return moved and math.hypot(*net) <= pos_tol and abs(_wrap(d0[3] + d1[3])) <= yaw_tol


def oscillations(actions: Sequence[Action], pos_tol: float = POS_TOL, yaw_tol: float = YAW_TOL) -> set[int]:
    """Rule 1: motions undone within the next two motions (both are marked)."""
    motions = [i for i, a in enumerate(actions) if a.skill in MOTION_PRIMITIVES]
    out: set[int] = set()
    for k, i in enumerate(motions):
        for j in motions[k + 1:k + 1 + OSCILLATION_WINDOW]:
            if _undoes(actions[i], actions[j], pos_tol, yaw_tol):
                out.update((i, j))
                break
    return out


def _dead_reckon(window: Sequence[Action]) -> tuple[float, float, float, float]:
    x = y = z = yaw = 0.0
    for a in window:
        s = a.skill
        if s in ("yaw_left", "yaw_right"):
            yaw += _GENERIC_STEP["yaw"] * (1 if s == "yaw_left" else -1)
            continue
        fwd = {"forward": 1, "backward": -1}.get(s, 0) * _GENERIC_STEP["forward"]
        lat = {"left": 1, "right": -1}.get(s, 0) * _GENERIC_STEP["left"]
        z += {"up": 1, "down": -1}.get(s, 0) * _GENERIC_STEP["up"]
        x += fwd * math.cos(yaw) - lat * math.sin(yaw)
        y += fwd * math.sin(yaw) + lat * math.cos(yaw)
    return x, y, z, yaw


def _returns_to_start(window: Sequence[Action], pos_tol: float, yaw_tol: float) -> bool:
    start, end = window[0].start_pose, window[-1].end_pose
    if start is not None and end is not None and all(a.start_pose is not None and a.end_pose is not None
                                                     for a in window):
        dist = math.dist(start.position.as_tuple(), end.position.as_tuple())
        return dist <= pos_tol and abs(_wrap(end.yaw - start.yaw)) <= yaw_tol
    x, y, z, yaw = _dead_reckon(window)
    return math.hypot(x, y, z) < 1e-9 and abs(yaw) < 1e-9


def zero_net_sequences(actions: Sequence[Action], pos_tol: float = POS_TOL, yaw_tol: float = YAW_TOL) -> set[int]:
    """Rule 2: every action inside a run of >= 2 consecutive motions that returns to its start pose."""
    out: set[int] = set()
    n = len(actions)
    i = 0
    while i < n:
        if actions[i].skill not in MOTION_PRIMITIVES:
            i += 1
            continue
        j = i
        while j + 1 < n and actions[j + 1].skill in MOTION_PRIMITIVES:
            j += 1
        for a in range(i, j + 1):  # run is actions[i..j]
            for b in range(a + 1, j + 1):
                if _returns_to_start(actions[a:b + 1], pos_tol, yaw_tol):
                    out.update(range(a, b + 1))
        i = j + 1
    return out


def repeated_localizations(actions: Sequence[Action]) -> set[int]:
    """Rule 3: a localization repeating an earlier one (same kind, same argument) with no view change between."""
    out: set[int] = set()
    seen: set[tuple[str, str]] = set()
    for i, a in enumerate(actions):
        if a.skill in VIEW_CHANGING and a.state != "rejected":  # a rejected skill moved nothing
            seen.clear()
        elif a.skill in LOCALIZATIONS:
            key = (a.skill, _norm(a.argument))
            if key in seen:
                out.add(i)
            seen.add(key)
    return out


def _same_place(a: Pose | None, b: Pose | None, pos_tol: float, yaw_tol: float) -> bool:
    if a is None or b is None:
        return True  # unknown: the other conditions decide
    return (math.dist(a.position.as_tuple(), b.position.as_tuple()) <= pos_tol
            and abs(_wrap(a.yaw - b.yaw)) <= yaw_tol)


def futile_loops(actions: Sequence[Action], pos_tol: float = POS_TOL, yaw_tol: float = YAW_TOL) -> set[int]:
    """Rule 4: a failing skill repeated (same skill and argument) that fails again with no change of state
    since the earlier failure: nothing succeeded between, the same object held, the vehicle where it was."""
    out: set[int] = set()
    failures: dict[tuple[str, str], Action] = {}  # failures since the last change of state
    for i, a in enumerate(actions):
        if a.state not in FAILING:  # a skill that ran (or a record without a state) may have changed things
            failures.clear()
            continue
        key = (a.skill, _norm(a.argument))
        earlier = failures.get(key)
        if earlier is not None and earlier.held == a.held and _same_place(earlier.end_pose, a.start_pose,
                                                                            pos_tol, yaw_tol):
            out.add(i)
        failures[key] = a
    return out


def redundant_actions(actions: Sequence[Action], pos_tol: float = POS_TOL, yaw_tol: float = YAW_TOL) -> set[int]:
    """Indices of redundant actions (union of the four rules)."""
    return (oscillations(actions, pos_tol, yaw_tol) | zero_net_sequences(actions, pos_tol, yaw_tol)
            | repeated_localizations(actions) | futile_loops(actions, pos_tol, yaw_tol))


def redundancy_ratio(actions: Sequence[Action]) -> float:
    """n_redundant / n_total for one episode (0 when there is no action)."""
    return len(redundant_actions(actions)) / len(actions) if actions else 0.0


def reasoning_steps(rec: EpisodeRecord) -> int:
    """Reasoning cycles of an episode: the step records, or the terminal status's count if more were announced
    than recorded (a lost sample must not make a policy look better)."""
    return max(len(rec.steps), rec.status.steps if rec.status else 0)


class Metrics(BaseModel):
    """The paper's metrics for one group of episodes (None where undefined, e.g. ARR with no success)."""

    model_config = ConfigDict(frozen=True)

    episodes: int
    successes: int
    not_run: int = 0
    sr: float | None = None
    sr_low: float | None = None
    """Lower end of SR's 95 % Wilson score interval (%)."""
    sr_high: float | None = None
    """Upper end of SR's 95 % Wilson score interval (%)."""
    arr: float | None = None
    rs: float | None = None
    iar: float | None = None
    rt_median: float | None = None
    rt_p95: float | None = None
    tt: float | None = None
    """TT on the wall clock, seconds."""
    tt_sim: float | None = None
    """TT in simulated seconds (successful episodes whose record has the simulator's clock)."""
    queries: int = 0
    invalid: int = 0
    ended_succeeded: int = 0
    """Episodes whose task ended `succeeded` (the policy's own end state), whatever the judge says."""
    judged_success: int = 0
    """Episodes the simulator's judge found right, whatever the task's end state."""
    collisions: int = 0
    """Collisions over all episodes: every incident the simulator recorded (each tag once per episode), the sum of
    the four kinds below."""
    vehicle_collisions: int = 0
    """Airframe or landing-gear contacts with furniture, walls or the ceiling ("vehicle-<thing>")."""
    gripper_strikes: int = 0
    """A finger pad or arm against furniture, a wall, the ceiling or an object other than the target
    ("gripper-<thing>")."""
    knocked_objects: int = 0
    """Objects knocked over or off what they stood on while not in the pads ("knocked-<object>")."""
    dropped_objects: int = 0
    """Objects that left the pads after a lift and fell more than 0.1 m ("dropped-<object>")."""
    collision_episodes: int = 0
    """Episodes with at least one collision (of any kind)."""
    collisions_per_episode: float | None = None
    motions_missed: int = 0
    """Episodes whose task asks for motions that did not happen before the pick (aermani/evaluation/scoring.py)."""
    guessed_successes: int = 0
    """Successes of size or conditional tasks whose object was picked before the policy had seen what decides it."""
    gvr: float | None = None
    """Grounding-violation rate: % of checked steps whose DRT contradicts what was measured (grounding.py)."""
    grounding_checked: int = 0
    """Steps the grounding check could check (a DRT and a live observation in the prompt)."""
    grounding_flagged: int = 0
    """Checked steps with at least one grounding violation."""


def iar_by_mode(records: Iterable[EpisodeRecord]) -> dict[str, tuple[int, int]]:
    """(invalid, calls) per answer decoding: `schema` (schema-constrained) and `text` (free text)."""
    out: dict[str, tuple[int, int]] = {}
    for r in records:
        if r.harness_error:
            continue
        for s in r.steps:
            for c in s.calls:
                mode = "schema" if c.structured else "text"
                bad, n = out.get(mode, (0, 0))
                out[mode] = (bad + (not c.valid), n + 1)
    return out


def query_counts(rec: EpisodeRecord) -> tuple[int, int]:
    """(invalid answers, model queries) of one episode: the recorded calls, or the terminal status's counters
    when it counted more (an invalid answer whose step then hit a transport error, a lost step sample)."""
    calls = [c for s in rec.steps for c in s.calls]
    invalid = sum(1 for c in calls if not c.valid)
    if rec.status is not None:
        return max(invalid, rec.status.invalid_answers), max(len(calls), rec.status.model_calls)
    return invalid, len(calls)


def judged_ok(rec: EpisodeRecord) -> bool:
    """The judge's verdict alone (older records kept only the combined verdict)."""
    return rec.judge_success if rec.judge_success is not None else rec.success


def wilson(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """The 95 % Wilson score interval of a success rate, in % (well behaved at 0 and n successes, unlike the
    normal approximation)."""
    if n <= 0:
        raise ValueError("no episodes")
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    lo = 0.0 if successes == 0 else max(0.0, centre - half)
    hi = 1.0 if successes == n else min(1.0, centre + half)
    return 100.0 * lo, 100.0 * hi


INCIDENT_KINDS = ("vehicle", "gripper", "knocked", "dropped")
"""The simulator's incident tags are "<kind>-<thing>" (services/sim/README.md "Gripper"); records from before
the gripper's incidents hold only "vehicle-" tags."""


def incident_counts(records: Iterable[EpisodeRecord]) -> dict[str, int]:
    """How many incidents of each kind (INCIDENT_KINDS) the records hold; a tag of no known kind counts as a
    vehicle collision (the only kind there was)."""
    out = dict.fromkeys(INCIDENT_KINDS, 0)
    for r in records:
        for tag in r.collisions:
            kind = tag.split("-", 1)[0]
            out[kind if kind in out else "vehicle"] += 1
    return out


def compute(records: Iterable[EpisodeRecord]) -> Metrics:
    records = list(records)
    ran = [r for r in records if not r.harness_error]
    ok = [r for r in ran if r.success]
    latencies = [c.latency_s for r in ran for s in r.steps for c in s.calls]
    counts = [query_counts(r) for r in ran]
    invalid, queries = sum(c[0] for c in counts), sum(c[1] for c in counts)
    collisions = [len(r.collisions) for r in ran]
    grounded = [g for r in ran for g in episode_grounding(r) if g.checked]
    sim = [d for r in ok if (d := r.sim_duration_s) is not None]
    kinds = incident_counts(ran)
    n = len(ran)
    return Metrics(
        episodes=n,
        successes=len(ok),
        not_run=len(records) - n,
        sr=100.0 * len(ok) / n if n else None,
        sr_low=wilson(len(ok), n)[0] if n else None,
        sr_high=wilson(len(ok), n)[1] if n else None,
        arr=100.0 * sum(redundancy_ratio(actions_of(r.steps)) for r in ok) / len(ok) if ok else None,
        rs=sum(reasoning_steps(r) for r in ran) / n if n else None,
        iar=100.0 * invalid / queries if queries else None,
        rt_median=percentile(latencies, 50) if latencies else None,
        rt_p95=percentile(latencies, 95) if latencies else None,
        tt=sum(r.duration_s for r in ok) / len(ok) if ok else None,
        tt_sim=sum(sim) / len(sim) if sim else None,
        queries=queries,
        invalid=invalid,
        ended_succeeded=sum(1 for r in ran if r.state == "succeeded"),
        judged_success=sum(1 for r in ran if judged_ok(r)),
        collisions=sum(collisions),
        vehicle_collisions=kinds["vehicle"],
        gripper_strikes=kinds["gripper"],
        knocked_objects=kinds["knocked"],
        dropped_objects=kinds["dropped"],
        collision_episodes=sum(1 for c in collisions if c),
        collisions_per_episode=sum(collisions) / n if n else None,
        motions_missed=sum(1 for r in ran if r.motions_ok is False),
        guessed_successes=sum(1 for r in ok if r.choice is not None and r.choice.informed is False),
        gvr=violation_rate(grounded),
        grounding_checked=len(grounded),
        grounding_flagged=sum(g.violated for g in grounded),
    )
