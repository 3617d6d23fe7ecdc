"""Preflight: PX4's failsafe parameters read over real MAVLink/UDP, checked with the vehicle's state before the
bridge arms; a failed preflight refuses arm and takeoff with every reason until the operator overrides it."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time

import pytest

from services.autopilot_bridge.preflight import PARAM_NAMES, check_params, summary
from shared.keys import Keys
from shared.messages import ArmCommand, PreflightCommand, TakeoffCommand
from tests.autopilot_bridge.test_bridge import bridge_and_fake
from tests.helpers import BusCollector, bus_for, run_stack

SAFE = {"COM_OBL_RC_ACT": 5.0, "COM_OF_LOSS_T": 0.5, "GF_ACTION": 2.0, "GF_MAX_HOR_DIST": 6.0,
        "GF_MAX_VER_DIST": 3.0}


def test_rules_pass_a_safe_airframe_and_name_each_unsafe_value():
    assert all(c.ok for c in check_params(SAFE))
    bad = {c.name: c for c in check_params({**SAFE, "COM_OBL_RC_ACT": 7.0, "GF_ACTION": 0.0,
                                            "GF_MAX_VER_DIST": 0.0, "COM_OF_LOSS_T": float("nan")})}
    assert [n for n, c in bad.items() if not c.ok] == ["COM_OBL_RC_ACT", "COM_OF_LOSS_T", "GF_ACTION",
                                                       "GF_MAX_VER_DIST"]
    assert bad["COM_OBL_RC_ACT"].value == "7 (Disarm)" and "drop the vehicle" in bad["COM_OBL_RC_ACT"].reason
    assert bad["GF_ACTION"].value == "0 (None)" and "leave the room" in bad["GF_ACTION"].reason
    assert "did not report" in bad["COM_OF_LOSS_T"].reason
    missing = check_params({})
    assert len(missing) == len(PARAM_NAMES) and not any(c.ok for c in missing)


@pytest.mark.parametrize("action", [0.0, 4.0, 5.0])
def test_offboard_loss_land_is_accepted_with_a_note_hold_and_position_are_recommended(action):
    """Land (4) flies, but it lands wherever the vehicle is when the stack dies (on the table, on its cup):
    the passed check says so, and the summary carries it; Hold and Position pass without a note."""
    checks = check_params({**SAFE, "COM_OBL_RC_ACT": action})
    obl = next(c for c in checks if c.name == "COM_OBL_RC_ACT")
    assert obl.ok and all(c.ok for c in checks)
    assert "5 Hold" in obl.expected and "recommended" in obl.expected
    text = summary(checks)
    assert text.startswith("preflight passed")
    if action == 4.0:
        assert "wherever the vehicle is" in obl.reason and "furniture" in obl.reason and "Hold" in obl.reason
        assert "note: COM_OBL_RC_ACT = 4 (Land)" in text and "furniture" in text
    else:
        assert obl.reason == "" and "note" not in text


async def test_preflight_command_reads_the_parameters_from_px4():
    async with bridge_and_fake() as (bridge, fake):
        res = await bridge.handle(PreflightCommand())
        assert res.ok, res.message
        checks = {c.name: c for c in res.checks}
        assert checks["GF_ACTION"].value == "2 (Hold)" and checks["link"].ok and checks["on_ground"].ok
        asked = {m.param_id.rstrip("\x00") for m in list(fake.received) if m.get_type() == "PARAM_REQUEST_READ"}
        assert asked == set(PARAM_NAMES)


@pytest.mark.parametrize("command", [ArmCommand(), TakeoffCommand(altitude=1.2)], ids=["arm", "takeoff"])
async def test_unsafe_failsafe_refuses_to_arm_and_nothing_is_sent(command):
    async with bridge_and_fake() as (bridge, fake):
        fake.params["COM_OBL_RC_ACT"] = 7.0  # offboard loss: Disarm in the air
        fake.params["GF_ACTION"] = 0.0  # geofence: none
        res = await bridge.handle(command)
        assert not res.ok
        assert "preflight failed" in res.message and "COM_OBL_RC_ACT" in res.message and "GF_ACTION" in res.message
        assert "PREFLIGHT_OVERRIDE" in res.message
        assert {c.name for c in res.checks if not c.ok} == {"COM_OBL_RC_ACT", "GF_ACTION"}
        assert not any(m.get_type() == "COMMAND_LONG" and m.command == 400 for m in list(fake.received))
        assert not bridge.armed and not fake.armed


async def test_a_parameter_px4_never_reports_fails_the_preflight():
    async with bridge_and_fake() as (bridge, fake):
        del fake.params["GF_MAX_HOR_DIST"]
        res = await bridge.handle(PreflightCommand())
        assert not res.ok and "GF_MAX_HOR_DIST = not reported" in res.message


async def test_override_arms_despite_a_failed_preflight_and_the_verdict_records_it():
    async with bridge_and_fake(preflight_override=True, preflight_override_reason="bench, props off") as (bridge,
                                                                                                       fake):
        reports: list = []
        bridge._publish_report = reports.append  # what the bridge publishes on autopilot/preflight
        fake.params["GF_ACTION"] = 0.0
        assert not (await bridge.handle(PreflightCommand())).ok  # the verdict is still told
        res = await bridge.handle(ArmCommand())
        assert res.ok, res.message
        assert fake.armed
        assert [(r.trigger, r.ok, r.overridden) for r in reports] == [("request", False, False), ("arm", False, True)]
        assert reports[-1].override_reason == "bench, props off"
        assert any(c.name == "GF_ACTION" and not c.ok for c in reports[-1].checks)


def _preflight_cli(endpoint: str) -> subprocess.CompletedProcess:
    # The simulator renders 2 fps here (a fast suite) on a machine the rest of the suite keeps busy: the camera
    # and bus checks are held to that (their limits are the options'; what they measure is the same).
    return subprocess.run([sys.executable, "-m", "aermani.cli", "preflight", "--connect", endpoint, "--timeout", "30",
                           "--min-fps", "1", "--max-frame-age", "2", "--max-bus-ms", "2000"],
                          capture_output=True, text=True, timeout=120, env={**os.environ, "COLUMNS": "200"})


@pytest.mark.integration
@pytest.mark.parametrize("unsafe", [False, True], ids=["configured", "unsafe_failsafe"])
def test_aermani_preflight_against_the_simulator(tmp_path, unsafe):
    """`aermani preflight` over the real stack (simulator's PX4 over MAVLink/UDP, bridge, Zenoh): passes on the
    simulator's configuration; with the offboard-loss action set to Disarm and no geofence action it fails with
    the reasons, and the bridge refuses the takeoff."""
    env = {"AERMANI_SIM_FPS": "2"}
    if unsafe:
        env["AERMANI_SIM_PX4_PARAMS"] = "COM_OBL_RC_ACT=7,GF_ACTION=0"
    with run_stack(["sim", "autopilot_bridge"], tmp_path, env=env) as stack, \
            BusCollector(stack.endpoint, lambda bus: bus.subscribe(Keys("am1").autopilot_preflight).recv) as listener:
        # autopilot/preflight is collected on the listener's own thread while the CLI runs its own event loop
        reports = listener.items
        out = _preflight_cli(stack.endpoint)
        for _ in range(20):  # the bridge answers "no link to PX4" until the simulator's first heartbeat
            if "no link to PX4" not in out.stdout:
                break
            time.sleep(1.0)
            out = _preflight_cli(stack.endpoint)
        text = out.stdout + out.stderr
        if not unsafe:
            assert out.returncode == 0, text
            assert "preflight passed" in text and "COM_OBL_RC_ACT" in text and "5 (Hold)" in text
            assert "camera" in text and "mavlink_rate" in text and "bus_round_trip" in text
            listener.wait_for(lambda rs: any(r.trigger == "operator" for r in rs), 30, "the operator's report")
            operator = [r for r in reports if r.trigger == "operator"]
            assert operator and operator[-1].ok, reports  # the verdict is on the bus, so a recording keeps it
            assert {"camera", "mavlink_rate", "bus_round_trip", "GF_ACTION"} <= {c.name for c in operator[-1].checks}
            return
        assert out.returncode == 1, text
        assert "preflight failed" in text and "7 (Disarm)" in text and "0 (None)" in text

        async def takeoff() -> None:
            async with bus_for(stack) as bus:
                res = await bus.query(Keys("am1").autopilot_command, TakeoffCommand(altitude=1.2), timeout=60)
                assert not res.ok and "preflight failed" in res.message, res.message
                state = await bus.subscribe(Keys("am1").autopilot_state, maxsize=1).recv(timeout=10)
                assert not state.armed

        asyncio.run(takeoff())
        listener.wait_for(lambda rs: any(r.trigger == "takeoff" for r in rs), 30, "the take-off gate's report")
        gate = [r for r in reports if r.trigger == "takeoff"]
        assert gate and not gate[-1].ok and not gate[-1].overridden, reports
