"""Each task scored for what it asks (aermani/evaluation/scoring.py), on real recorded episodes of the dev split
(tests/evaluation/data/rules-dev-2026-12-06.jsonl.gz: their steps, skill outcomes and poses) and on the
simulator's real world answers (SimCore's judge, op world, for the recorded scenario: the layout rebuilt from its
seed)."""

from __future__ import annotations

import gzip
import math
from functools import cache
from pathlib import Path
from typing import get_args

import pytest

from aermani.evaluation.records import EpisodeRecord
from aermani.evaluation.report import choice_lines, motion_lines
from aermani.evaluation.scoring import (
    MIN_HORIZONTAL_M,
    MIN_VERTICAL_M,
    MIN_YAW_RAD,
    accepted_objects,
    check_motions,
    decide,
    score_choice,
    score_episode,
)
from aermani.evaluation.tasks import (
    MOTION_KINDS,
    ConditionalChoice,
    EvalTask,
    ExpectedMotion,
    SizeChoice,
    load_suites,
)
from shared.messages import JudgeRequest, JudgeResult, Scenario

# The dev report of 2026-12-06 (kinematic vehicle, split of 2026-11): recorded episodes whose steps these tests
# name; the report that replaced it in docs/eval/rules-dev is a later run on another world.
DEV_RUN = Path(__file__).resolve().parent / "data" / "rules-dev-2026-12-06.jsonl.gz"


@cache
def _records() -> dict[str, EpisodeRecord]:
    with gzip.open(DEV_RUN, "rt", encoding="utf-8") as f:
        recs = [EpisodeRecord.model_validate_json(line) for line in f if line.strip()]
    assert all(r.task.split == "dev" for r in recs)  # never a test-split episode
    return {r.episode_id: r for r in recs}


def _rec(eid: str) -> EpisodeRecord:
    return _records()[eid]


def _world(scenario: Scenario) -> JudgeResult:
    """The simulator's ground truth of the scenario's layout, as the runner asks for it at the start."""
    from services.sim.core import SimCore

    core = SimCore(scenario, realism="realistic")
    return core.judge(JudgeRequest(op="world"))


def _recorded_world(rec: EpisodeRecord) -> JudgeResult:
    assert rec.judge is not None and rec.judge.scenario is not None
    world = _world(rec.judge.scenario)
    # the layout rebuilt from the recorded scenario is the one the episode flew in
    assert world.scenario is not None and world.scenario.start == rec.judge.scenario.start
    return world


def M(skill: str, times: int = 1, to: str | None = None) -> ExpectedMotion:  # noqa: N802 - reads like the suites
    return ExpectedMotion(skill=skill, times=times, to=to)


GO_UP = "rules/full/sequential/004-s936101692"  # "Go up a bit, then forward once, and grab the coke can."


def test_the_motion_kinds_are_the_primitives_plus_turn_and_approach() -> None:
    from shared.skills import MOTION_PRIMITIVES

    assert set(get_args(ExpectedMotion.model_fields["skill"].annotation)) == set(MOTION_KINDS)
    assert set(MOTION_KINDS) == {*MOTION_PRIMITIVES, "turn", "approach"}
    with pytest.raises(ValueError, match="approach"):
        ExpectedMotion(skill="approach")
    with pytest.raises(ValueError, match="approach"):
        ExpectedMotion(skill="up", to="table")


def test_a_motion_counts_from_half_a_default_step_of_the_executor() -> None:
    from services.executor.settings import ExecutorSettings

    s = ExecutorSettings()
    assert pytest.approx(s.horizontal_step / 2) == MIN_HORIZONTAL_M
    assert pytest.approx(s.vertical_step / 2) == MIN_VERTICAL_M
    assert pytest.approx(math.radians(s.yaw_step_deg / 2)) == MIN_YAW_RAD


def test_commanded_motions_are_found_in_the_recorded_trajectory_in_order_before_the_pick() -> None:
    rec = _rec(GO_UP)
    ok = check_motions([M("up"), M("forward")], rec.steps, None)
    assert ok.ok and "up x1: step 1 up (" in ok.detail and "up +0.24 m" in ok.detail, ok.detail
    assert not check_motions([M("forward"), M("up")], rec.steps, None).ok  # the climb came first
    assert not check_motions([M("up", times=2)], rec.steps, None).ok  # one climb, not two
    assert not check_motions([M("down")], rec.steps, None).ok
    # "Move forward twice, turn right, and pick up the tissue box": the yaw is measured, not the skill's name
    tissue = _rec("rules/full/sequential/000-s923845130")
    assert check_motions([M("forward", 2), M("yaw_right")], tissue.steps, None).ok
    assert not check_motions([M("forward", 2), M("yaw_left")], tissue.steps, None).ok
    # "Turn around": four yaw steps one way, either way
    around = _rec("rules/full/sequential/007-s273211455")
    assert check_motions([M("turn", 4)], around.steps, None).ok
    assert not check_motions([M("turn", 9)], around.steps, None).ok


def test_a_task_that_never_climbed_fails_whatever_the_judge_says() -> None:
    """Issue 26: "go a bit higher" read as an object to find counted as a success. The same episode without its
    climb (the motion that did not happen) is not a success, though the judge found the can picked."""
    rec = _rec(GO_UP)
    assert rec.success and rec.judge_success
    never = [s for s in rec.steps if s.ste is None or s.ste.skill != "up"]
    task = rec.task.model_copy(update={"motions": (M("up"), M("forward"))})
    success, verdict, fields = score_episode(task, never, None, rec.held, True, rec.verdict)
    assert not success and fields["motions_ok"] is False
    assert "commanded motions did not happen: up x1 never happened before the pick" in verdict
    success, verdict, fields = score_episode(task, rec.steps, None, rec.held, True, rec.verdict)
    assert success and fields["motions_ok"] is True and verdict == rec.verdict
    # a climb after the pick is not the climb the command asked for before it
    pick = next(i for i, s in enumerate(rec.steps) if s.ste and s.ste.skill == "grasp")
    late = [*never[:pick - 1], never[pick - 1], *[s for s in rec.steps if s.ste and s.ste.skill == "up"]]
    assert not check_motions([M("up")], late, None).ok


def test_an_approach_is_checked_against_the_true_footprint() -> None:
    sink = _rec("rules/full/sequential/008-s686749748")  # "Go over to the sink. If there's a red cup there ..."
    world = _recorded_world(sink)
    got = check_motions([M("approach", to="sink")], sink.steps, world)
    assert got.ok and "within 1.32 m at the start" in got.detail, got.detail  # it took off near the sink
    # a motion right after an arrival counts (its step began there), and one asked for after it must follow it
    assert [s.ste.skill for s in sink.steps[:3]] == ["yaw_left", "yaw_right", "forward"]
    assert check_motions([M("approach", to="sink"), M("yaw_left")], sink.steps, world).ok
    assert not check_motions([M("yaw_right"), M("yaw_left")], sink.steps, world).ok
    # "Approach the counter. ...": the policy scanned, never came near the counter, and picked from afar
    counter = _rec("rules/full/sequential/001-s935737221")
    got = check_motions([M("approach", to="counter")], counter.steps, _recorded_world(counter))
    assert not got.ok and "within 2.52 m of it at best" in got.detail, got.detail
    assert not check_motions([M("approach", to="counter")], counter.steps, None).ok  # no world: not shown


def test_the_simulator_decides_size_and_conditional_choices_from_the_world() -> None:
    suites = load_suites(split="dev")
    world = _world(Scenario(seed=5, target_object="green bottle", extra_objects=("coke can", "apple", "cardboard box",
                                                                                     "cracker box"), distractors=()))
    assert decide(SizeChoice(select="largest", among=("cardboard box", "cracker box")), world)[0] == ("cardboard box",)
    answer, why = decide(SizeChoice(select="smallest", among=("cardboard box", "cracker box")), world)
    assert answer == ("cracker box",) and "cardboard box 5.28 L, cracker box 2.35 L" in why, why
    assert decide(SizeChoice(select="tallest", among=("green bottle", "coke can", "apple")), world)[0] == (
        "green bottle",)
    # the conditional's two dev lines: the layout decides the branch
    lines = [t for t in suites["sequential"] if t.command.startswith("Approach the counter.")]
    choice = ConditionalChoice(if_present="orange", on="counter", then="orange", otherwise="banana")
    got = {t.target_object: decide(choice, _world(t.scenario(11))) for t in lines}
    assert got["orange"] == (("orange",), "the orange rests on the counter: the condition holds")
    assert got["banana"] == (("banana",), "no orange in the world: the condition does not hold")
    elsewhere = _world(Scenario(seed=11, target_object="orange", placements={"orange": "table"}, distractors=()))
    assert decide(choice, elsewhere)[0] == ("banana",)  # an orange, but not on the counter
    assert lines[0].choice == choice  # the suite line carries it
    assert accepted_objects(lines[0], None)[0] == ()  # no world at the start: not decided, not guessed
    assert accepted_objects(lines[0], _world(lines[0].scenario(11))) == (("orange",), "")
    plain = lines[0].model_copy(update={"choice": None})
    assert accepted_objects(plain, None) == (plain.accepted, "")


def test_a_choice_made_before_seeing_what_decides_it_is_a_guess() -> None:
    """Issue 26: "the only box I detect". The real dev episode took the cracker box for "the larger one" having
    seen only it; another saw both boxes before it took the smaller."""
    larger = _rec("rules/full/clutter/000-s299657781")  # "Of the two boxes, pick up the larger one."
    choice = SizeChoice(select="largest", among=("cardboard box", "cracker box"))
    out = score_choice(choice, _recorded_world(larger), larger.steps, larger.held)
    assert out.answer == ("cardboard box",) and out.chosen == "cracker box"
    assert out.informed is False and out.seen == ("cracker box",)
    smaller = _rec("rules/full/clutter/005-s336731463")  # "Grab the smaller of the two boxes."
    out = score_choice(choice.model_copy(update={"select": "smallest"}), _recorded_world(smaller), smaller.steps,
                       smaller.held)
    assert out.answer == ("cracker box",) and out.chosen == "cracker box" and out.informed is True
    assert out.seen == ("cardboard box", "cracker box")
    # the same success had the policy seen only the box it took: flagged in the verdict and the report
    seen_one = [s for s in smaller.steps if "cardboard box" not in (s.ste.argument or "" if s.ste else "")]
    blind = [s.model_copy(update={"prompt": {}}) for s in seen_one]
    task = smaller.task.model_copy(update={"choice": choice.model_copy(update={"select": "smallest"})})
    success, verdict, fields = score_episode(task, blind, _recorded_world(smaller), smaller.held, True, "holding it")
    assert success and fields["choice"].informed is False
    assert "a success on a guess: the cracker box was picked before the cardboard box was seen" in verdict
    guess = smaller.model_copy(update={"task": task, "success": True, **fields})
    text = "\n".join(choice_lines([guess]))
    assert "a **success on a guess**: 1 of 1 success(es)" in text and "yes, **on a guess**" in text
    from aermani.evaluation.metrics import compute

    assert compute([guess]).guessed_successes == 1 and compute([smaller]).guessed_successes == 0


def test_the_report_lists_the_motion_checks() -> None:
    rec = _rec(GO_UP)
    task = rec.task.model_copy(update={"motions": (M("up"), M("forward"))})
    never = [s for s in rec.steps if s.ste is None or s.ste.skill != "up"]
    success, verdict, fields = score_episode(task, never, None, rec.held, True, rec.verdict)
    bad = rec.model_copy(update={"task": task, "steps": never, "success": success, "verdict": verdict, **fields})
    text = "\n".join(motion_lines([bad]))
    assert "0 of 1 episode(s) made them before the pick; 1 episode(s) that ended succeeded" in text
    assert f"| {GO_UP} | up x1, forward x1 | **no** | no |" in text
    from aermani.evaluation.metrics import compute

    m = compute([bad, rec])
    assert (m.motions_missed, m.successes, m.judged_success) == (1, 1, 2)
    assert motion_lines([rec]) == []


def test_suite_lines_with_scoring_fields_validate() -> None:
    with pytest.raises(ValueError, match="not one the choice can name"):
        EvalTask(command="Take the larger box.", target_object="apple",
                 choice=SizeChoice(select="largest", among=("cardboard box", "cracker box")))
    with pytest.raises(ValueError, match="not laid out"):
        EvalTask(command="Take the larger box.", target_object="cardboard box",
                 choice=SizeChoice(select="largest", among=("cardboard box", "cracker box")))
    t = EvalTask.model_validate({"command": "Climb, then grab the cup.", "target_object": "red cup",
                                 "motions": [{"skill": "up"}], "choice": None})
    assert t.motions == (M("up"),)


def test_every_dev_choice_line_is_decided_by_its_own_layouts_as_the_line_expects() -> None:
    """The sequential dev lines all say which motions they ask for; each size or conditional line's choice, decided
    by the simulator on the layouts the run gives it, names the line's target (the two lines of a conditional lay
    out one branch each)."""
    from aermani.evaluation.runner import RunConfig, episode_specs

    suites = load_suites(split="dev")
    assert all(t.motions for t in suites["sequential"] if t.expect == "success")
    choices = [t for ts in suites.values() for t in ts if t.choice is not None]
    assert {t.choice.kind for t in choices} == {"size", "conditional"}
    specs = [s for s in episode_specs(RunConfig(out=Path("."), split="dev")) if s.task.choice is not None]
    assert len(specs) == 2 * len(choices)
    for spec in specs:
        assert spec.task.choice is not None
        answer, why = decide(spec.task.choice, _world(spec.task.scenario(spec.seed)))
        assert answer == (spec.task.target_object,), (spec.task.command, spec.seed, why)


def test_a_round_table_is_not_the_table() -> None:
    from aermani.evaluation.scoring import _same

    assert _same("the round table", "round table") and _same("Cracker  Box", "cracker box")
    assert not _same("round table", "table") and not _same("table", "round table")
    assert not _same("red cup", "cup")


def test_an_approach_asked_after_a_motion_must_come_after_it() -> None:
    from shared.messages import Pose, ReasoningStep, SimObjectTruth, SkillOutcome, SkillState, SkillToExecute, Vec3

    def pose(x: float) -> Pose:
        return Pose(position=Vec3(x=x, z=1.5), yaw=math.pi)  # facing -x: forward moves away from the table

    away = ReasoningStep(task_id="t", step=1, ste=SkillToExecute(skill="forward"), skill_state=SkillState.SUCCEEDED,
                         outcome=SkillOutcome(start_pose=pose(0.0), end_pose=pose(-2.5)))
    table = SimObjectTruth(name="table", category="surface", position=Vec3(x=1.5, z=0.375),
                           size=Vec3(x=1.2, y=0.8, z=0.75))
    world = JudgeResult(objects=(table,))
    assert check_motions([M("approach", to="table"), M("forward")], [away], world).ok  # near it, then away
    got = check_motions([M("forward"), M("approach", to="table")], [away], world)
    assert not got.ok and "within 3.40 m of it at best" in got.detail, got.detail
