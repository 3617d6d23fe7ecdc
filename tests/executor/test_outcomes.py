"""Every skill's result is a code plus facts (no policy reads the message): the executor's own refusals,
motion, localization, an out-of-reach grasp, a busy executor and a cancel, against the toy world on a
real bus."""

from __future__ import annotations

from shared.action import skill_client
from shared.messages import OutcomeCode, SkillAccept, SkillRequest, SkillState, Vec3, now_ns
from tests.executor.rig import rig
from tests.helpers import wait_until


async def test_codes_and_facts_of_skills_and_refusals():
    async with rig() as r:
        r.world.add_object("red cup", 3.0, 0.0, 0.75)
        st = await r.run_skill("teleport")
        assert st.state == SkillState.REJECTED and st.outcome.code == OutcomeCode.FAILED
        st = await r.run_skill("obj_localization")  # its argument is required
        assert st.state == SkillState.REJECTED and st.outcome.code == OutcomeCode.BLOCKED
        st = await r.run_skill("takeoff")  # airborne already
        assert st.state == SkillState.REJECTED and st.outcome.code == OutcomeCode.BLOCKED
        st = await r.run_skill("forward")
        assert st.state == SkillState.SUCCEEDED and st.outcome.code == OutcomeCode.SUCCEEDED
        assert st.outcome.facts.distance_m is not None and abs(st.outcome.facts.distance_m - 0.5) < 0.1
        assert st.outcome.facts.holding is None
        st = await r.run_skill("obj_localization", "blue box")
        assert st.state == SkillState.FAILED and st.outcome.code == OutcomeCode.NOT_DETECTED
        assert st.outcome.facts.target == "blue box"
        st = await r.run_skill("obj_localization", "red cup")
        assert st.outcome.code == OutcomeCode.SUCCEEDED and st.outcome.facts.target == "red cup"
        assert st.outcome.facts.distance_m is not None and st.outcome.facts.distance_m > 2.0
        # Beyond the grasp's reach: refused as out_of_reach with the distance and the reach, in the accept too.
        acc = await r.request("grasp")
        assert not acc.accepted and acc.outcome is not None and acc.outcome.code == OutcomeCode.OUT_OF_REACH
        facts = acc.outcome.facts
        assert facts.reach_m == r.executor.settings.reach and facts.distance_m > facts.reach_m
        st = await r.terminal(acc.goal_id)
        assert st.state == SkillState.REJECTED and st.outcome == acc.outcome
        # A geofence refusal is out of reach too: turn to face the near wall and step toward it repeatedly.
        for _ in range(20):
            st = await r.run_skill("forward")
            if st.state != SkillState.SUCCEEDED:
                break
        assert st.state == SkillState.REJECTED and st.outcome.code in (OutcomeCode.OUT_OF_REACH, OutcomeCode.BLOCKED)


async def test_a_cancelled_skill_is_aborted_and_a_busy_executor_blocks():
    # The vehicle is frozen once the step's setpoint arrives, so the skill can only end by the cancel (its own
    # timeout is minutes away).
    async with rig(motion_slack_s=300.0) as r:
        async with skill_client(r.bus, r.keys.vehicle_id) as client:
            goal = await client.send_goal(SkillRequest(skill="backward", task_id="t1"))
            assert goal.accepted, goal.reason
            await wait_until(lambda: "goto" in r.vehicle.commands, what="the step's setpoint")
            r.vehicle.speed = 0.0
            busy = await r.request("yaw_left")
            assert not busy.accepted and busy.outcome is not None and busy.outcome.code == OutcomeCode.BLOCKED
            reply = await goal.cancel(reason="test stop", source="test")
            assert reply.accepted, reply.reason
            st = await goal.result(timeout=30)
        assert st is not None and st.state == SkillState.ABORTED and st.outcome.code == OutcomeCode.ABORTED
        assert "test stop" in st.message


async def test_check_skill_answers_as_run_skill_would_and_starts_nothing():
    """executor/check_skill (asked before an operator's approval): the same refusal, code and facts as run_skill
    for a grasp out of reach, an accept for a feasible skill, and neither moves the vehicle, reserves the
    executor or publishes a status."""
    async with rig() as r:
        r.world.add_object("red cup", 3.0, 0.0, 0.75)
        assert (await r.run_skill("obj_localization", "red cup")).outcome.code == OutcomeCode.SUCCEEDED
        commands = list(r.vehicle.commands)

        async def check(skill: str, argument: str | None = None) -> SkillAccept:
            return await r.bus.query(r.keys.check_skill, SkillRequest(skill=skill, argument=argument, task_id="t1"),
                                     timeout=5.0)

        far = await check("grasp", "red cup")
        assert not far.accepted and far.goal_id == "" and far.outcome is not None
        assert far.outcome.code == OutcomeCode.OUT_OF_REACH
        assert far.outcome.facts.distance_m > far.outcome.facts.reach_m == r.executor.settings.reach
        assert not (await check("teleport")).accepted
        ok = await check("yaw_left")
        assert ok.accepted and ok.goal_id == "" and ok.reason == ""
        assert r.executor.goal is None and r.vehicle.commands == commands
        refused = await r.request("grasp", "red cup")  # run_skill agrees with the check
        assert not refused.accepted and refused.reason == far.reason and refused.outcome.code == far.outcome.code
        # Statuses on the key arrive in order, and the localization's were read to its end above: up to
        # yaw_left's end, only the two run_skill goals published any.
        acc = await r.request("yaw_left")
        seen = set()
        while True:
            st = await r.statuses.recv(timeout=60)
            seen.add(st.goal_id)
            if st.goal_id == acc.goal_id and st.state.terminal:
                break
        assert seen == {refused.goal_id, acc.goal_id}, seen


async def test_a_recorded_memory_is_refused_unless_allowed_and_never_taken_mid_skill():
    """`executor/restore_memory` (the flight fork's): off on a vehicle by default; allowed, refused while a skill
    runs (the memory unchanged), then taken between skills, each sighting as old as when recorded."""
    from shared.messages import MemoryObject, MemoryRestore, WorkingMemory

    cup = MemoryObject(label="red cup", position=Vec3(x=1.0, y=0.0, z=0.8), last_seen_ns=now_ns() - 5_000_000_000)
    req = MemoryRestore(task_id="fork-1", memory=WorkingMemory(objects=(cup,)), taken_ns=now_ns())
    async with rig() as r:
        reply = await r.bus.query(r.keys.restore_memory, req, timeout=10)
        assert not reply.accepted and "AERMANI_EXECUTOR_MEMORY_RESTORE" in reply.reason
        assert r.executor.memory.find_object("red cup") is None
    async with rig(memory_restore=True, motion_slack_s=300.0) as r:
        async with skill_client(r.bus, r.keys.vehicle_id) as client:
            goal = await client.send_goal(SkillRequest(skill="backward", task_id="t1"))
            assert goal.accepted, goal.reason
            await wait_until(lambda: "goto" in r.vehicle.commands, what="the step's setpoint")
            r.vehicle.speed = 0.0
            busy = await r.bus.query(r.keys.restore_memory, req, timeout=10)
            assert not busy.accepted and "mid-skill" in busy.reason
            assert r.executor.memory.find_object("red cup") is None
            assert (await goal.cancel(reason="test stop", source="test")).accepted
            await goal.result(timeout=30)
        reply = await r.bus.query(r.keys.restore_memory, req, timeout=10)
        assert reply.accepted, reply.reason
        back = r.executor.memory.find_object("red cup")
        assert back is not None and 4.0 < (now_ns() - back.last_seen_ns) / 1e9 < 60.0
