"""A payload's vehicle id is its key's (issue 32): over real Zenoh sessions on loopback, a state, status or request
naming another vehicle is refused (logged, counted as malformed, never handed to the consumer) and the matching one
passes."""

from __future__ import annotations

import logging

import pytest

from shared import keys as k
from shared import messages as m
from shared.bus import check_vehicle, key_vehicle
from shared.errors import DecodeError, RemoteError
from tests.helpers import bus_pair, first_answer, matched

pytestmark = pytest.mark.integration


def test_the_rule():
    am2 = k.Keys("am2")
    check_vehicle(am2.autopilot_state, m.VehicleState(vehicle_id="am2"))
    check_vehicle(am2.abort, m.Abort())  # names no vehicle
    check_vehicle(k.FLEET_ABORT, m.Abort())
    check_vehicle("somewhere/else", m.VehicleState())  # not an aermani key
    with pytest.raises(DecodeError, match="VehicleState of vehicle 'am1' on a key of vehicle 'am2'"):
        check_vehicle(am2.autopilot_state, m.VehicleState())
    with pytest.raises(DecodeError, match="on a fleet-wide key"):
        check_vehicle(k.AUTOPILOT_STATE.fleet().replace("*", k.FLEET_ID), m.VehicleState())
    assert key_vehicle(am2.task_status) == "am2" and key_vehicle(k.FLEET_ABORT) == k.FLEET_ID
    assert key_vehicle("aermani/v1") is None


async def test_a_state_on_another_vehicles_key_is_refused(router, caplog):
    am2 = k.Keys("am2").autopilot_state
    async with bus_pair(router) as (a, b):
        sub = b.subscribe(am2)
        await matched(a, am2)
        with caplog.at_level(logging.WARNING, logger="aermani.bus"):
            # The default vehicle id (am1) on am2's key, then am2's own state: reliable, so both arrive, in order.
            a.publish(am2, m.VehicleState(position=m.Vec3(z=9.0), armed=True), reliable=True)
            a.publish(am2, m.VehicleState(vehicle_id="am2", position=m.Vec3(z=1.5)), reliable=True)
            got = await sub.recv(timeout=5)
        assert got.vehicle_id == "am2" and got.position.z == 1.5
        assert sub.malformed == 1 and b.stats()["malformed"] == 1
        assert "VehicleState of vehicle 'am1' on a key of vehicle 'am2'" in caplog.text
        with pytest.raises(TimeoutError):
            await sub.recv(timeout=0.5)


async def test_a_fleet_subscriber_checks_each_sample_against_its_own_key(router):
    fleet = k.REASONER_TASK_STATUS.fleet()
    on = {v: k.Keys(v).task_status for v in ("am1", "am2")}
    fleet_key = k.BoundTopic(f"{k.ROOT}/{k.FLEET_ID}/{k.REASONER_TASK_STATUS.name}", k.REASONER_TASK_STATUS)

    def status(vehicle: str, task: str) -> m.TaskStatus:
        return m.TaskStatus(vehicle_id=vehicle, task_id=task, command="pick up the red cup",
                            state=m.TaskState.RUNNING)

    async with bus_pair(router) as (a, b):
        sub = b.subscribe(fleet)
        await matched(a, fleet)
        a.publish(on["am1"], status("am1", "task-ok1"))
        a.publish(on["am2"], status("am1", "task-forged"))  # am1's status on am2's key
        a.publish(fleet_key, status("am1", "task-fleet"))  # one vehicle's status on the fleet-wide key
        a.publish(on["am2"], status("am2", "task-ok2"))
        got = [(await sub.recv(timeout=5)).task_id for _ in range(2)]
        assert got == ["task-ok1", "task-ok2"]
        assert sub.malformed == 2


async def test_a_request_naming_another_vehicle_is_refused_and_the_handler_never_runs(router):
    q = k.Query("test/vehicle_query", m.VehicleState, m.CancelReply, "test", "test").bind("am2")
    seen: list[m.VehicleState] = []

    async def handle(req: m.VehicleState) -> m.CancelReply:
        seen.append(req)
        return m.CancelReply(accepted=True)

    async with bus_pair(router) as (a, b):
        a.serve(q, handle)
        assert (await first_answer(b, q, m.VehicleState(vehicle_id="am2"))).accepted
        with pytest.raises(RemoteError, match="VehicleState of vehicle 'am1' on a key of vehicle 'am2'"):
            await b.query(q, m.VehicleState(), timeout=5)
        assert [r.vehicle_id for r in seen] == ["am2"]
