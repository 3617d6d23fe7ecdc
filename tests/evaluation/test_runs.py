"""Reading what a step measured back from its prompt (evaluation records), and the step comparison of `diff`."""

from __future__ import annotations

from aermani.evaluation.diff import compare_tasks
from aermani.evaluation.runs import RunStep, RunTask, observation_from_prompt
from services.reasoner.prompt import History, HistoryEntry, Observation
from shared.messages import (
    Detection,
    MemoryObject,
    OutcomeCode,
    ReasoningStep,
    SkillFacts,
    SkillOutcome,
    SkillState,
    SkillToExecute,
    Vec3,
    VehicleState,
    WorkingMemory,
)


def test_the_prompt_history_reads_back_as_the_measurements_it_was_written_from() -> None:
    """The reader follows the reasoner's own rendering (services/reasoner/prompt.py): rendered here, read back."""
    memory = WorkingMemory(objects=(MemoryObject(label="red cup", position=Vec3(x=1.2, y=0.3, z=0.8)),),
                           placements=(MemoryObject(label="round table", position=Vec3(x=2.0, y=-1.0, z=0.75)),),
                           held_object="red cup", visible=("round table",))
    obs = Observation(state=VehicleState(position=Vec3(x=0.5, y=-0.25, z=1.5)),
                      detections=(Detection(label="round table", category="surface", size=Vec3(x=1, y=1, z=0.7),
                                            centroid=Vec3(x=2.0, y=-1.0, z=0.4)), Detection(label="coke can")),
                      memory=memory)
    history = History()
    history.append(HistoryEntry(1, "grasp", "red cup", "succeeded", "grasped"))
    got = observation_from_prompt(history.render(obs))
    assert got is not None and got.source == "prompt"
    assert [d.label for d in got.detections or ()] == ["round table", "coke can"]
    assert got.held_object == "red cup" and got.memory_known
    assert got.position is not None and (got.position.x, got.position.y, got.position.z) == (0.5, -0.25, 1.5)
    assert got.positions == (("red cup", 1.2, 0.3, 0.8), ("round table", 2.0, -1.0, 0.75))
    assert got.gripper_holding is None  # no previous skill read the gripper

    empty = observation_from_prompt(History().render(Observation()))
    assert empty is not None and empty.detections == () and empty.held_object is None and empty.position is None
    assert observation_from_prompt("1. grasp(red cup) -> succeeded") is None  # the paper's History: no live part
    # the previous skill's gripper reading is the telemetry of this step's observation
    prev = ReasoningStep(task_id="t", step=1, outcome=SkillOutcome(
        code=OutcomeCode.SUCCEEDED, facts=SkillFacts(gripper_width_m=0.0, holding=None)))
    read = observation_from_prompt(History().render(Observation()), prev)
    assert read is not None and read.gripper_holding is False


def _step(n: int, skill: str, arg: str | None = None, code: OutcomeCode = OutcomeCode.SUCCEEDED) -> RunStep:
    return RunStep(ReasoningStep(task_id="t", step=n, ste=SkillToExecute(skill=skill, argument=arg), valid=True,
                                 skill_state=SkillState.SUCCEEDED, outcome=SkillOutcome(code=code)), None)


def test_steps_differ_by_skill_argument_or_outcome_and_the_first_is_the_divergence() -> None:
    a = RunTask("a", "a", "cmd", "rules", "full", "succeeded",
                [_step(1, "obj_localization", "Red  Cup"), _step(2, "grasp", "red cup"), _step(3, "forward")])
    b = RunTask("b", "b", "cmd", "rules", "full", "failed",
                [_step(1, "obj_localization", "red cup"), _step(2, "grasp", "red cup", OutcomeCode.MISSED),
                 _step(3, "forward"), _step(4, "done")])
    d = compare_tasks(a, b)
    assert [(p.step, p.differs, p.why, p.divergence) for p in d.steps] == [
        (1, False, "", False), (2, True, "outcome", True), (3, False, "", False), (4, True, "only in B", False)]
    assert d.first_divergence == 2
    assert compare_tasks(a, a).first_divergence is None
