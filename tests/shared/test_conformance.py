"""The conformance check (`shared.conformance`) against every real service and every test fake.

Each one must publish what its declarations say with valid types (periodic topics within seconds), answer
every queryable it declares (a malformed request gets an error or a structured refusal, never silence),
and hold its liveliness token (and publish health, where the real service does)."""

from __future__ import annotations

import asyncio

import pytest

from shared.bus import Bus
from shared.conformance import check_service, declared_by
from shared.keys import Keys
from tests.executor.fakes import FakeAutopilot, FakeDepth, FakePerception, ToyWorld, cancel_all
from tests.helpers import bus_for, run_stack


def test_declarations_name_what_each_service_does():
    topics, queries = declared_by("executor")
    assert {t.name for t in topics} >= {"executor/skill_status", "executor/memory", "safety/abort_ack"}
    assert {q.name for q in queries} == {"executor/run_skill", "executor/check_skill", "executor/cancel_skill",
                                         "executor/skill_result", "executor/skills", "executor/restore_memory"}
    topics, queries = declared_by("reasoner")
    assert {q.name for q in queries} == {"reasoner/start_task", "reasoner/cancel_task", "reasoner/task_result",
                                         "reasoner/decide_approval"}


async def test_a_silent_or_wrong_fake_fails_the_check(router):
    """The check can fail: a queryable nobody serves and a topic with the wrong payload are reported."""
    async with await Bus.open(connect=[router]) as bus:
        keys = Keys("bad")
        bus.declare_token(keys.alive("executor"))

        async def ticker():
            while True:  # memory key carrying a Health: not what the key declares
                bus.publish(keys.memory.key, b'{"kind": "health", "service": "x", "ok": true}',
                            schema="aermani.Health")
                await asyncio.sleep(0.1)

        task = asyncio.create_task(ticker())
        try:
            report = await check_service(bus, "executor", "bad", timeout=1.5)
        finally:
            await cancel_all([task])
        failed = {f.key.split("/", 3)[3] for f in report.findings if not f.ok}
        assert not report.ok
        assert {"executor/memory", "executor/run_skill", "executor/check_skill", "executor/skills"} <= failed, \
            report.summary()


async def test_a_state_naming_another_vehicle_fails_the_check(router):
    """A bridge of vehicle `bad` whose states say the default `am1`: every subscriber refuses them, so does the
    check."""
    from shared.messages import Vec3, VehicleState

    async with await Bus.open(connect=[router]) as bus:
        keys = Keys("bad")

        async def ticker():
            while True:
                bus.publish(keys.autopilot_state, VehicleState(position=Vec3(z=1.0)))
                await asyncio.sleep(0.1)

        task = asyncio.create_task(ticker())
        try:
            report = await check_service(bus, "autopilot_bridge", "bad", expect_alive=False, timeout=1.5,
                                         require_periodic=False)
        finally:
            await cancel_all([task])
        failed = {f.key.split("/", 3)[3]: f.detail for f in report.findings if not f.ok}
        assert "of vehicle 'am1' on a key of vehicle 'bad'" in failed.get("autopilot/state", ""), report.summary()


async def test_executor_test_fakes_conform(router):
    async with await Bus.open(connect=[router]) as bus:
        keys = Keys("fk")
        world = ToyWorld()
        world.add_object("red cup", 2.0, 0.0, 0.75)
        vehicle = FakeAutopilot(bus, keys, world, airborne_at=1.5)
        perception = FakePerception(bus, keys, world, vehicle)
        perception.serve()
        depth = FakeDepth(bus, keys)
        tasks = [asyncio.create_task(vehicle.run()), asyncio.create_task(depth.run()),
                 asyncio.create_task(perception.run())]
        try:
            # The fakes declare no liveliness (tests start them in-process); tf comes from the simulator or
            # a bridge with publish_tf, and the segmentation oracle only from the simulator.
            for name, skip in (("autopilot_bridge", ("tf",)), ("perception", ()),
                               ("camera", ("tf",))):
                report = await check_service(bus, name, "fk", expect_alive=False, timeout=3.0, skip=skip)
                report.raise_for_failures()
        finally:
            await cancel_all(tasks)


async def test_reasoner_world_fake_conforms_as_an_executor(router):
    from services.reasoner.library import default_library
    from tests.reasoner.fake_world import MiniWorld, Thing, serve_executor

    async with await Bus.open(connect=[router]) as bus:
        keys = Keys("fw")
        task = await serve_executor(bus, MiniWorld([Thing("red cup")]), keys)
        try:
            report = await check_service(bus, "executor", "fw", expect_alive=False, timeout=3.0,
                                         library=default_library())
            report.raise_for_failures()
        finally:
            await cancel_all([task])


async def test_gateway_fake_conforms_as_a_reasoner(router):
    from services.reasoner.library import default_library
    from shared.messages import TaskRequest
    from tests.gateway.fakes import FakeVehicle

    async with await Bus.open(connect=[router]) as bus:
        fake = FakeVehicle(bus, "gw", steps=30, step_delay_s=0.1, services=("reasoner", "executor"))
        await fake.start()
        try:
            lib = default_library()
            # Its steps and skill statuses (it stands in for the executor too) name only real skills.
            skills = asyncio.create_task(check_service(
                bus, "executor", "gw", expect_alive=False, timeout=2.0, require_periodic=False, library=lib,
                skip=("executor/memory", "executor/run_skill", "executor/check_skill", "executor/cancel_skill",
                  "executor/skill_result")))
            await asyncio.sleep(0.3)
            accept = await bus.query(Keys("gw").start_task, TaskRequest(command="pick up the red cup"))
            assert accept.accepted
            report = await check_service(bus, "reasoner", "gw", timeout=2.0, library=lib)
            report.raise_for_failures()
            skills_report = await skills
            assert any(f.key.endswith("executor/skill_status") for f in skills_report.findings)
            skills_report.raise_for_failures()
        finally:
            await fake.stop()


@pytest.mark.integration
async def test_every_real_service_conforms(tmp_path):
    services = ["sim", "autopilot_bridge", "perception", "executor", "reasoner", "recorder"]
    with run_stack(services, tmp_path, env={"AERMANI_RECORDER_OUT_DIR": str(tmp_path / "rec")}) as stack:
        async with bus_for(stack) as bus:
            reports = []
            for name, health, skip in (
                ("sim", True, ()),
                ("autopilot_bridge", True, ("tf",)),  # tf comes from the sim here (publish_tf off)
                ("perception", True, ()),
                ("executor", False, ()),
                ("reasoner", False, ()),
                ("recorder", True, ()),
            ):
                reports.append(await check_service(bus, name, stack.procs[0].vehicle_id, timeout=5.0,
                                                   expect_health=health, skip=skip))
            failures = [r.summary() for r in reports if not r.ok]
            assert not failures, "\n".join(failures)


async def test_an_executor_fake_that_runs_an_unknown_skill_fails_the_check(router):
    """Valid requests too: a skill server that accepts a goal naming no skill, and reports running it, fails
    on the goal queryable and on its status topic (the skill is not in the live library)."""
    from services.reasoner.library import default_library
    from shared.action import SKILL_ACTION, ActionServer
    from shared.messages import SkillAccept, SkillState, SkillStatus

    async with await Bus.open(connect=[router]) as bus:
        async def accept(req):
            return SkillAccept(accepted=True, goal_id="g-1")

        async def execute(handle):
            handle.publish(SkillStatus(goal_id=handle.goal_id, skill="teleport", state=SkillState.SUCCEEDED))

        ActionServer(bus, SKILL_ACTION, "bad", goal_callback=accept, execute_callback=execute).start()
        publisher = asyncio.create_task(_publish_forever(bus, SkillStatus(goal_id="g-0", skill="teleport",
                                                                         state=SkillState.SUCCEEDED)))
        try:
            report = await check_service(bus, "executor", "bad", expect_alive=False, timeout=2.0,
                                         require_periodic=False, library=default_library(),
                                         skip=("executor/memory", "executor/skills"))
        finally:
            await cancel_all([publisher])
        failed = {f.key.split("/", 3)[3]: f.detail for f in report.findings if not f.ok}
        assert "accepted a request it must refuse" in failed.get("executor/run_skill", ""), report.summary()
        assert "teleport" in failed.get("executor/skill_status", ""), report.summary()
        assert "executor/cancel_skill" not in failed, report.summary()  # an unknown goal's cancel is refused


async def _publish_forever(bus, status) -> None:
    from shared.keys import Keys

    while True:  # a status stream the topic check samples (its own subscription may come late)
        bus.publish(Keys("bad").skill_status, status)
        await asyncio.sleep(0.05)
