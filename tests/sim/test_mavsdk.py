"""A standard third-party client flies the simulator: MAVSDK (PyPI `mavsdk`, the native MAVSDK library) over
the ground-station link, the way QGroundControl-class tools and user scripts talk to PX4 SITL.

MAVSDK sends NaN in every COMMAND_LONG parameter it does not set, reads SYS_STATUS's PREARM_CHECK bit for
`health.is_armable`, sets parameters through the parameter protocol and starts offboard after a single
setpoint, so this test fails whenever the simulator stops behaving like PX4 on any of those.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync, ActionError, ActionResult
from mavsdk.asyncio.plugins.failure import FailureAsync
from mavsdk.asyncio.plugins.offboard import OffboardAsync, PositionNedYaw
from mavsdk.asyncio.plugins.param import ParamAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
from mavsdk.plugins.failure import FailureType, FailureUnit
from mavsdk.plugins.telemetry import FlightMode

from aermani.launcher import free_udp_port
from services.sim.core import SimCore
from services.sim.mavlink_server import LinkSettings, MavlinkServer
from services.sim.vehicle import VehicleParams
from shared.messages import Scenario


async def first(gen: AsyncIterator[Any], pred: Callable[[Any], bool] = lambda _: True, timeout: float = 20.0,
                what: str = "") -> Any:
    async def scan() -> Any:
        async for x in gen:
            if pred(x):
                return x
        raise AssertionError(f"stream ended before {what}")

    try:
        return await asyncio.wait_for(scan(), timeout)
    except TimeoutError:
        raise AssertionError(f"MAVSDK telemetry: no {what or 'matching value'} within {timeout} s") from None
    finally:
        await gen.aclose()


@pytest.fixture
def sim_gcs(request):
    """The simulator on a GCS link; `dynamics` from the test's parametrisation, else the configured one."""
    gcs = free_udp_port()
    # A long auto-disarm delay so the explicit disarm below is what disarms the vehicle.
    core = SimCore(Scenario(seed=5, target_object="red cup"), VehicleParams(disarm_after_land=60.0),
                   dynamics=getattr(request, "param", None))
    server = MavlinkServer(core, [LinkSettings("api", free_udp_port(), "127.0.0.1", free_udp_port()),
                                  LinkSettings("gcs", free_udp_port(), "127.0.0.1", gcs)], speed_factor=3.0)
    server.start()
    yield core, server, gcs
    server.stop()


async def test_mavsdk_flies_the_simulator_over_the_gcs_link(sim_gcs):
    core, server, gcs = sim_gcs

    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as mavsdk:
        await mavsdk.add_any_connection(f"udpin://127.0.0.1:{gcs}")
        drone = await mavsdk.first_autopilot(timeout_s=15.0)
        assert drone is not None, "MAVSDK found no autopilot on the GCS link"
        assert await drone.get_system_id() == 1
        action, tel = ActionAsync(drone), TelemetryAsync(drone)
        offboard, param, failure = OffboardAsync(drone), ParamAsync(drone), FailureAsync(drone)

        # Telemetry: position, health (armable from SYS_STATUS), flight mode, battery.
        start = await first(tel.subscribe_position_velocity_ned(), what="position")
        assert start.position.down_m == pytest.approx(0.0, abs=0.02)
        await first(tel.subscribe_health(), lambda h: h.is_armable and h.is_local_position_ok, what="armable")
        assert await first(tel.subscribe_flight_mode(), what="flight mode") == FlightMode.HOLD
        battery = await first(tel.subscribe_battery(), what="battery")
        assert 0.9 <= battery.remaining_percent <= 1.0 or 90 <= battery.remaining_percent <= 100

        # PX4's arming check: no position estimate (an injected GPS/VIO failure) -> arming refused with
        # TEMPORARILY_REJECTED and the reason as STATUSTEXT; it refuses injection until SYS_FAILURE_EN = 1.
        await param.set_param_float("SYS_FAILURE_EN", 1.0)
        await failure.inject(FailureUnit.SENSOR_VIO, FailureType.OFF, 0)
        # (subscribed before the arm command: the generator registers its callback on its first step)
        reason = asyncio.create_task(first(tel.subscribe_status_text(), lambda t: t.text.startswith("Preflight"),
                                           what="arming-denied STATUSTEXT"))
        await asyncio.sleep(0.2)
        with pytest.raises(ActionError) as refused:
            await action.arm()
        assert refused.value.result == ActionResult.COMMAND_DENIED
        assert (await reason).text == "Preflight Fail: No valid local position estimate"
        with core.lock:
            assert not core.vehicle.armed
        await failure.inject(FailureUnit.SENSOR_VIO, FailureType.OK, 0)
        await first(tel.subscribe_health(), lambda h: h.is_armable, what="armable again")

        # Arm (MAVSDK sends NaN in params 2-7), take off to MIS_TAKEOFF_ALT set through the parameter protocol.
        await action.arm()
        assert await first(tel.subscribe_armed(), lambda a: a, what="armed")
        await action.set_takeoff_altitude(1.5)
        await action.takeoff()
        await first(tel.subscribe_in_air(), lambda a: a, what="in air")
        hover = await first(tel.subscribe_position_velocity_ned(), lambda p: p.position.down_m < -1.45,
                            timeout=30, what="take-off altitude")
        n, e = hover.position.north_m, hover.position.east_m

        # Offboard position setpoints: one setpoint, start, then fly 1 m north and up to 2 m facing east.
        await offboard.set_position_ned(PositionNedYaw(n, e, -1.5, 0.0))
        await offboard.start()
        await first(tel.subscribe_flight_mode(), lambda m: m == FlightMode.OFFBOARD, what="OFFBOARD")
        await offboard.set_position_ned(PositionNedYaw(n + 1.0, e, -2.0, 90.0))
        there = await first(tel.subscribe_position_velocity_ned(),
                            lambda p: math.hypot(p.position.north_m - n - 1.0, p.position.east_m - e) < 0.05
                            and abs(p.position.down_m + 2.0) < 0.05, timeout=30, what="offboard target")
        heading = await first(tel.subscribe_heading(), lambda h: abs(h.heading_deg - 90.0) < 2.0,
                              what="heading 90 deg")
        assert there and heading
        with core.lock:
            assert math.hypot(core.vehicle.p[0] - n - 1.0, core.vehicle.p[1] - e) < 0.1

        # Land, then disarm on the ground.
        await offboard.stop()
        await action.land()
        await first(tel.subscribe_flight_mode(), lambda m: m == FlightMode.LAND, what="LAND")
        await first(tel.subscribe_in_air(), lambda a: not a, timeout=40, what="on ground")
        await action.disarm()
        assert await first(tel.subscribe_armed(), lambda a: not a, what="disarmed") is False
        with core.lock:
            assert not core.vehicle.armed and core.vehicle.on_ground
            assert core.counters.get("handler_errors", 0) == 0


@pytest.mark.parametrize("sim_gcs", ["multirotor"], indirect=True)
async def test_mavsdk_attitude_tilts_while_accelerating_and_is_level_in_hover(sim_gcs):
    """The attitude is flown, not drawn: MAVSDK's attitude telemetry (ATTITUDE / ATTITUDE_QUATERNION) shows a
    level vehicle in hover and the nose pitched down by several degrees while it accelerates north."""
    core, server, gcs = sim_gcs
    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as mavsdk:
        await mavsdk.add_any_connection(f"udpin://127.0.0.1:{gcs}")
        drone = await mavsdk.first_autopilot(timeout_s=15.0)
        assert drone is not None, "MAVSDK found no autopilot on the GCS link"
        action, tel, offboard = ActionAsync(drone), TelemetryAsync(drone), OffboardAsync(drone)
        await first(tel.subscribe_health(), lambda h: h.is_armable, what="armable")
        await action.arm()
        await action.set_takeoff_altitude(1.5)
        await action.takeoff()
        hover = await first(tel.subscribe_position_velocity_ned(), lambda p: p.position.down_m < -1.45
                            and abs(p.velocity.down_m_s) < 0.05, timeout=30, what="take-off altitude, still")
        n, e = hover.position.north_m, hover.position.east_m
        await offboard.set_position_ned(PositionNedYaw(n, e, -1.5, 0.0))
        await offboard.start()
        await first(tel.subscribe_flight_mode(), lambda m: m == FlightMode.OFFBOARD, what="OFFBOARD")
        await first(tel.subscribe_heading(), lambda h: min(h.heading_deg, 360.0 - h.heading_deg) < 1.0,
                    what="heading north")  # so that north is along the body's x axis below
        # Hover: the stream settles level (within 1 degree: in still air only the controller's residue tilts it).
        level = await first(tel.subscribe_attitude_euler(), lambda a: abs(a.roll_deg) < 1.0
                            and abs(a.pitch_deg) < 1.0, timeout=20, what="level attitude in hover")
        assert abs(level.roll_deg) < 1.0 and abs(level.pitch_deg) < 1.0
        # Accelerate north: to push north a multirotor tilts its thrust north, nose down (FRD pitch < 0).
        await offboard.set_position_ned(PositionNedYaw(n + 3.0, e, -1.5, 0.0))
        tilted = await first(tel.subscribe_attitude_euler(), lambda a: a.pitch_deg < -5.0, timeout=15,
                             what="nose-down pitch of more than 5 degrees while accelerating north")
        assert abs(tilted.roll_deg) < 3.0  # north along the body x axis: pitch, hardly any roll
        with core.lock:
            assert core.vehicle.v[0] > 0.0  # it is indeed moving north ...
        # ... and speeding up (5 deg of pitch come 0.16 s after the step, at 4 cm/s: how far it got by the time
        # the telemetry arrived depends on the link's latency, so the speed is awaited, not sampled).
        await first(tel.subscribe_position_velocity_ned(), lambda p: p.velocity.north_m_s > 0.1, timeout=10,
                    what="speed north above 0.1 m/s")
        # Arrived: braking pitched it nose up; it settles level again.
        await first(tel.subscribe_position_velocity_ned(), lambda p: abs(p.position.north_m - n - 3.0) < 0.05,
                    timeout=30, what="arrival")
        await first(tel.subscribe_attitude_euler(), lambda a: abs(a.roll_deg) < 1.0 and abs(a.pitch_deg) < 1.0,
                    timeout=10, what="level attitude after arrival")
        await offboard.stop()
