"""Closed-loop grasp and place against the real sim, bridge and perception under injected error (sim/fault):
a vehicle that settles a few centimetres off every position setpoint (`hover offset`), a miscalibrated camera
mount (`camera_mount offset`: every detection is off, the executor cannot know), an object knocked over
(`object knock`), a jump of the pose estimate (`estimate offset`). What happened is judged by the simulator's
ground truth (`sim/judge`), what the skill reports by its outcome code and facts."""

from __future__ import annotations

import math

import pytest

from shared.messages import GripperCommand, OutcomeCode, SkillState, VehicleState
from tests.executor.test_integration import KEYS, Client
from tests.helpers import bus_for, run_stack

pytestmark = [pytest.mark.integration, pytest.mark.slow]

SERVICES = ["sim", "autopilot_bridge", "perception", "executor"]


# The kinematic body, for the reason tests/executor/test_integration.py's stack gives: these tests assert what one
# grasp call does (under an injected error, its outcome code).
@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    with run_stack(SERVICES, tmp_path_factory.mktemp("closed_loop_stack"),
                   env={"AERMANI_SIM_SPEED_FACTOR": "3", "AERMANI_SIM_DYNAMICS": "kinematic"}) as s:
        yield s


async def fault(c: Client, unit: str, kind: str, **kw) -> None:
    res = await c.bus.query(KEYS.sim_fault, {"unit": unit, "type": kind, **kw}, timeout=10)
    assert res["ok"], res


@pytest.fixture
async def client(stack):
    async with bus_for(stack) as bus:
        c = Client(bus)
        try:
            yield c
        finally:
            # every test starts from a faultless world (the faults outlive a reset) and an open gripper (a test
            # that failed holding something would leave the executor believing it holds it)
            await fault(c, "hover", "ok")
            await fault(c, "camera_mount", "ok")
            await fault(c, "estimate", "ok")
            await c.bus.query(KEYS.autopilot_command, GripperCommand(action="open"), timeout=10)


async def test_grasp_corrects_a_hover_offset_lifts_and_place_verifies_rest(client):
    c = client
    await c.reset(seed=5, target_object="red cup", destination="table")
    await c.takeoff()
    # 4.6 cm off every setpoint: beyond the pads' +-2.5 cm along their width, inside the 8 cm arrival tolerance,
    # so an open-loop grasp closes beside the cup while believing it arrived
    await fault(c, "hover", "offset", x=0.035, y=-0.03)
    await c.approach("red cup")
    st = await c.run("grasp")
    facts = st.outcome.facts
    assert st.state == SkillState.SUCCEEDED, (st.message, facts)
    assert st.outcome.code == OutcomeCode.SUCCEEDED and facts.holding == "red cup" and facts.target == "red cup"
    assert 1 <= facts.attempts <= 3 and len(facts.reasons) == facts.attempts - 1, facts
    # the gripper point closed within the window although the vehicle settles 4.6 cm off its setpoints
    assert facts.offset_m is not None and facts.offset_m <= 0.035, facts
    assert facts.gripper_width_m is not None and 0.05 <= facts.gripper_width_m <= 0.11, facts
    held = await c.judge(op="held")
    assert held.held == "red cup", held.message
    await c.search_near("placement_localization", "table")
    st = await c.run("place")
    assert st.state == SkillState.SUCCEEDED, (st.message, st.outcome.facts)
    assert st.outcome.code == OutcomeCode.SUCCEEDED and st.outcome.facts.target == "table"
    verdict = await c.judge(op="on_surface", object="red cup", surface="table")
    assert verdict.ok, verdict.message
    await c.ok("land")


async def test_a_miss_fails_and_its_code_agrees_with_what_happened_to_the_cup(client):
    c = client
    await c.reset(seed=5, target_object="red cup", destination="table")
    await c.takeoff()
    # The camera is believed 9 cm further forward than it sits: every detection lands 9 cm beyond the cup along
    # the approach, where the pads (5 cm wide) close on air; nothing the executor measures can tell.
    await fault(c, "camera_mount", "offset", x=0.09)
    await c.approach("red cup")
    before = await cup_position(c)
    st = await c.run("grasp")
    facts = st.outcome.facts
    assert st.state == SkillState.FAILED, st.message
    assert facts.holding is None and facts.target == "red cup"
    assert (await c.judge(op="held")).held is None
    # What the skill reports must agree with what happened. Usually the pads close on air and the cup stands
    # where it was: missed, three attempts, a reason each. The open fingers, with the vehicle's hover wander,
    # sometimes brush the cup: pushed along the shelf, still standing, the next attempt starts from where it
    # stands (still missed); tipped over, the honest report is knocked_over. From the pre-grasp pose the
    # miscalibrated camera may also lose the cup: not_detected. A knock is reported only when two looks see the
    # cup lower or lying; one partial view that reads its top low is not enough.
    moved = math.dist(before, await cup_position(c))
    standing = (await c.judge(op="on_surface", object="red cup", surface="shelf")).ok
    code = st.outcome.code
    if not standing:  # knocked over: said so, or the miscalibrated camera lost it
        assert code in (OutcomeCode.KNOCKED_OVER, OutcomeCode.NOT_DETECTED), (moved, code, st.message, facts)
    else:
        assert code in (OutcomeCode.MISSED, OutcomeCode.KNOCKED_OVER, OutcomeCode.NOT_DETECTED), (
            moved, code, st.message, facts)
    if code == OutcomeCode.MISSED:
        assert facts.attempts == 3 and len(facts.reasons) == 3, facts
        assert all("missed" in r for r in facts.reasons), facts.reasons
    false_knock = " (a false knock: the cup still stands)" if code == OutcomeCode.KNOCKED_OVER and standing else ""
    print(f"true displacement of the cup: {moved * 100:.1f} cm -> {code.value}{false_knock}")
    await c.ok("land")


async def cup_position(c: Client) -> tuple[float, float, float]:
    cup = next(o for o in (await c.judge(op="world")).objects if o.name == "red cup")
    return cup.position.x, cup.position.y, cup.position.z


async def test_a_miss_that_knocks_the_object_over_is_reported_knocked_over(client):
    c = client
    await c.reset(seed=5, target_object="red cup", destination="table")
    await c.takeoff()
    await fault(c, "camera_mount", "offset", x=0.09)
    await c.approach("red cup")
    states = c.bus.subscribe(KEYS.autopilot_state, maxsize=100)
    acc = await c.request("grasp")
    assert acc.accepted, acc.reason
    # The fingers close on air (the miss above); while the skill waits for contact, the cup is knocked over,
    # as a pad brushing it would.
    while True:
        s: VehicleState = await states.recv(timeout=150)
        if s.gripper.value == "closed" and not s.gripper_holding:
            break
    await fault(c, "object", "knock", name="red cup")
    st = await c.terminal(acc.goal_id)
    facts = st.outcome.facts
    assert st.state == SkillState.FAILED, st.message
    assert st.outcome.code == OutcomeCode.KNOCKED_OVER, (st.outcome.code, st.message, facts)
    assert facts.attempts == 1 and len(facts.reasons) == 1 and "knocked_over" in facts.reasons[0], facts
    assert (await c.judge(op="held")).held is None
    assert not (await c.judge(op="on_surface", object="red cup", surface="shelf")).ok  # truly tipped
    await c.ok("land")


def beyond_the_edge(table, spot, margin: float = 0.25) -> tuple[float, float]:
    """A world (x, y) `margin` beyond the table edge nearest to `spot`, along the table's own axes."""
    c, s = math.cos(table.yaw), math.sin(table.yaw)
    dx, dy = spot.x - table.position.x, spot.y - table.position.y
    lx, ly = c * dx + s * dy, -s * dx + c * dy
    if table.size.x / 2 - abs(lx) <= table.size.y / 2 - abs(ly):
        lx = math.copysign(table.size.x / 2 + margin, lx)
    else:
        ly = math.copysign(table.size.y / 2 + margin, ly)
    return table.position.x + c * lx - s * ly, table.position.y + s * lx + c * ly


async def test_place_reports_unstable_when_the_released_object_falls_off(client):
    c = client
    # The red cup, not a rolling object: place asks a rolling one (apple, orange) a fresh spot away from the
    # edges, and that re-localization, when the table happens to be in view, sees through the jumped estimate
    # below, so the test would hinge on the camera's view. (The apple is also found from the take-off spot, 2.9
    # m away, in only some frames: ~90 px against the colour segmenter's 60 px blob minimum.)
    await c.reset(seed=5, target_object="red cup", destination="table")
    await c.takeoff()
    await c.approach("red cup")
    st = await c.run("grasp")
    assert st.state == SkillState.SUCCEEDED, (st.message, st.outcome.facts)
    assert (await c.judge(op="held")).held == "red cup"
    loc = await c.search_near("placement_localization", "table")
    spot = loc.outcome.estimate.pose.position
    table = next(o for o in (await c.judge(op="world")).objects if o.name == "table")
    # The pose estimate jumps (a bad relocalization) so that flying to the spot truly ends 25 cm beyond the
    # table's nearest edge: the cup is released over the floor. Camera and vehicle share the estimate, so
    # only the object's height tells.
    tx, ty = beyond_the_edge(table, spot)
    await fault(c, "estimate", "offset", x=spot.x - tx, y=spot.y - ty)
    st = await c.run("place")
    facts = st.outcome.facts
    assert st.state == SkillState.FAILED, st.message
    assert st.outcome.code == OutcomeCode.UNSTABLE, (st.outcome.code, st.message, facts)
    assert facts.target == "table" and facts.holding is None
    assert not (await c.judge(op="on_surface", object="red cup", surface="table")).ok
    assert (await c.judge(op="held")).held is None
    await fault(c, "estimate", "ok")
    await c.ok("land")


async def test_place_verifies_rest_against_the_surface_seen_now_when_the_estimate_wanders(client):
    """The pose estimate drops 6 cm between placement_localization and place (a realistic multirotor's vertical
    estimate wanders with sigma 2.8 cm). The cup is truly released on the table, a few centimetres higher than
    planned; the table's top measured before the release now reads 6 cm off the support seen under the cup, so a
    check against it calls a good place unstable. Against the table's top seen from the same view it rests."""
    c = client
    await c.reset(seed=5, target_object="red cup", destination="table")
    await c.takeoff()
    await c.approach("red cup")
    st = await c.run("grasp")
    assert st.state == SkillState.SUCCEEDED, (st.message, st.outcome.facts)
    await c.search_near("placement_localization", "table")
    await fault(c, "estimate", "offset", z=-0.06)  # the vehicle believes itself 6 cm lower than it is
    st = await c.run("place")
    assert st.state == SkillState.SUCCEEDED, (st.message, st.outcome.perceived)
    assert (await c.judge(op="on_surface", object="red cup", surface="table")).ok
    await fault(c, "estimate", "ok")
    await c.ok("land")


async def test_an_object_found_lying_is_grasped_and_placed_but_not_claimed_standing(client):
    """Dev episode search/000 (and, with a tissue box, localization/002, /008, search/007): an object tipped by an
    earlier knock was grasped lying and set down lying, and place, comparing its height with the height it had
    when found, called it placed. Grasp now tells from its shape (a cup lying: 8 cm tall, 11 cm long) or, for a
    box, its finger gap (tests/executor/test_routines.py), and place reports it fallen over. (A knocked tissue
    box runs the same way here, except that in 1 of 6 runs place timed out lowering it onto the table: issue 25,
    not this test's subject.)"""
    c, name = client, "red cup"
    # seed 8: it stands on the counter (1.4 x 0.6 m), 1.6 m from the table, and lies there knocked over
    await c.reset(seed=8, target_object=name, destination="table")
    await fault(c, "object", "knock", name=name)
    await c.takeoff()
    await c.search_near("obj_localization", name)
    await c.approach(name)
    st = await c.run("grasp")
    facts = st.outcome.facts
    assert st.state == SkillState.SUCCEEDED, (st.message, facts)
    assert facts.upright is False and "it lay on its side" in st.message, (st.message, facts)
    await c.search_near("placement_localization", "table", within=2.0)  # 1.6 m from the counter's edge
    st = await c.run("place")
    assert st.state == SkillState.FAILED and st.outcome.code == OutcomeCode.UNSTABLE, st.message
    assert st.outcome.facts.upright is False and "lies on its side" in st.message, st.message
    verdict = await c.judge(op="on_surface", object=name, surface="table")
    # the simulator agrees: not placed, and for that reason
    assert not verdict.ok and any(ch.name == "upright" and not ch.ok for ch in verdict.checks), verdict.message
    await c.ok("land")
