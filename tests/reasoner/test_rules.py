"""The rules policy on scripted worlds for each of the paper's four suites, through the real loop and parser."""

from __future__ import annotations

import asyncio
import math

import pytest

from services.reasoner.backends.base import PastStep, PolicyContext, Seen
from services.reasoner.backends.rules import (
    RulesBackend,
    RulesPolicy,
    parse_command,
    render_answer,
)
from services.reasoner.loop import TaskRunner, policy_context
from services.reasoner.parse import parse_answer
from services.reasoner.prompt import History, PromptCompiler
from services.reasoner.settings import ReasonerSettings
from shared.messages import VARIANTS, OutcomeCode, SkillFacts, TaskRequest, TaskState
from tests.reasoner.fake_world import MiniWorld, MiniWorldPort, Thing
from tests.reasoner.prompt_reader import answer_for_prompt

TABLE = Thing("table", "surface", headings=(0, 1, 7), size=(1.2, 0.8, 0.75))


def run_task(command: str, world: MiniWorld, variant: str = "full", **settings: object):
    settings.setdefault("max_steps", 40)
    s = ReasonerSettings(variant=variant, **settings)
    steps, statuses = [], []
    runner = TaskRunner(TaskRequest(command=command), s, RulesBackend(), MiniWorldPort(world),
                        publish_step=steps.append, publish_status=statuses.append)
    final = asyncio.run(runner.run(asyncio.Event()))
    return final, steps, statuses


def skills_of(world: MiniWorld) -> list[str]:
    return world.executed


def test_localization_pick_and_place() -> None:
    w = MiniWorld([Thing("red cup"), TABLE])
    final, steps, statuses = run_task("Pick up the red cup and place it on the table", w)
    assert final.state is TaskState.SUCCEEDED, final.message
    assert w.executed == ["takeoff", "obj_localization(red cup)", "grasp(red cup)", "placement_localization(table)",
                          "place", "done"]
    assert w.placed_on == {"red cup": "table"}
    assert statuses[0].state is TaskState.RUNNING and statuses[-1] is final
    assert all(s.valid and s.retries == 0 and s.drt.reasoning for s in steps)
    assert final.model_calls == len(steps) and final.invalid_answers == 0


def test_get_and_put_in() -> None:
    w = MiniWorld([Thing("coke can"), Thing("sink", "surface", headings=(2,))])
    final, *_ = run_task("Get the coke can and put it in the sink", w)
    assert final.state is TaskState.SUCCEEDED and w.placed_on == {"coke can": "sink"}
    assert w.executed.count("yaw_left") == 2  # searched for the sink after the grasp


def test_clutter_larger_box() -> None:
    w = MiniWorld([Thing("tissue box", size=(0.2, 0.1, 0.1)), Thing("cracker box", size=(0.3, 0.2, 0.1)),
                   Thing("red cup")])
    final, *_ = run_task("Of the two boxes, pick up the larger one.", w)
    assert final.state is TaskState.SUCCEEDED
    assert "obj_localization(cracker box)" in w.executed and w.held == "cracker box" and w.executed[-1] == "done"


def test_clutter_larger_box_by_the_catalogue_through_the_loop() -> None:
    # measured from afar the cardboard box (partly hidden) reads smaller; perception's catalogue knows better
    w = MiniWorld([Thing("cracker box", size=(0.16, 0.07, 0.21), catalog=(0.16, 0.07, 0.21)),
                   Thing("cardboard box", size=(0.05, 0.04, 0.08), catalog=(0.22, 0.16, 0.15))])
    final, *_ = run_task("Of the two boxes, pick up the larger one.", w)
    assert final.state is TaskState.SUCCEEDED and w.held == "cardboard box", w.executed


def test_clutter_smaller_and_ignore_tools() -> None:
    w = MiniWorld([Thing("tissue box", size=(0.2, 0.1, 0.1)), Thing("cracker box", size=(0.3, 0.2, 0.1))])
    run_task("of the two boxes pick up the smaller one", w)
    assert w.held == "tissue box"
    w = MiniWorld([Thing("hammer"), Thing("green bottle"), Thing("screwdriver")])
    final, *_ = run_task("Ignore the tools and pick up the green bottle.", w)
    assert final.state is TaskState.SUCCEEDED and w.held == "green bottle"
    assert not any("hammer" in e or "screwdriver" in e for e in w.executed)


def test_bring_me_a_snack() -> None:
    w = MiniWorld([Thing("hammer"), Thing("apple")])
    final, *_ = run_task("Bring me a snack", w)
    assert final.state is TaskState.SUCCEEDED and w.held == "apple"


def test_sequential_motions_then_pick() -> None:
    w = MiniWorld([Thing("tissue box", headings=(7,), needs_forward=2)])
    final, *_ = run_task("Move forward twice, turn right, and pick up the tissue box.", w)
    assert final.state is TaskState.SUCCEEDED
    assert w.executed[:4] == ["takeoff", "forward", "forward", "yaw_right"]
    assert w.executed[4:] == ["obj_localization(tissue box)", "grasp(tissue box)", "done"]


@pytest.mark.parametrize(("present", "expected"), [(("orange", "banana"), "orange"), (("banana",), "banana")])
def test_conditional(present: tuple[str, ...], expected: str) -> None:
    # The counter is detected 1.2 m away, within the approach radius: decide at once from what is seen.
    w = MiniWorld([Thing(p) for p in present] + [Thing("counter", "surface")])
    final, *_ = run_task("Approach the counter. If you see an orange, pick it up; otherwise grab the banana.", w)
    assert final.state is TaskState.SUCCEEDED and w.held == expected
    assert w.executed[1:] == [f"obj_localization({expected})", f"grasp({expected})", "done"]


COUNTER_CMD = "Approach the counter. If you see an orange, pick it up; otherwise grab the banana."


def _ctx(command: str, steps: list, **kw: object) -> PolicyContext:
    return PolicyContext(command=command, variant="full", skills=[], steps=steps, **kw)


def _motion(skill: str, x: float, y: float, yaw_deg: float) -> PastStep:
    return PastStep(skill, None, "succeeded", f"{skill} done: now at ({x:.2f}, {y:.2f}, 1.50), yaw {yaw_deg:.0f} deg",
                    pose=(x, y, math.radians(yaw_deg)))


def test_approach_turns_then_flies_until_close_then_decides() -> None:
    policy = RulesPolicy()
    where = {"counter": (4.0, 0.0)}
    # Facing away: turn toward the counter first.
    skill, *_ = policy.decide(_ctx(COUNTER_CMD, [], pose=(0.0, 0.0, math.pi / 2), positions=where))
    assert skill == "yaw_right"
    steps = [_motion("yaw_right", 0.0, 0.0, 45), _motion("yaw_right", 0.0, 0.0, 0)]
    skill, *_ = policy.decide(_ctx(COUNTER_CMD, steps, pose=(0.0, 0.0, 0.0), positions=where))
    assert skill == "forward"
    steps += [_motion("forward", 0.5 * i, 0.0, 0) for i in range(1, 5)]
    # 2.0 m away: still too far, even though an orange is already in view.
    seen = [Seen("orange", "object", 0.001, 2.1), Seen("banana", "object", 0.002, 2.2)]
    skill, *_ = policy.decide(_ctx(COUNTER_CMD, steps, pose=(2.0, 0.0, 0.0), positions=where, visible=seen))
    assert skill == "forward"
    steps.append(_motion("forward", 2.5, 0.0, 0))
    skill, arg, _ = policy.decide(_ctx(COUNTER_CMD, steps, pose=(2.5, 0.0, 0.0), positions=where, visible=seen))
    assert (skill, arg) == ("obj_localization", "orange")
    # Only the banana there: the otherwise branch, decided after the same approach.
    skill, arg, _ = policy.decide(_ctx(COUNTER_CMD, steps, pose=(2.5, 0.0, 0.0), positions=where, visible=seen[1:]))
    assert (skill, arg) == ("obj_localization", "banana")
    # A failed look for the orange there also means "otherwise".
    failed = [*steps, PastStep("obj_localization", "orange", "failed", "orange not visible", OutcomeCode.NOT_DETECTED)]
    skill, arg, _ = policy.decide(_ctx(COUNTER_CMD, failed, pose=(2.5, 0.0, 0.0), positions=where, visible=seen))
    assert (skill, arg) == ("obj_localization", "banana")


PLACE_CMD = "Pick up the red cup and place it on the table."
_PICKED = [PastStep("obj_localization", "red cup", "succeeded", "localized red cup at (1.00, 0.00, 0.80)",
                    found_at=(1.0, 0.0, 0.8)),
           PastStep("grasp", "red cup", "succeeded", "grasped the red cup; holding it at (0.30, 0.00, 1.50)",
                    facts=SkillFacts(target="red cup", holding="red cup")),
           PastStep("placement_localization", "table", "succeeded",
                    "found placement spot on the table at (2.00, 0.00, 0.78) (surface z 0.75)",
                    found_at=(2.0, 0.0, 0.78), surface_z=0.75)]


def test_place_released_but_unconfirmed_looks_then_finishes_or_regrasps() -> None:
    policy = RulesPolicy()
    lost = PastStep("place", None, "failed", "released the red cup over the table but could not see it there "
                                             "afterwards: red cup not visible", OutcomeCode.UNSTABLE)
    steps = [*_PICKED, lost]
    # Not holding any more: never loop on placement_localization + place; look for the object instead.
    skill, arg, _ = policy.decide(_ctx(PLACE_CMD, steps, pose=(2.0, -0.8, 1.57)))
    assert (skill, arg) == ("obj_localization", "red cup")
    on_table = PastStep("obj_localization", "red cup", "succeeded", "localized red cup at (2.08, 0.05, 0.81)",
                        found_at=(2.08, 0.05, 0.81))
    assert policy.decide(_ctx(PLACE_CMD, [*steps, on_table], pose=(2.0, -0.8, 1.57)))[0] == "done"
    on_floor = PastStep("obj_localization", "red cup", "succeeded", "localized red cup at (2.60, 0.50, 0.05)",
                        found_at=(2.6, 0.5, 0.05))
    skill, arg, _ = policy.decide(_ctx(PLACE_CMD, [*steps, on_floor], pose=(2.0, -0.8, 1.57),
                                       known_objects=["red cup"]))
    assert (skill, arg) == ("grasp", "red cup")


def test_place_off_spot_but_on_surface_is_done() -> None:
    off = PastStep("place", None, "failed", "released the red cup but it lies at (2.25, 0.05, 0.80), 0.25 m from "
                                            "the placement spot on the table", OutcomeCode.UNSTABLE,
                   found_at=(2.25, 0.05, 0.80))
    assert RulesPolicy().decide(_ctx(PLACE_CMD, [*_PICKED, off], pose=(2.0, -0.8, 1.57)))[0] == "done"


def test_a_place_that_left_the_object_fallen_over_ends_the_task_failed() -> None:
    # Dev episode localization/028: the cup toppled on release and lay on the sink; the task ended succeeded.
    # Lying there (or picked up again and set down the same way) it is not placed, and nothing stands it up.
    fallen = PastStep("place", None, "failed", "", OutcomeCode.UNSTABLE,
                      SkillFacts(target="table", upright=False), found_at=(2.05, 0.02, 0.79))
    d = RulesPolicy().decide_full(_ctx(PLACE_CMD, [*_PICKED, fallen], pose=(2.0, -0.8, 1.57)))
    assert d.skill == "done" and d.failure is not None and "fallen over" in d.failure, d
    standing = PastStep("place", None, "failed", "", OutcomeCode.UNSTABLE, SkillFacts(target="table", upright=True),
                        found_at=(2.05, 0.02, 0.79))
    d = RulesPolicy().decide_full(_ctx(PLACE_CMD, [*_PICKED, standing], pose=(2.0, -0.8, 1.57)))
    assert d.skill == "done" and d.failure is None, d


def test_failed_placement_localization_flies_toward_remembered_surface() -> None:
    cmd = "Find the purple cup and place it on the round table."
    steps = [PastStep("obj_localization", "purple cup", "succeeded", "localized purple cup at (2.10, -1.14, 0.81)"),
             PastStep("grasp", "purple cup", "succeeded", "grasped the purple cup"),
             PastStep("placement_localization", "round table", "failed", "round table seen but with too few depth "
                                                                          "points: no horizontal plane found")]
    where = {"round table": (-1.0, 2.5), "table": (2.0, -0.7)}
    seen = [Seen("round table", "surface", None, 3.7)]
    ctx = _ctx(cmd, steps, held="purple cup", pose=(1.0, -0.5, math.atan2(3.0, -2.0)), positions=where, visible=seen)
    assert RulesPolicy().decide(ctx)[0] == "forward"
    ctx = _ctx(cmd, [*steps, _motion("forward", -0.5, 1.5, 124)], held="purple cup",
               pose=(-0.5, 1.5, math.atan2(1.0, -0.5)), positions=where, visible=seen)
    assert RulesPolicy().decide(ctx)[:2] == ("placement_localization", "round table")


def test_search_out_of_view_then_place() -> None:
    w = MiniWorld([Thing("purple cup", headings=(3,)), Thing("round table", "surface", headings=(5,))])
    final, *_ = run_task("Find the purple cup and place it on the round table.", w)
    assert final.state is TaskState.SUCCEEDED and w.placed_on == {"purple cup": "round table"}
    # First a direct look on a fresh frame (perception's list lags at take-off), then the scan.
    assert w.executed[1:5] == ["obj_localization(purple cup)"] + ["yaw_left"] * 3


def test_failed_grasp_relocalizes() -> None:
    w = MiniWorld([Thing("red cup"), TABLE], fail_next={"grasp": 1})
    final, steps, _ = run_task("pick up the red cup and place it on the table", w)
    assert final.state is TaskState.SUCCEEDED
    assert w.executed[1:5] == ["obj_localization(red cup)", "grasp(red cup)", "obj_localization(red cup)",
                               "grasp(red cup)"]
    assert steps[1].skill_state.value == "failed"


def test_never_found_ends_not_found_before_the_step_cap() -> None:
    w = MiniWorld([TABLE])
    final, steps, _ = run_task("pick up the unicorn", w, max_steps=80)
    assert final.state is TaskState.FAILED and final.message.startswith("not found: the unicorn"), final.message
    assert len(steps) < 80 and steps[-1].ste.skill == "done"
    assert "forward" in w.executed and "grasp" not in " ".join(w.executed)


def test_step_cap_still_ends_a_task_that_cannot_finish() -> None:
    w = MiniWorld([TABLE])
    final, steps, _ = run_task("pick up the unicorn", w, max_steps=12)
    assert final.state is TaskState.FAILED and "12 steps" in final.message and len(steps) == 12


def test_ununderstood_command_is_refused_before_takeoff_and_any_skill() -> None:
    w = MiniWorld([Thing("red cup"), TABLE])
    final, steps, statuses = run_task("Sing me a song", w)
    assert final.state is TaskState.FAILED and final.message.startswith("command refused before takeoff")
    assert "Sing me a song" in final.message and "no motion" in final.message
    assert w.executed == [] and not w.airborne and steps == [] and final.model_calls == 0
    # The same refusal through the answer path, for a caller that skips the pre-check: a `done` with the reason.
    d = RulesPolicy().decide_full(_ctx("what's the weather", []))
    assert d.skill == "done" and d.failure and d.failure.startswith("refused:")


class Room:
    """A kinematic stand-in for the flight (yaw 45 deg, 0.5 m steps, walls at +-3.8 m) that reports poses as the
    executor's motions do; `hidden` things become visible within 1.6 m."""

    def __init__(self, hidden: dict[str, tuple[float, float]] | None = None) -> None:
        self.x, self.y, self.yaw = 0.3, -0.2, 0.0
        self.hidden = hidden or {}
        self.steps: list[PastStep] = []
        self.path: list[tuple[float, float]] = [(self.x, self.y)]

    def visible(self) -> list[Seen]:
        return [Seen(n, "object", 0.001, math.dist(p, (self.x, self.y))) for n, p in self.hidden.items()
                if math.dist(p, (self.x, self.y)) <= 1.6]

    def apply(self, skill: str, arg: str | None) -> None:
        state, msg, code = "succeeded", "", OutcomeCode.SUCCEEDED
        if skill in ("yaw_left", "yaw_right"):
            self.yaw += math.pi / 4 if skill == "yaw_left" else -math.pi / 4
        elif skill == "forward":
            nx, ny = self.x + 0.5 * math.cos(self.yaw), self.y + 0.5 * math.sin(self.yaw)
            if max(abs(nx), abs(ny)) > 3.8:
                state, msg, code = "rejected", "geofence 0.20 m ahead", OutcomeCode.OUT_OF_REACH
            else:
                self.x, self.y = nx, ny
        elif skill == "obj_localization":
            state, msg, code = "failed", f"{arg} not visible", OutcomeCode.NOT_DETECTED
        pose = None
        if skill in ("yaw_left", "yaw_right", "forward") and state == "succeeded":
            msg = f"{skill} done: now at ({self.x:.2f}, {self.y:.2f}, 1.50), yaw {math.degrees(self.yaw):.0f} deg"
            pose = (self.x, self.y, self.yaw)
        self.path.append((self.x, self.y))
        self.steps.append(PastStep(skill, arg, state, msg, code, pose=pose))

    def fly(self, command: str, max_steps: int = 80):
        policy = RulesPolicy()
        for _ in range(max_steps):
            ctx = _ctx(command, list(self.steps), pose=(self.x, self.y, self.yaw), visible=self.visible())
            d = policy.decide_full(ctx)
            if d.skill in ("done", "grasp") or (d.skill == "obj_localization" and self.visible()):
                return d
            self.apply(d.skill, d.argument)
        return None


def test_exploration_moves_through_the_room_then_reports_not_found() -> None:
    room = Room()
    d = room.fly("Could you look around and find the unicorn for me?")
    assert d is not None and d.skill == "done" and d.failure and d.failure.startswith("not found: the unicorn")
    assert len(room.steps) < 80
    start = room.path[0]
    assert max(math.dist(start, p) for p in room.path) >= 1.5  # moved, not only rotated
    skills = [s.skill for s in room.steps]
    assert skills.count("forward") >= 4 and skills.count("yaw_left") >= 7
    # Deterministic: the same context gives the same flight.
    again = Room()
    again.fly("Could you look around and find the unicorn for me?")
    assert [s.skill for s in again.steps] == skills


def test_exploration_finds_a_target_out_of_sight_of_the_start() -> None:
    room = Room(hidden={"red cup": (-1.7, 0.0)})
    d = room.fly("Pick up the red cup and place it on the table")
    assert d is not None and (d.skill, d.argument) == ("obj_localization", "red cup"), d
    assert math.dist((room.x, room.y), (-1.7, 0.0)) <= 1.6


@pytest.mark.parametrize("variant", VARIANTS)
def test_every_variant_answer_passes_the_validator(variant: str) -> None:
    w = MiniWorld([Thing("red cup"), TABLE])
    final, steps, _ = run_task("Pick up the red cup and place it on the table", w, variant=variant)
    assert final.state is TaskState.SUCCEEDED and final.invalid_answers == 0
    assert all(s.variant == variant for s in steps)


@pytest.mark.parametrize("variant", VARIANTS)
def test_policy_from_prompt_text_matches_direct_context(variant: str) -> None:
    """The fake VLM servers answer from the prompt text alone; they must agree with the in-process policy."""
    w = MiniWorld([Thing("cracker box", size=(0.3, 0.2, 0.1)), Thing("tissue box", size=(0.2, 0.1, 0.1)), TABLE])
    port = MiniWorldPort(w)
    lib = port.library
    h = History()
    from services.reasoner.prompt import HistoryEntry

    h.append(HistoryEntry(1, "yaw_left", None, "succeeded"))
    h.append(HistoryEntry(2, "obj_localization", "cracker box", "failed", "not visible"))
    obs = asyncio.run(port.observe(0))
    cmd = "of the two boxes pick up the larger one and place it on the table"
    prompt = PromptCompiler(variant, lib).compile(cmd, h, obs)
    ctx = policy_context(cmd, variant, lib, h, obs)
    from services.reasoner.backends.rules import RulesPolicy

    direct = render_answer(ctx, *RulesPolicy().decide(ctx))
    via_text = answer_for_prompt(prompt.text)
    if variant == "unstructured":  # no History in that prompt: only the decision's form is comparable
        assert parse_answer(via_text, variant, lib).ste.skill
    else:
        assert parse_answer(via_text, variant, lib).ste == parse_answer(direct, variant, lib).ste


def test_parse_command_suites() -> None:
    p = parse_command("Find the soda can on the table and bring it here")
    assert p.target == "soda can" and p.destination is None
    p = parse_command("Locate the cardboard box and bring it to the sink.")
    assert p.target == "cardboard box" and p.destination == "sink"
    p = parse_command("Move closer to the table, turn left, and pick up the cup")
    assert p.motions == ["forward", "yaw_left"] and p.target == "cup"


def test_out_of_reach_turns_toward_then_flies_closer_then_retries() -> None:
    from services.reasoner.backends.base import PastStep, PolicyContext
    from services.reasoner.backends.rules import RulesPolicy

    refused = PastStep("place", None, "rejected", "the placement spot on the table is 4.28 m away (reach 3.00 m): "
                                                  "move closer", OutcomeCode.OUT_OF_REACH,
                       SkillFacts(distance_m=4.28, reach_m=3.0))
    base = {"command": "pick up the red cup and place it on the table", "variant": "full", "skills": [],
            "held": "red cup", "known_placements": ["table"], "positions": {"table": (0.0, 4.0)}}
    steps = [PastStep("grasp", "red cup", "succeeded"), PastStep("placement_localization", "table", "succeeded"),
             refused]
    policy = RulesPolicy()
    assert policy.decide(PolicyContext(**base, steps=steps, pose=(0.0, 0.0, 0.0)))[0] == "yaw_left"
    assert policy.decide(PolicyContext(**base, steps=steps, pose=(0.0, 0.0, 1.57)))[0] == "forward"
    near = [*steps, PastStep("forward", None, "succeeded")]
    assert policy.decide(PolicyContext(**base, steps=near, pose=(0.0, 2.0, 1.57)))[0] == "place"


def test_approach_does_not_oscillate_around_a_yaw_step() -> None:
    # 25 deg off after a 45 deg turn: turning again would put it 20 deg off the other side, and back.
    where = {"counter": (4.0 * math.cos(math.radians(25)), 4.0 * math.sin(math.radians(25)))}
    steps = [_motion("yaw_right", 0.0, 0.0, 0)]
    assert RulesPolicy().decide(_ctx(COUNTER_CMD, steps, pose=(0.0, 0.0, 0.0), positions=where))[0] == "forward"


def test_larger_box_choice_survives_losing_sight_of_the_other() -> None:
    cmd = "Of the two boxes, pick up the larger one."
    both = [Seen("large box", "object", 0.02, 2.0), Seen("small box", "object", 0.005, 2.1)]
    policy = RulesPolicy()
    assert policy.decide(_ctx(cmd, [], visible=both))[:2] == ("obj_localization", "large box")
    lost = [PastStep("obj_localization", "large box", "failed", "large box not visible: no large box in view",
                     OutcomeCode.NOT_DETECTED)]
    # Only the small box in view now, and the large one remembered to the left: turn back, never take the small.
    skill, arg, _ = policy.decide(_ctx(cmd, lost, visible=both[1:], pose=(0.0, 0.0, 0.0),
                                       positions={"large box": (0.0, 2.0), "small box": (2.0, 0.0)}))
    assert (skill, arg) == ("yaw_left", None)
    skill, arg, _ = policy.decide(_ctx(cmd, [*lost, _motion("yaw_left", 0, 0, 45), _motion("yaw_left", 0, 0, 90)],
                                       visible=both[1:], pose=(0.0, 0.0, math.pi / 2),
                                       positions={"large box": (0.0, 2.0), "small box": (2.0, 0.0)}))
    assert (skill, arg) == ("obj_localization", "large box")


def test_larger_box_by_name_when_only_one_is_in_view() -> None:
    cmd = "Of the two boxes, pick up the larger one and place it on the table."
    policy = RulesPolicy()
    small = [Seen("small box", "object", 0.005, 2.0)]
    steps = [_motion("yaw_left", 0, 0, 45)]
    # Only the small one in view and none seen before: keep looking rather than take it.
    assert policy.decide(_ctx(cmd, steps, visible=small, pose=(0.0, 0.0, math.pi / 4)))[0] == "yaw_left"
    # The large one was seen behind: turn toward it.
    where = {"large box": (-2.0, 0.0), "small box": (1.4, 1.4)}
    assert policy.decide(_ctx(cmd, steps, visible=small, pose=(0.0, 0.0, math.pi / 4), positions=where))[0] == \
        "yaw_left"
    assert policy.decide(_ctx(cmd, steps, visible=small, pose=(0.0, 0.0, math.pi), positions=where))[:2] == \
        ("obj_localization", "large box")


def test_larger_box_by_catalogued_size_when_perception_knows_both_classes() -> None:
    # Dev clutter/000: at 2.3 m the cardboard box, half hidden behind the cracker box, measured smaller; their
    # classes' catalogued sizes (22 x 16 x 15 cm against 16 x 7 x 21 cm) say which is larger.
    cmd = "Of the two boxes, pick up the larger one."
    both = [Seen("cracker box", "object", 0.0030, 2.3, 0.16 * 0.07 * 0.21),
            Seen("cardboard box", "object", 0.0016, 2.4, 0.22 * 0.16 * 0.15)]
    policy = RulesPolicy()
    skill, arg, why = policy.decide(_ctx(cmd, [], visible=both))
    assert (skill, arg) == ("obj_localization", "cardboard box") and "catalogued" in why, why
    smaller = "Grab the smaller of the two boxes."
    assert policy.decide(_ctx(smaller, [], visible=both))[:2] == ("obj_localization", "cracker box")
    # Two of one class (or no catalogue): as measured.
    twins = [Seen("cracker box", "object", 0.0030, 2.3, 0.0024), Seen("cracker box 2", "object", 0.0020, 2.0, 0.0024)]
    assert policy.decide(_ctx(cmd, [], visible=twins))[:2] == ("obj_localization", "cracker box")
    assert policy.decide(_ctx(cmd, [], visible=[Seen(v.label, v.category, v.volume, v.distance) for v in both]))[:2] \
        == ("obj_localization", "cracker box")


def test_the_only_box_in_view_is_taken_for_the_larger_only_after_a_full_scan() -> None:
    # Dev clutter/044: one look into the scan it saw the cracker box, took "the only box I detect" and never saw
    # the larger one elsewhere in the room.
    cmd = "Pick up the larger box -- ignore the tissue box."
    one = [Seen("cracker box", "object", 0.0024, 2.9, 0.0024)]
    policy = RulesPolicy()
    turns = [_motion("yaw_left", 0.0, 0.0, 45 * (i + 1)) for i in range(7)]
    for k in range(7):
        skill, arg, why = policy.decide(_ctx(cmd, turns[:k], visible=one, pose=(0.0, 0.0, math.radians(45 * k))))
        assert (skill, arg) == ("yaw_left", None), (k, skill, arg, why)
    skill, arg, why = policy.decide(_ctx(cmd, turns, visible=one, pose=(0.0, 0.0, math.radians(315))))
    assert (skill, arg) == ("obj_localization", "cracker box") and "after a full scan" in why, why
    # Out of view when the scan ends, the one box it showed is chosen (and faced); the excluded one never is.
    where = {"cracker box": (0.0, -2.9), "tissue box": (2.0, 0.0)}
    skill, arg, why = policy.decide(_ctx(cmd, turns, visible=[], pose=(0.0, 0.0, 0.0), positions=where))
    assert skill == "yaw_right" and "only box a full scan showed" in why, (skill, why)


def test_approach_retries_one_blocked_forward_and_decides_after_two() -> None:
    where = {"counter": (4.0, 0.0)}
    blocked = PastStep("forward", None, "rejected", "obstacle 0.15 m ahead", OutcomeCode.BLOCKED)
    seen = [Seen("banana", "object", 0.002, 3.0)]
    policy = RulesPolicy()
    assert policy.decide(_ctx(COUNTER_CMD, [blocked], pose=(0.0, 0.0, 0.0), positions=where, visible=seen))[0] == \
        "forward"
    assert policy.decide(_ctx(COUNTER_CMD, [blocked, blocked], pose=(0.0, 0.0, 0.0), positions=where,
                              visible=seen))[:2] == ("obj_localization", "banana")


def test_demo_scenario_keeps_a_command_without_destination_without_one():
    # The demo judges "held" for such commands; the simulator's own choice of destination must not leak in.
    from aermani.demo import scenario_for

    sc, _ = scenario_for("ignore the tools and pick up the green bottle", None, None, 0)
    assert sc.target_object == "green bottle" and sc.destination is None
    sc, _ = scenario_for("pick up the red cup and place it on the table", None, None, 0)
    assert sc.destination == "table"


@pytest.mark.parametrize(("command", "dest"), [
    ("Could you bring the red cup over to the table?", "table"),
    ("Put the red cup onto the counter next to the sink", "counter"),
    ("I'd like you to grab the red cup that is on the table and drop it off in the sink", "sink"),
])
def test_paraphrased_commands_place_on_the_named_destination(command: str, dest: str) -> None:
    # Before the new reader these ended with the cup held and the task reported succeeded (or found nothing).
    w = MiniWorld([Thing("red cup"), TABLE, Thing("counter", "surface", headings=(2,)),
                   Thing("sink", "surface", headings=(3,))])
    final, *_ = run_task(command, w)
    assert final.state is TaskState.SUCCEEDED, final.message
    assert w.placed_on == {"red cup": dest} and w.held is None


# --------------------------------------------------------------------------- decisions come from codes, not prose


def _noisy(ctx: PolicyContext, seed: int) -> PolicyContext:
    """The same context with every executor message replaced by seeded noise (and one by a misleading phrase)."""
    import dataclasses
    import random

    rng = random.Random(seed)
    words = ["released", "lies at (9.00, 9.00, 9.00)", "reach 0.10 m", "away", "closer", "now at (5.00, 5.00, 1.50), "
             "yaw 90 deg", "surface z 3.00", "zzz", "grasped"]
    steps = [dataclasses.replace(s, message=" ".join(rng.choice(words) for _ in range(rng.randint(0, 6))))
             for s in ctx.steps]
    return dataclasses.replace(ctx, steps=steps)


def _scenarios() -> list[PolicyContext]:
    where = {"counter": (4.0, 0.0)}
    seen = [Seen("orange", "object", 0.001, 2.1), Seen("banana", "object", 0.002, 2.2)]
    approach = [_motion("yaw_right", 0.0, 0.0, 45), _motion("yaw_right", 0.0, 0.0, 0),
                *[_motion("forward", 0.5 * i, 0.0, 0) for i in range(1, 6)]]
    refused = PastStep("place", None, "rejected", "", OutcomeCode.OUT_OF_REACH,
                       SkillFacts(distance_m=4.28, reach_m=3.0))
    lost = PastStep("place", None, "failed", "", OutcomeCode.UNSTABLE)
    off = PastStep("place", None, "failed", "", OutcomeCode.UNSTABLE, found_at=(2.25, 0.05, 0.80))
    far = PastStep("place", None, "failed", "", OutcomeCode.UNSTABLE, found_at=(3.25, 1.05, 0.05))
    fallen = PastStep("place", None, "failed", "", OutcomeCode.UNSTABLE, SkillFacts(upright=False),
                      found_at=(2.25, 0.05, 0.80))
    missed = PastStep("grasp", "red cup", "failed", "", OutcomeCode.MISSED, SkillFacts(attempts=2, offset_m=0.031))
    room = Room()
    room.fly("Could you look around and find the unicorn for me?", max_steps=30)
    return [
        _ctx(COUNTER_CMD, approach[:2], pose=(0.0, 0.0, 0.0), positions=where),
        _ctx(COUNTER_CMD, approach, pose=(2.5, 0.0, 0.0), positions=where, visible=seen),
        _ctx(PLACE_CMD, [*_PICKED, refused], held="red cup", pose=(0.0, 0.0, 1.57), positions={"table": (0.0, 4.0)}),
        _ctx(PLACE_CMD, [*_PICKED, lost], pose=(2.0, -0.8, 1.57)),
        _ctx(PLACE_CMD, [*_PICKED, off], pose=(2.0, -0.8, 1.57)),
        _ctx(PLACE_CMD, [*_PICKED, far], pose=(2.0, -0.8, 1.57), known_objects=["red cup"]),
        _ctx(PLACE_CMD, [*_PICKED, fallen], pose=(2.0, -0.8, 1.57)),
        _ctx(PLACE_CMD, [*_PICKED[:1], missed], pose=(0.5, 0.0, 0.0), known_objects=["red cup"]),
        _ctx("Could you look around and find the unicorn for me?", room.steps, pose=(room.x, room.y, room.yaw)),
    ]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rewording_the_messages_changes_no_decision(seed: int) -> None:
    """The policy decides from codes, facts and poses: the same decision (skill, argument, reasoning, failure)
    with every message replaced by noise, including phrases the old text matching would have acted on."""
    policy = RulesPolicy()
    decisions = set()
    for ctx in _scenarios():
        plain = policy.decide_full(ctx)
        assert policy.decide_full(_noisy(ctx, seed)) == plain
        decisions.add(plain.skill)
    assert len(decisions) >= 4  # the scenarios reach different branches: the comparison is not vacuous


def test_place_codes_decide_release() -> None:
    """An unstable place released the object (look for it), a blocked one did not (the cup is still held)."""
    policy = RulesPolicy()
    unstable = PastStep("place", None, "failed", "", OutcomeCode.UNSTABLE)
    assert policy.decide(_ctx(PLACE_CMD, [*_PICKED, unstable], pose=(2.0, -0.8, 1.57)))[:2] == \
        ("obj_localization", "red cup")
    blocked = PastStep("place", None, "rejected", "", OutcomeCode.BLOCKED, SkillFacts(holding="red cup"))
    assert policy.decide(_ctx(PLACE_CMD, [*_PICKED, blocked], pose=(2.0, -0.8, 1.57)))[0] != "obj_localization"


def test_a_place_refused_for_holding_nothing_ends_the_belief_that_the_grasp_still_holds() -> None:
    """Working memory can lag the steps, so a grasp that succeeded since the last release counts as holding;
    a later place that the executor refused while its facts said the gripper held nothing settles it (a fork
    under load once looped placement_localization and place 30 times on the stale belief)."""
    policy = RulesPolicy()
    refused = PastStep("place", None, "rejected", "", OutcomeCode.BLOCKED, SkillFacts(target="table"))
    # The table in view and its spot in memory: on the old belief the policy would place again.
    ctx = _ctx(PLACE_CMD, [*_PICKED, refused], pose=(2.0, -0.8, 1.57), visible=[Seen("table", "surface", 0.0, 1.2)],
               known_placements=["table"], positions={"table": (2.0, 0.0)})
    skill = policy.decide(ctx)[0]
    assert skill not in ("place", "placement_localization"), skill  # it looks for the cup again


@pytest.mark.parametrize(("state", "code"), [("succeeded", OutcomeCode.SUCCEEDED), ("failed", OutcomeCode.FAILED),
                                             ("rejected", OutcomeCode.BLOCKED), ("timeout", OutcomeCode.TIMED_OUT),
                                             ("aborted", OutcomeCode.ABORTED)])
def test_a_status_without_code_maps_from_its_state(state: str, code: OutcomeCode) -> None:
    assert PastStep("forward", None, state, "older log").code == code


def test_a_verbless_command_is_flown_and_its_first_step_says_how_it_was_read() -> None:
    """Issue 33: "red cup to the table" is not refused; the first decision says it was read as pick and place."""
    policy = RulesPolicy()
    d = policy.decide_full(_ctx("red cup to the table", []))
    assert d.failure is None and d.skill != "done"
    assert "no task verb" in d.reasoning and "red cup" in d.reasoning and "table" in d.reasoning
    later = policy.decide_full(_ctx("red cup to the table", [_motion("yaw_left", 0.0, 0.0, 45.0)]))
    assert "no task verb" not in later.reasoning


def test_the_search_covers_every_viewpoint_within_the_not_found_bound() -> None:
    """The search budget is the coverage itself (shared/search.py): from any start the policy scans, flies to all
    four viewpoints and scans there before it says not found, and the episode stays within the evaluation's
    not-found bound (a budget of 60 steps cut the search short at the third viewpoint)."""
    from shared.search import NOT_FOUND_MAX_STEPS, SCAN_TURNS, SEARCH_STEPS, VIEWPOINTS

    for x, y, yaw in ((0.3, -0.2, 0.0), (2.5, 2.5, 1.0), (-3.0, 0.0, 0.0), (0.0, 0.0, math.pi), (1.0, -2.9, -2.0)):
        room = Room()
        room.x, room.y, room.yaw = x, y, yaw
        room.path = [(x, y)]
        d = room.fly("Could you look around and find the unicorn for me?", max_steps=200)
        assert d is not None and d.skill == "done" and d.failure, (x, y, yaw)
        skills = [s.skill for s in room.steps]
        assert skills[-SCAN_TURNS:] == ["yaw_left"] * SCAN_TURNS, skills  # it ended scanning the last viewpoint
        assert skills.count("obj_localization") == VIEWPOINTS + 1, skills  # a look after every earlier scan
        assert len(room.steps) <= SEARCH_STEPS and len(room.steps) + 1 <= NOT_FOUND_MAX_STEPS, len(room.steps)


def test_a_place_the_object_slipped_out_of_before_the_release_is_not_done_and_picks_it_up_again() -> None:
    # Dev grasp run seed 4: the tissue box left the pads on place's way down and lay upside down on the sink.
    # Place reports `slipped` (the gripper holds nothing, and the object is in memory where it came to rest):
    # never done on where it fell, never another place of nothing; pick it up again.
    slipped = PastStep("place", None, "failed", "", OutcomeCode.SLIPPED, SkillFacts(target="table"))
    policy = RulesPolicy()
    skill, arg, _ = policy.decide(_ctx(PLACE_CMD, [*_PICKED, slipped], pose=(2.0, -0.8, 1.57),
                                       known_objects=["red cup"]))
    assert (skill, arg) == ("obj_localization", "red cup")  # where it rests now, then the grasp
    # Before this, the policy took the last successful grasp for a hold and flew on to place nothing.
    skill, _, _ = policy.decide(_ctx(PLACE_CMD, [*_PICKED, slipped], pose=(2.0, -0.8, 1.57)))
    assert skill not in ("done", "place", "placement_localization"), skill
