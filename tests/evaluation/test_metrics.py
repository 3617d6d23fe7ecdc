"""The paper's metrics on hand-made traces, with exact expected numbers."""

from __future__ import annotations

import math

import pytest

from aermani.evaluation.metrics import (
    Action,
    actions_of,
    compute,
    futile_loops,
    oscillations,
    percentile,
    query_counts,
    redundancy_ratio,
    redundant_actions,
    repeated_localizations,
    zero_net_sequences,
)
from aermani.evaluation.records import EpisodeRecord
from aermani.evaluation.report import _endings_section
from aermani.evaluation.runner import success_verdict
from aermani.evaluation.tasks import EvalTask
from shared.messages import (
    ModelCall,
    Pose,
    ReasoningStep,
    SkillOutcome,
    SkillState,
    SkillToExecute,
    TaskState,
    TaskStatus,
    Vec3,
)

TASK = EvalTask(command="Pick up the red cup and place it on the table.", suite="localization",
                target_object="red cup", destination="table")


def acts(*names: str) -> list[Action]:
    out = []
    for n in names:
        skill, _, arg = n.partition(":")
        out.append(Action(skill, arg or None))
    return out


def step(i: int, skill: str | None, arg: str | None = None, *, calls=((True, 0.5),), state=SkillState.SUCCEEDED,
         start: Pose | None = None, end: Pose | None = None) -> ReasoningStep:
    return ReasoningStep(
        task_id="t", step=i,
        calls=tuple(ModelCall(raw_answer="{}", valid=v, latency_s=lat) for v, lat in calls),
        ste=SkillToExecute(skill=skill, argument=arg) if skill else None, valid=skill is not None,
        skill_state=state if skill else None,
        outcome=SkillOutcome(start_pose=start, end_pose=end) if (start or end) else None,
    )


def record(eid: str, success: bool, steps: list[ReasoningStep], duration_s: float = 10.0, **kw) -> EpisodeRecord:
    status = TaskStatus(task_id="t", command=TASK.command, state=TaskState.SUCCEEDED if success else
                        TaskState.FAILED, steps=len(steps), started_ns=1_000_000_000,
                        ended_ns=1_000_000_000 + int(duration_s * 1e9))
    return EpisodeRecord(episode_id=eid, suite="localization", backend="rules", variant="full", task=TASK, seed=1,
                         state=status.state.value, success=success, steps=steps, status=status, **kw)


# ---------------------------------------------------------------- ARR rules


def test_oscillation_within_two_motions_marks_both():
    a = acts("forward", "yaw_left", "backward", "obj_localization:red cup", "grasp")
    assert oscillations(a) == {0, 2}


def test_oscillation_beyond_two_motions_is_not_redundant():
    a = acts("forward", "yaw_left", "up", "backward")
    assert oscillations(a) == set()


def test_oscillation_chain():
    assert oscillations(acts("left", "right", "left")) == {0, 1, 2}


def test_zero_net_square_without_poses():
    # forward, left, backward, right: back at the start whatever the step sizes; no pair is adjacent-opposite
    a = acts("forward", "left", "backward", "right", "obj_localization:cup")
    assert oscillations(a) == {0, 1, 2, 3}  # each leg is undone two motions later
    assert zero_net_sequences(a) == {0, 1, 2, 3}


def test_zero_net_square_with_separated_legs():
    # forward, left, up, backward, right, down: no opposite within two motions, still zero net
    a = acts("forward", "left", "up", "backward", "right", "down")
    assert oscillations(a) == set()
    assert zero_net_sequences(a) == set(range(6))


def test_zero_net_needs_consecutive_motions():
    # a localization between the legs breaks the run: rule 2 does not apply
    a = acts("forward", "left", "obj_localization:cup", "backward", "right")
    assert zero_net_sequences(a) == set()


def test_zero_net_yaw_turn_is_not_zero_without_poses():
    # forward, yaw_left, backward does not return to the start for a generic yaw step
    assert zero_net_sequences(acts("forward", "yaw_left", "backward")) == set()
    # a full turn around with the same number of left and right yaws does
    assert zero_net_sequences(acts("yaw_left", "yaw_left", "yaw_right", "yaw_right")) == {0, 1, 2, 3}


def test_zero_net_from_trajectory_poses():
    p = lambda x, y, yaw=0.0: Pose(position=Vec3(x=x, y=y, z=1.5), yaw=yaw)  # noqa: E731
    # forward, yaw_left, forward, yaw_left ... poses say it came back within 5 cm (tolerance 10 cm)
    a = [Action("forward", None, p(0, 0), p(1, 0)),
         Action("yaw_left", None, p(1, 0), p(1, 0, math.pi / 2)),
         Action("forward", None, p(1, 0, math.pi / 2), p(1, 1, math.pi / 2)),
         Action("yaw_left", None, p(1, 1, math.pi / 2), p(1, 1, math.pi)),
         Action("forward", None, p(1, 1, math.pi), p(0.03, 1.0, math.pi)),
         Action("yaw_left", None, p(0.03, 1.0, math.pi), p(0.03, 1.0, -math.pi / 2)),
         Action("forward", None, p(0.03, 1.0, -math.pi / 2), p(0.03, 0.04, -math.pi / 2)),
         Action("yaw_left", None, p(0.03, 0.04, -math.pi / 2), p(0.03, 0.04, 0.02)),
         Action("obj_localization", "cup", p(0.03, 0.04), p(0.03, 0.04))]
    assert zero_net_sequences(a) == set(range(8))
    # but the same motions ending 30 cm away are not redundant
    far = [*a[:6], Action("forward", None, a[6].start_pose, p(0.3, 0.0, -math.pi / 2)), a[7]]
    far[7] = Action("yaw_left", None, p(0.3, 0.0, -math.pi / 2), p(0.3, 0.0, 0.0))
    assert zero_net_sequences(far) == set()


def test_repeated_localization_without_motion():
    a = acts("obj_localization:red cup", "placement_localization:table", "obj_localization:Red  Cup",
             "forward", "obj_localization:red cup", "grasp", "placement_localization:table",
             "placement_localization:table")
    assert repeated_localizations(a) == {2, 7}


def test_rejected_skill_does_not_change_the_view():
    a = [Action("placement_localization", "shelf", state="succeeded"), Action("place", None, state="rejected"),
         Action("placement_localization", "shelf", state="succeeded"), Action("forward", None, state="rejected"),
         Action("placement_localization", "shelf", state="succeeded"), Action("place", None, state="failed"),
         Action("placement_localization", "shelf", state="succeeded")]
    assert repeated_localizations(a) == {2, 4}


def test_redundant_union_counts_each_action_once():
    # forward/backward is both an oscillation and a zero-net pair: 2 redundant actions, not 4
    a = acts("forward", "backward", "obj_localization:cup", "obj_localization:cup", "grasp")
    assert redundant_actions(a) == {0, 1, 3}
    assert redundancy_ratio(a) == pytest.approx(3 / 5)


def test_clean_pick_and_place_has_no_redundancy():
    a = acts("forward", "forward", "obj_localization:red cup", "grasp", "yaw_left", "placement_localization:table",
             "place")
    assert redundant_actions(a) == set()
    assert redundancy_ratio([]) == 0.0


def test_actions_skip_done_and_unexecuted_steps():
    steps = [step(1, "forward"), step(2, None, calls=((False, 0.4), (False, 0.4))), step(3, "done")]
    assert [a.skill for a in actions_of(steps)] == ["forward"]


# ---------------------------------------------------------------- aggregate metrics


def test_percentile_linear_interpolation():
    xs = [1.0, 2.0, 3.0, 4.0]
    assert percentile(xs, 50) == pytest.approx(2.5)
    assert percentile(xs, 95) == pytest.approx(3.85)
    assert percentile([7.0], 95) == 7.0


def test_compute_on_hand_made_episodes():
    ep1 = record("e1", True, [  # 4 actions, forward/backward oscillation -> 2/4 redundant; 4 calls, 1 invalid
        step(1, "forward", calls=((True, 1.0),)),
        step(2, "backward", calls=((False, 2.0), (True, 3.0))),
        step(3, "obj_localization", "red cup", calls=((True, 4.0),)),
        step(4, "grasp", calls=()),
        step(5, "done", calls=()),
    ], duration_s=20.0)
    ep2 = record("e2", True, [  # 3 actions, none redundant; 2 calls valid
        step(1, "obj_localization", "red cup", calls=((True, 5.0),)),
        step(2, "grasp", calls=((True, 6.0),)),
        step(3, "place", calls=()),
    ], duration_s=40.0)
    ep3 = record("e3", False, [  # failure: 2 steps, 2 invalid calls; its actions do not count for ARR
        step(1, "left", calls=((False, 7.0),)),
        step(2, "right", calls=((False, 8.0),)),
    ], duration_s=600.0)
    m = compute([ep1, ep2, ep3])
    assert m.episodes == 3 and m.successes == 2
    assert m.sr == pytest.approx(200 / 3)
    assert m.arr == pytest.approx(100 * (0.5 + 0.0) / 2)  # 25.0
    assert m.rs == pytest.approx((5 + 3 + 2) / 3)
    assert m.queries == 8 and m.invalid == 3
    assert m.iar == pytest.approx(37.5)
    assert m.rt_median == pytest.approx(4.5)  # latencies 1..8
    assert m.rt_p95 == pytest.approx(7.65)
    assert m.tt == pytest.approx(30.0)


def test_compute_leaves_out_episodes_the_harness_could_not_run():
    ok = record("e1", True, [step(1, "obj_localization", "red cup"), step(2, "grasp")])
    broken = EpisodeRecord(episode_id="e2", suite="localization", backend="rules", variant="full", task=TASK, seed=2,
                           harness_error="sim/reset failed")
    m = compute([ok, broken])
    assert (m.episodes, m.not_run, m.sr, m.rs) == (1, 1, 100.0, 2.0)


def test_compute_without_success_or_calls():
    m = compute([record("e1", False, [step(1, "forward", calls=())])])
    assert m.sr == 0.0 and m.arr is None and m.tt is None and m.iar is None and m.rt_median is None
    assert compute([]).sr is None


def test_rs_counts_steps_announced_by_the_status_when_samples_were_lost():
    rec = record("e1", True, [step(1, "grasp")])
    rec = rec.model_copy(update={"status": rec.status.model_copy(update={"steps": 4})})
    assert compute([rec]).rs == 4.0


# ---------------------------------------------------------------- issue 14: displacement, futile loops, IAR, SR


def _p(x: float, y: float, yaw: float = 0.0, z: float = 1.5) -> Pose:
    return Pose(position=Vec3(x=x, y=y, z=z), yaw=yaw)


def test_oscillation_is_judged_by_net_displacement_when_poses_are_logged():
    # forward then backward, but the backward step was blocked (the vehicle stayed 0.5 m ahead): not undone
    blocked = [Action("forward", None, _p(0, 0), _p(0.5, 0), "succeeded"),
               Action("backward", None, _p(0.5, 0), _p(0.48, 0), "succeeded")]
    assert oscillations(blocked) == set()
    # forward then left after a yaw of 180 degrees would not be "opposite" by name, but here a left step
    # carried the vehicle back to where the forward step began: the motion was undone
    undone = [Action("forward", None, _p(0, 0), _p(0.5, 0), "succeeded"),
              Action("left", None, _p(0.5, 0, -math.pi / 2), _p(0.02, 0, -math.pi / 2), "succeeded")]
    assert oscillations(undone) == {0, 1}
    # a motion that did not move the vehicle is not "undone" by the next one
    stuck = [Action("up", None, _p(0, 0), _p(0, 0), "failed"),
             Action("down", None, _p(0, 0), _p(0, 0, z=1.0), "succeeded")]
    assert oscillations(stuck) == set()


def test_oscillation_by_displacement_includes_yaw():
    turned = [Action("yaw_left", None, _p(0, 0, 0.0), _p(0, 0, 0.5), "succeeded"),
              Action("yaw_right", None, _p(0, 0, 0.5), _p(0, 0, 0.05), "succeeded")]
    assert oscillations(turned) == {0, 1}
    half = [Action("yaw_left", None, _p(0, 0, 0.0), _p(0, 0, 0.5), "succeeded"),
            Action("yaw_right", None, _p(0, 0, 0.5), _p(0, 0, 0.3), "succeeded")]
    assert oscillations(half) == set()


def test_futile_loop_counts_the_repeats_of_a_failing_skill_with_no_change_of_state():
    a = [Action("grasp", "red cup", _p(1, 0), _p(1, 0), "failed"),
         Action("grasp", "Red Cup", _p(1, 0), _p(1, 0), "failed"),
         Action("grasp", "red cup", _p(1, 0), _p(1, 0), "rejected")]
    assert futile_loops(a) == {1, 2}
    assert redundant_actions(a) == {1, 2}
    assert redundancy_ratio(a) == pytest.approx(2 / 3)


def test_futile_loop_needs_no_change_between_the_failures():
    moved = [Action("grasp", "red cup", _p(1, 0), _p(1, 0), "failed"),
             Action("forward", None, _p(1, 0), _p(1.3, 0), "succeeded"),
             Action("grasp", "red cup", _p(1.3, 0), _p(1.3, 0), "failed")]
    assert futile_loops(moved) == set()
    # the vehicle drifted 40 cm between the two failures (no skill succeeded): the state changed
    drifted = [Action("grasp", "red cup", _p(1, 0), _p(1, 0), "failed"),
               Action("grasp", "red cup", _p(1.4, 0), _p(1.4, 0), "failed")]
    assert futile_loops(drifted) == set()
    # another argument is another attempt; a repeat that succeeds was not futile
    other = [Action("obj_localization", "red cup", None, None, "failed"),
             Action("obj_localization", "purple cup", None, None, "failed"),
             Action("obj_localization", "red cup", None, None, "succeeded")]
    assert futile_loops(other) == set()
    held = [Action("place", "table", None, None, "failed", held="red cup"),
            Action("place", "table", None, None, "failed", held=None)]
    assert futile_loops(held) == set()


def test_futile_loop_from_step_records():
    fail = SkillState.FAILED
    steps = [step(1, "grasp", "red cup", state=fail, start=_p(1, 0), end=_p(1, 0)),
             step(2, "grasp", "red cup", state=fail, start=_p(1, 0), end=_p(1, 0)),
             step(3, "done")]
    assert futile_loops(actions_of(steps)) == {1}


def test_iar_counts_an_invalid_answer_followed_by_a_transport_error():
    # step 1: valid; step 2: an invalid answer, then the re-prompt hit a transport error (the loop records the
    # step with its calls and no skill); the status counted 3 queries, 1 invalid
    steps = [step(1, "obj_localization", "red cup", calls=((True, 0.5),)),
             ReasoningStep(task_id="t", step=2, calls=(ModelCall(raw_answer="{", valid=False, error="no JSON"),),
                           skill_message="model unavailable: 503")]
    rec = record("e1", False, steps)
    rec = rec.model_copy(update={"status": rec.status.model_copy(update={"model_calls": 2, "invalid_answers": 1})})
    assert query_counts(rec) == (1, 2)
    m = compute([rec])
    assert (m.invalid, m.queries, m.iar) == (1, 2, 50.0)
    # a lost step sample: the status counted an invalid answer the records do not hold
    lost = rec.model_copy(update={"steps": steps[:1], "status": rec.status.model_copy(
        update={"model_calls": 3, "invalid_answers": 2})})
    assert compute([lost]).iar == pytest.approx(200 / 3)


def test_sr_needs_the_end_state_and_the_judge():
    assert success_verdict("succeeded", True, "red cup rests on the table", 600) == (True, "red cup rests on the table")
    ok, why = success_verdict("failed", True, "red cup rests on the table", 600)
    assert not ok and "ended failed, not succeeded" in why
    ok, why = success_verdict("timeout", True, "red cup rests on the table", 600)
    assert not ok and "T_max (600 s)" in why
    assert success_verdict("succeeded", False, "red cup is in the gripper", 600)[0] is False
    both = record("e1", True, [step(1, "grasp")], judge_success=True)
    claimed = record("e2", True, [step(1, "grasp")], judge_success=False).model_copy(update={"success": False})
    placed = record("e3", False, [step(1, "grasp")], judge_success=True)
    m = compute([both, claimed, placed])
    assert (m.ended_succeeded, m.judged_success, m.successes) == (2, 2, 1)
    assert m.sr == pytest.approx(100 / 3)


def test_collisions_are_counted_per_episode():
    a = record("e1", True, [step(1, "grasp")], collisions=("vehicle-shelf", "vehicle-wall"))
    b = record("e2", False, [step(1, "grasp")])
    c = record("e3", False, [step(1, "forward")], collisions=("vehicle-table",))
    m = compute([a, b, c])
    assert (m.collisions, m.collision_episodes) == (3, 2)
    assert m.collisions_per_episode == pytest.approx(1.0)


def test_gripper_strikes_knocked_and_dropped_objects_are_collisions_counted_by_kind():
    a = record("e1", True, [step(1, "grasp")], collisions=("gripper-table", "knocked-red cup"))
    b = record("e2", False, [step(1, "grasp")], collisions=("dropped-apple", "vehicle-wall", "gripper-purple cup"))
    c = record("e3", True, [step(1, "grasp")])  # a clean one
    old = record("e4", False, [step(1, "forward")], collisions=("vehicle-shelf",))  # before the gripper's tags
    m = compute([a, b, c, old])
    assert (m.collisions, m.collision_episodes) == (6, 3)
    assert (m.vehicle_collisions, m.gripper_strikes, m.knocked_objects, m.dropped_objects) == (2, 2, 1, 1)
    assert compute([c]).collisions == 0 and compute([c]).gripper_strikes == 0
    # The report's table counts each kind in its own column.
    table = next(line for line in _endings_section([a, b, c, old], [("rules", "full")], False)
                 if line.startswith("| ") and not line.startswith("| Method"))
    cells = [x.strip() for x in table.strip("|").split("|")]
    assert cells[7].startswith("6 ") and cells[8:13] == ["2", "2", "1", "1", "3"], cells


def test_displacement_rules_from_step_records():
    """The trajectory log as recorded: poses in the skills' outcomes of real ReasoningStep messages."""
    steps = [step(1, "forward", start=_p(0, 0), end=_p(0.5, 0)),
             step(2, "obj_localization", "red cup", state=SkillState.FAILED, start=_p(0.5, 0), end=_p(0.5, 0)),
             step(3, "backward", start=_p(0.5, 0), end=_p(0.01, 0)),  # undoes step 1 (one motion later)
             step(4, "yaw_left", start=_p(0.01, 0), end=_p(0.01, 0, 0.6)),
             step(5, "obj_localization", "red cup", start=_p(0.01, 0, 0.6), end=_p(0.01, 0, 0.6)),
             step(6, "done")]
    a = actions_of(steps)
    assert [x.skill for x in a] == ["forward", "obj_localization", "backward", "yaw_left", "obj_localization"]
    assert oscillations(a) == {0, 2} and zero_net_sequences(a) == set()  # a localization sits between them
    assert futile_loops(a) == set() and redundant_actions(a) == {0, 2}
    assert compute([record("e1", True, steps)]).arr == pytest.approx(100 * 2 / 5)


def test_a_refused_command_is_a_failed_episode_not_an_excluded_one() -> None:
    """A command the policy refuses before takeoff is its answer: counted as a failure, never restarted or
    left out of the metrics (records written by older harnesses are read the same way)."""
    from aermani.evaluation.records import EpisodeRecord
    from aermani.evaluation.runner import _failed_before_first_step
    from aermani.evaluation.tasks import EvalTask
    from shared.messages import TaskState, TaskStatus

    task = EvalTask(command="tissue box -> shelf", suite="localization", target_object="tissue box",
                    destination="shelf")
    refused = TaskStatus(task_id="t", command=task.command, state=TaskState.FAILED, steps=0,
                         message="command refused before takeoff: I cannot understand it")
    rec = EpisodeRecord(episode_id="e", suite="localization", backend="rules", variant="full", task=task, seed=1,
                        status=refused)
    assert not _failed_before_first_step(rec)
    takeoff = rec.model_copy(update={"status": refused.model_copy(update={"message": "takeoff failed: no GPS"})})
    assert _failed_before_first_step(takeoff)
    old = EpisodeRecord.model_validate({**rec.model_dump(mode="json"), "attempts": 3, "harness_error":
                                        "failed before the first reasoning step 3 times: command refused before "
                                        "takeoff: I cannot understand it"})
    assert old.harness_error == "" and old.attempts == 3


def test_wilson_interval_at_the_edges_and_in_the_middle() -> None:
    from aermani.evaluation.metrics import wilson

    lo, hi = wilson(7, 10)
    assert round(lo, 1) == 39.7 and round(hi, 1) == 89.2  # the textbook value for 7/10
    assert wilson(10, 10)[1] == 100.0 and round(wilson(10, 10)[0], 1) == 72.2
    assert wilson(0, 10)[0] == 0.0 and round(wilson(0, 10)[1], 1) == 27.8
    lo, hi = wilson(80, 100)
    assert lo < 80.0 < hi and hi - lo < wilson(8, 10)[1] - wilson(8, 10)[0]  # more episodes, narrower


def test_tt_in_simulated_seconds_beside_the_wall_clock():
    """TT on the wall clock mixes sped-up simulated time with real waits; the simulator's clock (read from the
    judge just before the start and just after the end) gives TT in simulated seconds, over successes only."""
    a = record("e1", True, [step(1, "grasp")], duration_s=10.0, sim_started_s=2.0, sim_ended_s=42.0)
    b = record("e2", True, [step(1, "grasp")], duration_s=20.0, sim_started_s=1.5, sim_ended_s=61.5)
    c = record("e3", False, [step(1, "grasp")], duration_s=50.0, sim_started_s=0.0, sim_ended_s=500.0)
    m = compute([a, b, c])
    assert m.tt == pytest.approx(15.0) and m.tt_sim == pytest.approx(50.0)
    old = record("e4", True, [step(1, "grasp")], duration_s=30.0)  # a record from before the clock was kept
    assert old.sim_duration_s is None and compute([old]).tt_sim is None
    assert compute([a, old]).tt_sim == pytest.approx(40.0) and compute([a, old]).tt == pytest.approx(20.0)


def test_collisions_are_counted_by_kind_from_the_judge_s_answer():
    """The runner keeps the judge's `collisions` as they come; the metrics and the report's end-state table count
    every entry by its kind (airframe, gripper strikes, knocked and dropped objects)."""
    from aermani.evaluation.report import _endings_section
    from shared.messages import JudgeResult

    answers = [JudgeResult(held="red cup", collisions=("vehicle-shelf", "gripper-table", "knocked-red cup")),
               JudgeResult(collisions=("dropped-coke can", "vehicle-wall")), JudgeResult()]
    recs = [record(f"e{i}", i == 0, [step(1, "grasp")], judge=j, collisions=j.collisions)
            for i, j in enumerate(answers)]
    m = compute(recs)
    assert (m.collisions, m.vehicle_collisions, m.gripper_strikes, m.knocked_objects, m.dropped_objects,
            m.collision_episodes) == (5, 2, 1, 1, 1, 2)
    row = next(line for line in _endings_section(recs, [("rules", "full")], False) if line.startswith("| rules"))
    assert "| 5 (1.67 per episode) | 2 | 1 | 1 | 1 | 2 |" in row, row
    assert row.startswith("| rules (non-VLM baseline) | 3 | 1 | 1 | 0 | 1 | 0 | 5 "), row
    assert compute([recs[2]]).collisions == 0
