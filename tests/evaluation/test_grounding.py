"""The grounding check on hand-built steps: each kind of statement, matched with the perception's vocabulary."""

from __future__ import annotations

from aermani.evaluation.grounding import StepObservation, check_step, check_steps, violation_rate
from shared.messages import DescriptiveReasoningTrace, Detection, ReasoningStep, SkillToExecute, Vec3


def step(n: int = 1, *, image: str | None = None, summary: str | None = None,
         reasoning: str | None = None) -> ReasoningStep:
    return ReasoningStep(task_id="t", step=n, drt=DescriptiveReasoningTrace(
        image_description=image, summary=summary, reasoning=reasoning,
        action_predictions={"grasp": "I will be holding the green bottle"}),
        ste=SkillToExecute(skill="obj_localization", argument="red cup"), valid=True)


def seen(*labels: str, held: str | None = None, holding: bool | None = None,
         positions: tuple[tuple[str, float, float, float], ...] = ()) -> StepObservation:
    return StepObservation(detections=tuple(Detection(label=lab) for lab in labels), held_object=held,
                           memory_known=True, gripper_holding=holding, position=Vec3(z=1.5), positions=positions)


def kinds(g) -> list[str]:
    return [v.kind for v in g.violations]


def test_objects_said_seen_are_matched_with_the_perception_vocabulary() -> None:
    obs = seen("red cup", "round table")
    assert kinds(check_step(step(image="A red mug stands on the round table."), obs)) == []  # mug = cup
    assert kinds(check_step(step(image="Perception reports: red cup, table."), obs)) == []
    g = check_step(step(image="I see a purple cup and a green bottle near the table."), obs)
    assert kinds(g) == ["not_detected", "not_detected"] and g.claims == 3
    assert "'purple cup'" in g.violations[0].reason and "'green bottle'" in g.violations[1].reason
    # a cup is a cup whatever its colour when none is named; "soda" is a family covering the coke can
    assert kinds(check_step(step(image="There is a cup."), obs)) == []
    assert kinds(check_step(step(image="A soda is on the shelf."), seen("coke can", "shelf"))) == []


def test_absence_and_the_held_object_and_other_fields() -> None:
    obs = seen("red cup", held="purple cup", holding=True)
    assert kinds(check_step(step(image="The purple cup hangs below, the red cup ahead."), obs)) == []
    assert kinds(check_step(step(image="No red cup is in view."), obs)) == ["detected_but_denied"]
    assert kinds(check_step(step(image="I do not see a banana."), obs)) == []
    # the reasoning's objects are statements of seeing only with a word of seeing
    assert kinds(check_step(step(reasoning="Localize the banana before grasping."), obs)) == []
    assert kinds(check_step(step(reasoning="I can see the banana."), obs)) == ["not_detected"]


def test_what_the_gripper_holds() -> None:
    empty = seen("red cup", holding=False)
    g = check_step(step(summary="1 skills executed; last grasp -> succeeded. Holding: red cup."), empty)
    assert kinds(g) == ["holds_nothing"] and "gripper telemetry: empty" in g.violations[0].reason
    assert kinds(check_step(step(summary="Holding: nothing."), empty)) == []
    assert kinds(check_step(step(reasoning="Once grasped I will be holding the red cup."), empty)) == []
    held = seen("table", held="red cup", holding=True)
    assert kinds(check_step(step(reasoning="Holding the red cup; place it."), held)) == []
    assert kinds(check_step(step(reasoning="I am holding the mug."), held)) == []
    assert kinds(check_step(step(reasoning="The gripper is empty."), held)) == ["holds_something"]
    assert kinds(check_step(step(reasoning="I am carrying the green bottle."), held)) == ["holds_other"]
    # memory alone (no telemetry) decides when the gripper does not report contact
    assert kinds(check_step(step(summary="Holding: red cup."), seen("table"))) == ["holds_nothing"]


def test_stated_positions() -> None:
    obs = seen("red cup", positions=(("red cup", 1.2, 0.3, 0.8),))
    assert kinds(check_step(step(reasoning="The red cup is at (1.25, 0.30, 0.78)."), obs)) == []
    g = check_step(step(reasoning="The red cup is at (3.00, -1.00, 0.80)."), obs)
    assert kinds(g) == ["position"] and "2.22 m away" in g.violations[0].reason
    assert kinds(check_step(step(reasoning="It was seen earlier at (9.0, 9.0)."), obs)) == []
    assert kinds(check_step(step(reasoning="The banana is at (9.0, 9.0)."), obs)) == []  # nothing measured


def test_unchecked_steps_and_the_rate() -> None:
    no_drt = ReasoningStep(task_id="t", step=2, ste=SkillToExecute(skill="forward"), valid=True)
    results = check_steps([(step(1, image="A green bottle."), seen("red cup")), (no_drt, seen()),
                           (step(3, image="A red cup."), seen("red cup")), (step(4, image="x"), None)])
    assert [r.checked for r in results] == [True, False, True, False]
    assert violation_rate(results) == 50.0
    assert violation_rate([]) is None
