"""Localization, grasp and place routines, working memory and abort against the toy world on a real bus."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from services.reasoner.prompt import memory_summary, outcome_text
from shared.messages import Abort, OutcomeCode, SkillState
from tests.executor.rig import rig
from tests.helpers import matched, wait_until


def _scene(r) -> None:
    r.world.add_surface("table", 1.6, 0.0, 0.75)
    r.world.add_object("red cup", 1.5, 0.1, 0.75)
    r.world.add_surface("round table", -1.5, 1.5, 0.75, size=(0.9, 0.9))


async def test_localize_grasp_localize_placement_place():
    async with rig() as r:
        _scene(r)
        st = await r.run_skill("obj_localization", "blue box")
        assert st.state == SkillState.FAILED and "blue box not visible" in st.message
        st = await r.run_skill("obj_localization", "red cup")
        assert st.state == SkillState.SUCCEEDED, st.message
        assert st.outcome.estimate is not None and st.outcome.estimate.found
        assert "red cup at (1.50, 0.10" in st.outcome.perceived
        mem = await r.memory.recv(timeout=5)
        while not mem.objects:
            mem = await r.memory.recv(timeout=5)
        assert mem.objects[0].label == "red cup" and "red cup at (1.50" in memory_summary(mem)

        st = await r.run_skill("grasp")
        assert st.state == SkillState.SUCCEEDED, st.message
        assert r.world.objects["red cup"].attached and st.outcome.held_object == "red cup"
        assert r.vehicle.pos[2] >= 1.45  # retreated to flight altitude
        assert r.executor.memory.held == "red cup" and "red cup" not in r.executor.memory.objects

        st = await r.run_skill("placement_localization", "table")
        assert st.state == SkillState.SUCCEEDED, st.message
        st = await r.run_skill("place")
        assert st.state == SkillState.SUCCEEDED, st.message
        cup = r.world.objects["red cup"]
        assert not cup.attached and abs(cup.center[2] - cup.size[2] / 2 - 0.75) < 1e-6
        assert abs(cup.center[0] - 1.6) < 0.1 and abs(cup.center[1]) < 0.1
        assert r.executor.memory.held is None and st.outcome.held_object is None
        executed = r.executor.memory.snapshot().executed
        assert [e.split(":")[0] for e in executed] == [
            "obj_localization(blue box)", "obj_localization(red cup)", "grasp", "placement_localization(table)",
            "place"]


async def test_place_reports_an_object_that_fell_over_even_while_it_still_rocks():
    # Dev episode localization/028: the released cup toppled and was still rocking when looked at; place said
    # only "still moving", so the policy took it for placed. Fallen over is checked first (and confirmed by a
    # second look) and is in the facts. Here a bottle topples and rocks through every look.
    async with rig() as r:
        r.world.add_surface("table", 1.6, 0.0, 0.75)
        r.world.add_object("green bottle", 1.5, 0.1, 0.75, size=(0.07, 0.07, 0.25))
        r.world.topple.add("green bottle")
        for skill, arg in (("obj_localization", "green bottle"), ("grasp", None),
                           ("placement_localization", "table")):
            st = await r.run_skill(skill, arg)
            assert st.state == SkillState.SUCCEEDED, (skill, st.message)
        st = await r.run_skill("place")
        facts = st.outcome.facts
        assert st.state == SkillState.FAILED and st.outcome.code == OutcomeCode.UNSTABLE, st.message
        assert facts.upright is False and "fallen over" in st.message, (st.message, facts)
        assert facts.holding is None and r.executor.memory.held is None
        assert "fallen over" in outcome_text(st.outcome)
        # An upright place says so too.
        r.world.add_object("red cup", 1.5, -0.2, 0.75)
        for skill, arg in (("obj_localization", "red cup"), ("grasp", None), ("placement_localization", "table"),
                           ("place", None)):
            st = await r.run_skill(skill, arg)
            assert st.state == SkillState.SUCCEEDED, (skill, st.message)
        assert st.outcome.facts.upright is True and "upright" in outcome_text(st.outcome)


@pytest.mark.parametrize("topples", [True, False])
async def test_place_reports_a_tall_box_that_fell_onto_a_side_nearly_as_tall_by_its_catalogue(topples: bool):
    # Dev grasp run seed 23: a cracker box (16 x 7 x 21 cm) pivoted in the pads as it touched down and came to rest
    # on its 16 cm side; 5 cm shorter than when held is within the quarter of its height that a view's error may
    # take, so place claimed it placed. Its catalogued extents tell: 16 cm tall is how it lies, not how it stands.
    box = (0.16, 0.07, 0.21)
    async with rig() as r:
        r.world.add_surface("table", 1.6, 0.0, 0.75)
        r.world.add_object("cracker box", 1.5, 0.1, 0.75, size=box, catalog=box)
        if topples:
            r.world.topple.add("cracker box")
        for skill, arg in (("obj_localization", "cracker box"), ("grasp", None),
                           ("placement_localization", "table")):
            st = await r.run_skill(skill, arg)
            assert st.state == SkillState.SUCCEEDED, (skill, st.message)
        st = await r.run_skill("place")
        if topples:
            assert st.state == SkillState.FAILED and st.outcome.code == OutcomeCode.UNSTABLE, st.message
            assert st.outcome.facts.upright is False and "fallen over" in st.message, st.message
        else:
            assert st.state == SkillState.SUCCEEDED and st.outcome.facts.upright is True, st.message


async def test_place_never_claims_an_object_that_left_the_fingers_on_the_way_down():
    # Dev grasp run seed 4: a tissue box left the pads 28 cm above the sink on place's descent, landed upside
    # down, and place, seeing a box at rest on the sink, claimed it placed. The fingers' contact was gone before
    # the release: wherever it came to rest, it fell there.
    async with rig() as r:
        r.vehicle.fingers = True
        _scene(r)
        for skill, arg in (("obj_localization", "red cup"), ("grasp", None), ("placement_localization", "table")):
            st = await r.run_skill(skill, arg)
            assert st.state == SkillState.SUCCEEDED, (skill, st.message)
        r.world.slip_below["red cup"] = 0.75 + 0.11 + 0.25  # the gripper point 25 cm above where the cup rests
        st = await r.run_skill("place")
        assert st.state == SkillState.FAILED and st.outcome.code == OutcomeCode.SLIPPED, st.message
        assert "left the fingers before the release" in st.message and "fell there" in st.message, st.message
        assert st.outcome.facts.holding is None and r.executor.memory.held is None
        cup = r.world.objects["red cup"]
        assert not cup.attached and abs(cup.center[2] - cup.size[2] / 2 - 0.75) < 1e-6  # on the table
        # (Held to the end, the same place with sensing succeeds: test_a_box_grasped_lying_on_its_side_...)


async def test_a_box_grasped_lying_on_its_side_is_reported_lying_and_placed_so():
    # Dev episodes localization/002, /008, search/007: a tissue box tipped by an earlier knock was grasped on its
    # side and set down so, and place, comparing its height with the height it had when found, called it
    # placed. The finger gap tells: standing it is held across its 12 cm side, lying across its 10 cm height.
    box = (0.24, 0.12, 0.10)
    async with rig() as r:
        r.vehicle.fingers = True
        r.world.add_surface("table", 1.6, 0.0, 0.75)
        r.world.add_object("tissue box", 1.5, 0.1, 0.75, size=(0.24, 0.10, 0.12), catalog=box)
        for skill, arg in (("obj_localization", "tissue box"), ("grasp", None)):
            st = await r.run_skill(skill, arg)
            assert st.state == SkillState.SUCCEEDED, (skill, st.message)
        assert st.outcome.facts.upright is False and "it lay on its side" in st.message, (st.message,
                                                                                          st.outcome.facts)
        assert st.outcome.facts.gripper_width_m == 0.10
        st = await r.run_skill("placement_localization", "table")
        assert st.state == SkillState.SUCCEEDED, st.message
        st = await r.run_skill("place")
        facts = st.outcome.facts
        assert st.state == SkillState.FAILED and st.outcome.code == OutcomeCode.UNSTABLE, st.message
        assert facts.upright is False and "lies on its side" in st.message, (st.message, facts)
        assert not r.world.objects["tissue box"].attached and r.executor.memory.held is None
        # Standing, the same box is held across its 12 cm side and placed.
        r.world.add_object("tissue box", 1.5, -0.2, 0.75, size=box, catalog=box)
        for skill, arg in (("obj_localization", "tissue box"), ("grasp", None)):
            st = await r.run_skill(skill, arg)
            assert st.state == SkillState.SUCCEEDED, (skill, st.message)
        assert st.outcome.facts.upright is True and "on its side" not in st.message, st.message
        for skill, arg in (("placement_localization", "table"), ("place", None)):
            st = await r.run_skill(skill, arg)
            assert st.state == SkillState.SUCCEEDED, (skill, st.message)
        assert st.outcome.facts.upright is True


async def test_grasp_fails_when_the_object_moved_after_localization():
    async with rig() as r:
        _scene(r)
        assert (await r.run_skill("obj_localization", "red cup")).state == SkillState.SUCCEEDED
        r.world.objects["red cup"].center[:2] = (1.5, -0.35)  # nudged 0.45 m
        st = await r.run_skill("grasp")
        assert st.state == SkillState.FAILED and "moved since it was localized" in st.message
        assert not r.world.objects["red cup"].attached and r.executor.memory.held is None
        # memory now holds the new position: a second grasp picks it up
        st = await r.run_skill("grasp")
        assert st.state == SkillState.SUCCEEDED, st.message
        assert r.world.objects["red cup"].attached


async def test_grasp_fails_when_the_object_vanished():
    async with rig() as r:
        _scene(r)
        assert (await r.run_skill("obj_localization", "red cup")).state == SkillState.SUCCEEDED
        r.world.objects["red cup"].center[:2] = (-3.0, -3.0)
        st = await r.run_skill("grasp")
        assert st.state == SkillState.FAILED and "not visible" in st.message and "localize it again" in st.message
        assert "red cup" not in r.executor.memory.objects


async def test_grasp_that_closes_on_nothing_reports_a_miss():
    async with rig() as r:
        _scene(r)
        assert (await r.run_skill("obj_localization", "red cup")).state == SkillState.SUCCEEDED
        r.world.grab = lambda g: None  # the object slips: closing catches nothing
        st = await r.run_skill("grasp")
        assert st.state == SkillState.FAILED and "grasp missed" in st.message, st.message
        assert r.executor.memory.held is None and st.outcome.held_object is None
        assert r.vehicle.gripper.value == "open"


async def test_a_miss_that_pushed_the_object_still_standing_gets_the_next_attempt_from_where_it_stands():
    # Dev grasp benchmark seeds 3, 6, 18: a pad pushed the can, apple or box 6-11 cm along the table, still
    # standing (the simulator's judge records no knock), and the grasp ended knocked_over at once.
    # Without the gripper's sensing the miss shows only after the lift, where the cup still stands near its spot
    # (counted as picked up before, pushed 8 cm).
    for sensing in (True, False):
        async with rig() as r:
            r.vehicle.fingers = sensing
            _scene(r)
            assert (await r.run_skill("obj_localization", "red cup")).state == SkillState.SUCCEEDED
            grab, cup = r.world.grab, r.world.objects["red cup"]

            def push(g, grab=grab, cup=cup, r=r):  # the first close catches nothing and shoves the cup 8 cm on
                cup.center[0] += 0.08
                r.world.grab = grab
                return None

            r.world.grab = push
            st = await r.run_skill("grasp")
            facts = st.outcome.facts
            assert st.state == SkillState.SUCCEEDED and facts.attempts == 2, (sensing, st.message, facts)
            assert cup.attached and r.executor.memory.held == "red cup"
            if sensing:
                assert "pushed the red cup 8 cm, still standing" in st.outcome.perceived, st.outcome.perceived


async def test_a_top_read_low_once_after_a_miss_is_not_a_knock_twice_is_unless_it_lies_flat():
    # Dev grasp benchmark seed 17: after a miss, the close look read the can's top 4 cm low (its centre as high
    # as before) and the grasp ended "tipped over"; the judge saw it standing. One more look decides.
    # A flat tool has no standing height to lose: a low reading is never a knock (held-out seeds 209, 237).
    # A whole view 4 cm lower (the vehicle's vertical estimate wandered between the looks: dev seeds 7, 16, 19 read
    # "5-7 cm lower" twice, all standing) is not a top read low: its height above the table is what it was.
    low, drifted = (0.0, -0.03), (0.0, 0.0, -0.04)
    for low_looks, knocked, flat, look in ((1, False, False, low), (2, True, False, low), (2, False, True, low),
                                           (2, False, False, drifted)):
        async with rig() as r:
            r.vehicle.fingers = True
            _scene(r)
            if flat:
                tool = r.world.objects["red cup"]
                tool.size, tool.center[2] = (0.2, 0.05, 0.035), 0.75 + 0.0175  # the hammer's shape
            assert (await r.run_skill("obj_localization", "red cup")).state == SkillState.SUCCEEDED
            grab = r.world.grab

            def miss(g, low_looks=low_looks, grab=grab, r=r, look=look):  # the first close catches nothing; then
                r.world.looks["red cup"] = [look] * low_looks  # the looks as asked
                r.world.grab = grab
                return None

            r.world.grab = miss
            st = await r.run_skill("grasp")
            facts = st.outcome.facts
            if knocked:
                assert st.outcome.code == OutcomeCode.KNOCKED_OVER and facts.attempts == 1, (st.message, facts)
                assert "tipped over" in st.message and "3 cm shorter" in st.message, st.message
            else:
                assert st.state == SkillState.SUCCEEDED and facts.attempts == 2, (st.message, facts)


async def test_place_tells_looks_that_scatter_at_rest_from_an_object_that_rolls_on():
    # Dev grasp benchmark seeds 0 and 22: no two of 4 looks at a cup (3.0 cm) or a banana (10.9 cm) agreed and
    # place said "still moving"; both rested. Looks that scatter about one place are at rest; looks that run off
    # in one direction are not.
    for looks, rests in (([(0.03, 0.0), (-0.01, 0.0)] * 3, True), ([(0.04 * i, 0.0) for i in range(6)], False)):
        async with rig() as r:
            _scene(r)
            for skill, arg in (("obj_localization", "red cup"), ("grasp", None), ("placement_localization", "table")):
                st = await r.run_skill(skill, arg)
                assert st.state == SkillState.SUCCEEDED, (skill, st.message)
            r.world.looks["red cup"] = list(looks)
            st = await r.run_skill("place")
            if rests:
                assert st.state == SkillState.SUCCEEDED, st.message
                assert "scatter by up to 4.0 cm" in st.outcome.perceived, st.outcome.perceived
            else:
                assert st.outcome.code == OutcomeCode.UNSTABLE and "still moving" in st.message, st.message


async def _abort_and_check(r, goal_id: str) -> None:
    acks = r.bus.subscribe(r.keys.abort_ack)
    await matched(r.executor.bus, r.keys.abort_ack)  # a fixed pause raced the subscription on a loaded machine
    await matched(r.bus, r.keys.abort)
    abort = Abort(reason="test", source="test")
    r.bus.publish(r.keys.abort, abort)
    ack = await acks.recv(timeout=5)
    assert ack.abort_stamp_ns == abort.stamp_ns and ack.goal_id == goal_id and "holding" in ack.message
    st = await r.terminal(goal_id, 10)
    assert st.state == SkillState.ABORTED
    assert "hold" in r.vehicle.commands
    await wait_until(lambda: np.linalg.norm(r.vehicle.vel) < 0.05, 5, what="vehicle stopped")
    here = r.vehicle.pos.copy()
    await asyncio.sleep(0.5)
    assert np.linalg.norm(r.vehicle.pos - here) < 0.02, "vehicle kept moving after abort"
    # no timing assertion here: benchmarks/executor.py measures abort-to-hold
    # ready for the next skill at once
    nxt = await r.request("yaw_left")
    assert nxt.accepted, nxt.reason
    assert (await r.terminal(nxt.goal_id)).state == SkillState.SUCCEEDED


async def test_abort_during_a_translation_holds_and_leaves_the_executor_ready():
    async with rig(translation_speed=0.2) as r:
        acc = await r.request("forward")
        assert acc.accepted
        await wait_until(lambda: np.linalg.norm(r.vehicle.vel) > 0.1, 5, what="moving")
        await _abort_and_check(r, acc.goal_id)
        assert r.vehicle.pos[0] < 0.45  # stopped short of the full step


async def test_abort_during_grasp_holds_and_leaves_the_executor_ready():
    async with rig() as r:
        _scene(r)
        assert (await r.run_skill("obj_localization", "red cup")).state == SkillState.SUCCEEDED
        acc = await r.request("grasp")
        assert acc.accepted
        await wait_until(lambda: np.linalg.norm(r.vehicle.vel) > 0.1, 5, what="moving")
        await _abort_and_check(r, acc.goal_id)
        assert not r.world.objects["red cup"].attached


async def test_abort_with_nothing_running_is_acknowledged():
    async with rig() as r:
        acks = r.bus.subscribe(r.keys.abort_ack)
        await matched(r.executor.bus, r.keys.abort_ack)
        await matched(r.bus, r.keys.abort)
        r.bus.publish(r.keys.abort, Abort())
        ack = await acks.recv(timeout=5)
        assert ack.goal_id is None and "no skill running" in ack.message
        assert r.vehicle.commands == ["hold"]


async def test_grasp_beyond_reach_or_wider_than_the_fingers_is_refused_before_moving():
    async with rig() as r:
        r.world.add_surface("table", 3.0, 0.0, 0.75)
        r.world.add_object("red cup", 2.9, 0.1, 0.75)
        r.world.add_object("cardboard box", 1.5, -1.0, 0.75, size=(0.30, 0.24, 0.20))
        assert (await r.run_skill("obj_localization", "red cup")).state == SkillState.SUCCEEDED
        before = r.vehicle.pos.copy()
        st = await r.run_skill("grasp", "red cup")
        assert st.state == SkillState.REJECTED and "too far: approach first" in st.message, st.message
        assert np.allclose(r.vehicle.pos, before)
        assert (await r.run_skill("obj_localization", "cardboard box")).state == SkillState.SUCCEEDED
        st = await r.run_skill("grasp", "cardboard box")
        assert st.state == SkillState.REJECTED and "wider than the gripper opens" in st.message, st.message
        assert np.allclose(r.vehicle.pos, before) and not r.world.objects["cardboard box"].attached


async def test_grasp_outcome_carries_its_code_and_a_reason_per_attempt():
    async with rig() as r:
        _scene(r)
        assert (await r.run_skill("obj_localization", "red cup")).state == SkillState.SUCCEEDED
        grab = r.world.grab
        r.world.grab = lambda g: None  # the first closes catch nothing
        st = await r.run_skill("grasp")
        facts = st.outcome.facts
        assert st.outcome.code == OutcomeCode.MISSED and facts.attempts == 3 and len(facts.reasons) == 3, facts
        assert facts.target == "red cup" and facts.holding is None
        r.world.grab = grab
        assert (await r.run_skill("obj_localization", "red cup")).state == SkillState.SUCCEEDED
        st = await r.run_skill("grasp")
        assert st.state == SkillState.SUCCEEDED and st.outcome.code == OutcomeCode.SUCCEEDED, st.message
        assert st.outcome.facts.holding == "red cup" and st.outcome.facts.attempts == 1
