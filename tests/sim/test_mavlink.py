"""The simulated vehicle over real UDP with a raw pymavlink client, the way a bridge or a GCS talks to PX4."""

from __future__ import annotations

import math
import socket
import time

import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mav

from aermani.launcher import free_udp_port
from services.sim.core import SimCore
from services.sim.mavlink_server import LinkSettings, MavlinkServer
from services.sim.vehicle import VehicleParams
from shared.messages import Scenario

OFFBOARD = (mavutil.PX4_CUSTOM_MAIN_MODE_OFFBOARD, 0)
LOITER = (mavutil.PX4_CUSTOM_MAIN_MODE_AUTO, mavutil.PX4_CUSTOM_SUB_MODE_AUTO_LOITER)
LAND = (mavutil.PX4_CUSTOM_MAIN_MODE_AUTO, mavutil.PX4_CUSTOM_SUB_MODE_AUTO_LAND)
POS_YAW_MASK = 2552


class Client:
    def __init__(self, port: int) -> None:
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255,
                                               source_component=mav.MAV_COMP_ID_ONBOARD_COMPUTER)
        self.hb = self.conn.wait_heartbeat(timeout=20)
        assert self.hb is not None, "no heartbeat from the sim"

    def recv(self, kind: str, cond=lambda m: True, timeout: float = 20.0):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            m = self.conn.recv_match(type=kind, blocking=True, timeout=0.2)
            if m is not None and cond(m):
                return m
        raise TimeoutError(f"no {kind} matching the condition within {timeout} s")

    def drain(self, limit_s: float = 2.0) -> None:
        """Read what queued up while the test did not read (a sleep, a burst of setpoints): a full UDP receive
        buffer drops every new datagram, the COMMAND_ACK that answers the next command among them."""
        deadline = time.monotonic() + limit_s
        while time.monotonic() < deadline and self.conn.recv_match(blocking=False) is not None:
            pass

    def command(self, cmd: int, *p: float, target: int = 1) -> int:
        params = list(p) + [0.0] * (7 - len(p))
        self.drain()
        self.conn.mav.command_long_send(target, 1, cmd, 0, *params)
        return self.recv("COMMAND_ACK", lambda m: m.command == cmd, 10.0).result

    def mode(self) -> tuple[int, int]:
        hb = self.recv("HEARTBEAT", lambda m: m.get_srcSystem() == 1)
        return (hb.custom_mode >> 16) & 0xFF, (hb.custom_mode >> 24) & 0xFF

    def wait_mode(self, want: tuple[int, int], timeout: float = 20.0) -> None:
        deadline = time.monotonic() + timeout
        while self.mode() != want:
            if time.monotonic() > deadline:
                raise TimeoutError(f"mode {want} not reached")

    def armed(self) -> bool:
        return bool(self.recv("HEARTBEAT", lambda m: m.get_srcSystem() == 1).base_mode
                    & mav.MAV_MODE_FLAG_SAFETY_ARMED)

    def setpoint(self, n: float, e: float, d: float, yaw: float) -> None:
        self.conn.mav.set_position_target_local_ned_send(0, 1, 1, mav.MAV_FRAME_LOCAL_NED, POS_YAW_MASK,
                                                         n, e, d, 0, 0, 0, 0, 0, 0, yaw, 0)

    def stream_until(self, n: float, e: float, d: float, yaw: float, cond, timeout: float = 40.0):
        """Send setpoints at 20 Hz until cond(LOCAL_POSITION_NED, ATTITUDE) holds."""
        deadline = time.monotonic() + timeout
        att = None
        while time.monotonic() < deadline:
            self.setpoint(n, e, d, yaw)
            end = time.monotonic() + 0.05
            pos = None
            while time.monotonic() < end:
                m = self.conn.recv_match(blocking=True, timeout=max(0.0, end - time.monotonic()))
                if m is None:
                    continue
                if m.get_type() == "LOCAL_POSITION_NED":
                    pos = m
                elif m.get_type() == "ATTITUDE":
                    att = m
            if pos is not None and att is not None and cond(pos, att):
                return pos, att
        raise TimeoutError(f"setpoint ({n}, {e}, {d}, {yaw}) not reached")

    def close(self) -> None:
        self.conn.close()


@pytest.fixture
def sim():
    api, gcs = free_udp_port(), free_udp_port()
    core = SimCore(Scenario(seed=5, target_object="red cup"),
                   VehicleParams(failsafe_land_delay=1.0, disarm_after_land=0.5))
    server = MavlinkServer(core, [LinkSettings("api", free_udp_port(), "127.0.0.1", api),
                                  LinkSettings("gcs", free_udp_port(), "127.0.0.1", gcs)], speed_factor=3.0)
    server.start()
    client = Client(api)
    # Faster heartbeats so mode changes show up quickly (also exercises SET_MESSAGE_INTERVAL).
    assert client.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_HEARTBEAT, 100_000) == 0
    yield core, server, client, gcs
    client.close()
    server.stop()


def test_heartbeat_identity_and_capabilities(sim):
    core, server, client, gcs = sim
    hb = client.hb
    assert hb.type == mav.MAV_TYPE_QUADROTOR and hb.autopilot == mav.MAV_AUTOPILOT_PX4
    assert hb.base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
    assert client.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == 0
    av = client.recv("AUTOPILOT_VERSION")
    assert av.capabilities & mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert client.command(mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1) == 0
    assert client.command(31999) == mav.MAV_RESULT_UNSUPPORTED
    ext = client.recv("EXTENDED_SYS_STATE")
    assert ext.landed_state == mav.MAV_LANDED_STATE_ON_GROUND
    sys = client.recv("SYS_STATUS")
    assert 10_000 < sys.voltage_battery < 13_000 and 0 < sys.battery_remaining <= 100
    # Rates are honoured per message id: LOCAL_POSITION_NED off, then back on.
    assert client.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, -1) == 0
    time.sleep(0.3)
    client.drain()
    t_end = time.monotonic() + 0.6
    n_pos = 0
    while time.monotonic() < t_end:
        m = client.conn.recv_match(blocking=True, timeout=0.1)
        n_pos += m is not None and m.get_type() == "LOCAL_POSITION_NED"
    assert n_pos == 0
    assert client.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 0) == 0
    client.recv("LOCAL_POSITION_NED", timeout=5)
    # Parameters as ground stations read and write them; a write reaches the vehicle.
    client.conn.mav.param_request_read_send(1, 1, b"MIS_TAKEOFF_ALT", -1)
    pv = client.recv("PARAM_VALUE", lambda m: m.param_id == "MIS_TAKEOFF_ALT")
    assert pv.param_value == pytest.approx(1.5)
    client.conn.mav.param_set_send(1, 1, b"MIS_TAKEOFF_ALT", 2.0, mav.MAV_PARAM_TYPE_REAL32)
    client.recv("PARAM_VALUE", lambda m: m.param_id == "MIS_TAKEOFF_ALT" and abs(m.param_value - 2.0) < 1e-6)
    assert core.vehicle.params.takeoff_alt == pytest.approx(2.0)
    # COMMAND_INT takes the same path as COMMAND_LONG.
    client.conn.mav.command_int_send(1, 1, 0, mav.MAV_CMD_DO_SET_MODE, 0, 0, 1, *LOITER, 0, 0, 0, 0)
    assert client.recv("COMMAND_ACK", lambda m: m.command == mav.MAV_CMD_DO_SET_MODE).result == 0
    # The GCS link streams too, to its own port.
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", gcs))
        s.settimeout(5)
        assert s.recv(2048)


def test_arm_offboard_takeoff_goto_gripper_and_land(sim):
    core, server, client, _ = sim
    # OFFBOARD is refused without a setpoint stream.
    assert client.command(mav.MAV_CMD_DO_SET_MODE, 1, *OFFBOARD) == mav.MAV_RESULT_TEMPORARILY_REJECTED
    assert client.command(mav.MAV_CMD_NAV_TAKEOFF) == mav.MAV_RESULT_DENIED  # disarmed
    assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    assert client.armed()
    assert client.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 1.5) == 0
    client.recv("EXTENDED_SYS_STATE", lambda m: m.landed_state == mav.MAV_LANDED_STATE_IN_AIR, 30)
    pos = client.recv("LOCAL_POSITION_NED", lambda m: abs(m.z + 1.5) < 0.1, 30)
    # Disarm in the air is denied unless forced.
    assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mav.MAV_RESULT_TEMPORARILY_REJECTED
    # Stream for > 1 s, then OFFBOARD is accepted.
    n0, e0 = pos.x, pos.y
    deadline = time.monotonic() + 1.3
    while time.monotonic() < deadline:
        client.setpoint(n0, e0, -1.5, 0.0)
        time.sleep(0.05)
    client.setpoint(n0, e0, -1.5, 0.0)
    assert client.command(mav.MAV_CMD_DO_SET_MODE, 1, *OFFBOARD) == 0
    client.setpoint(n0, e0, -1.5, 0.0)

    # Fly to the target object (ground truth) with the gripper point 3 cm below its top, between the open
    # fingers; the estimate drifts a few cm from the truth (realistic), well inside the fingers' reach.
    with core.lock:
        cup = core.world.by_name("red cup")
        cx, cy, top = float(cup.center[0]), float(cup.center[1]), cup.top_z
    hover_z = -(top - 0.03 + 0.22)
    client.stream_until(cy, cx, -2.0, math.pi / 2,
                        lambda p, a: math.hypot(p.x - cy, p.y - cx) < 0.03 and abs(a.yaw - math.pi / 2) < 0.05)
    client.stream_until(cy, cx, hover_z, math.pi / 2,
                        lambda p, a: abs(p.z - hover_z) < 0.02 and math.hypot(p.x - cy, p.y - cx) < 0.02)
    client.setpoint(cy, cx, hover_z, math.pi / 2)
    assert client.command(mav.MAV_CMD_DO_GRIPPER, 1, mav.GRIPPER_ACTION_GRAB) == 0
    # The fingers close on it: held by contact, announced with the measured width.
    client.stream_until(cy, cx, hover_z, math.pi / 2, lambda p, a: core.world.holding() is not None, 10)
    with core.lock:
        assert core.world.holding().name == "red cup"
        assert abs(core.vehicle.finger_width - cup.size[0]) < 0.01

    # Carry it to a table and release just above it: it lands on the table.
    with core.lock:
        table = next(s for s in core.world.surfaces if s.name != cup.support)
        tx, ty, ttop, tname = float(table.center[0]), float(table.center[1]), table.top_z, table.name
    client.stream_until(ty, tx, -2.0, 0.0, lambda p, a: math.hypot(p.x - ty, p.y - tx) < 0.03)
    drop_z = -(ttop + 0.11 + 0.02 - 0.03 + 0.22)
    client.stream_until(ty, tx, drop_z, 0.0, lambda p, a: abs(p.z - drop_z) < 0.03)
    assert client.command(mav.MAV_CMD_DO_GRIPPER, 1, mav.GRIPPER_ACTION_RELEASE) == 0
    from shared.messages import JudgeRequest

    client.stream_until(ty, tx, drop_z, 0.0, lambda p, a: core.judge(
        JudgeRequest(op="on_surface", object="red cup", surface=tname)).ok, 10)
    assert not core.judge(JudgeRequest(op="held")).ok

    client.stream_until(n0, e0, -1.5, 0.0, lambda p, a: math.hypot(p.x - n0, p.y - e0) < 0.05)
    assert client.command(mav.MAV_CMD_NAV_LAND) == 0
    client.recv("EXTENDED_SYS_STATE", lambda m: m.landed_state == mav.MAV_LANDED_STATE_ON_GROUND, 40)
    assert client.recv("LOCAL_POSITION_NED").z > -0.02
    assert core.judge(JudgeRequest()).collisions == ()
    deadline = time.monotonic() + 10
    while client.armed():  # auto-disarm after landing
        assert time.monotonic() < deadline


def _param(client: Client, name: str) -> float:
    client.conn.mav.param_request_read_send(1, 1, name.encode(), -1)
    return client.recv("PARAM_VALUE", lambda m: m.param_id == name).param_value


def _fly_offboard_then_stop(core, client: Client) -> None:
    """Arm, stream setpoints, OFFBOARD to 1 m, then stop streaming (a dead bridge)."""
    assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    for _ in range(10):
        client.setpoint(0, 0, -1.0, 0.0)
        time.sleep(0.05)
    assert client.command(mav.MAV_CMD_DO_SET_MODE, 1, *OFFBOARD) == 0
    with core.lock:
        n, e = float(core.vehicle.p[0]), float(core.vehicle.p[1])
    client.stream_until(n, e, -1.0, 0.0, lambda p, a: abs(p.z + 1.0) < 0.05)


def test_offboard_loss_holds_by_default_well_past_the_failsafe_delay(sim):
    """COM_OBL_RC_ACT=5 (Hold), the simulator's default, reported as flown: offboard loss holds in the air
    long past COM_FAIL_ACT_T, and a new OFFBOARD (a restarted bridge) takes the vehicle back."""
    core, server, client, _ = sim
    assert _param(client, "COM_OBL_RC_ACT") == 5.0 and core.vehicle.params.offboard_loss_action == 5
    assert _param(client, "COM_FAIL_ACT_T") == pytest.approx(1.0)  # the vehicle's failsafe_land_delay
    _fly_offboard_then_stop(core, client)
    client.wait_mode(LOITER, 10)
    time.sleep(3 * core.vehicle.params.failsafe_land_delay)
    assert client.mode() == LOITER and client.armed()
    assert client.recv("EXTENDED_SYS_STATE").landed_state == mav.MAV_LANDED_STATE_IN_AIR
    assert client.recv("LOCAL_POSITION_NED").z < -0.9
    for _ in range(10):
        client.setpoint(0, 0, -1.2, 0.0)
        time.sleep(0.05)
    assert client.command(mav.MAV_CMD_DO_SET_MODE, 1, *OFFBOARD) == 0
    client.wait_mode(OFFBOARD, 5)


def test_offboard_loss_holds_then_lands(sim):
    """COM_OBL_RC_ACT=4 (Land), set over MAVLink: hold for COM_FAIL_ACT_T, land in place, disarm."""
    core, server, client, _ = sim
    client.conn.mav.param_set_send(1, 1, b"COM_OBL_RC_ACT", 4.0, mav.MAV_PARAM_TYPE_REAL32)
    client.recv("PARAM_VALUE", lambda m: m.param_id == "COM_OBL_RC_ACT" and m.param_value == 4.0)
    assert core.vehicle.params.offboard_loss_action == 4
    assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    deadline = time.monotonic() + 1.3
    while time.monotonic() < deadline:
        client.setpoint(0, 0, -1.0, 0.0)
        time.sleep(0.05)
    client.setpoint(0, 0, -1.0, 0.0)
    assert client.command(mav.MAV_CMD_DO_SET_MODE, 1, *OFFBOARD) == 0
    with core.lock:
        n, e = float(core.vehicle.p[0]), float(core.vehicle.p[1])
    client.stream_until(n, e, -1.0, 0.0, lambda p, a: abs(p.z + 1.0) < 0.05)
    stats = core.setpoint_stats()  # every setpoint's kernel receive time is recorded for the jitter figures
    assert stats["n"] == core.vehicle.setpoints_received > 20 and stats["interval_ms_p50"] > 0
    # Stop streaming: hold, then land, then disarm on the ground.
    client.wait_mode(LOITER, 10)
    client.recv("STATUSTEXT", lambda m: "offboard" in m.text.lower(), 5)
    client.wait_mode(LAND, 10)
    client.recv("EXTENDED_SYS_STATE", lambda m: m.landed_state == mav.MAV_LANDED_STATE_ON_GROUND, 30)
    deadline = time.monotonic() + 10
    while client.armed():
        assert time.monotonic() < deadline


def test_injected_signal_loss_silences_both_ways_while_the_vehicle_flies_on(sim):
    """sim/fault `mavlink_signal off` (PX4's `failure mavlink_signal off`): nothing goes out, what comes in is
    dropped, the vehicle flies on under PX4's offboard-loss failsafe; the links come back by themselves."""
    from services.sim.app import inject_fault

    core, server, client, _ = sim
    assert not inject_fault({"unit": "gps", "type": "off"}, None, server)["ok"]
    assert not inject_fault({"unit": "mavlink_signal", "type": "stuck"}, None, server)["ok"]
    assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    for _ in range(26):
        client.setpoint(0, 0, -1.0, 0.0)
        time.sleep(0.05)
    assert client.command(mav.MAV_CMD_DO_SET_MODE, 1, *OFFBOARD) == 0
    with core.lock:
        n, e = float(core.vehicle.p[0]), float(core.vehicle.p[1])
    client.stream_until(n, e, -1.0, 0.0, lambda p, a: abs(p.z + 1.0) < 0.1)
    assert inject_fault({"unit": "mavlink_signal", "type": "off", "duration_s": 2.5}, None, server)["ok"]
    client.drain()  # what was sent before the loss
    with pytest.raises(TimeoutError):
        client.stream_until(n, e, -1.0, 0.0, lambda p, a: True, timeout=1.0)  # setpoints out, nothing back
    with core.lock:
        assert core.counters.get("dropped_signal_lost", 0) > 0
        assert core.vehicle.mode_name != "OFFBOARD"  # PX4's failsafe took over without setpoints
    client.recv("HEARTBEAT", timeout=10)  # the links are back by themselves
    assert client.mode() in (LOITER, LAND)


def test_bad_input_changes_nothing(sim):
    core, server, client, _ = sim
    with core.lock:
        before = (core.vehicle.true_position_enu(), core.vehicle.armed, core.vehicle.mode_name)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    target = server.links[0].sock.getsockname()
    sock.sendto(b"\xfd\x09garbage-bytes\x00\xff" * 20, target)
    sock.sendto(bytes(range(256)), target)
    # A valid arm command for another system id, and one for another component, are ignored.
    client.conn.mav.command_long_send(7, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    client.conn.mav.command_long_send(1, 42, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    # A setpoint for another system and an unknown message (valid CRC, not handled) are ignored too.
    client.conn.mav.set_position_target_local_ned_send(0, 9, 1, mav.MAV_FRAME_LOCAL_NED, POS_YAW_MASK,
                                                       5, 5, -5, 0, 0, 0, 0, 0, 0, 0, 0)
    client.conn.mav.debug_send(0, 1, 2.0)
    sock.close()
    # Still alive and answering, nothing changed.
    assert client.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_HOME_POSITION) == 0
    client.recv("HOME_POSITION")
    assert not client.armed()
    with core.lock:
        after = (core.vehicle.true_position_enu(), core.vehicle.armed, core.vehicle.mode_name)
        counters = dict(core.counters)
    # The landed vehicle does not move (the physics settles it on its gear by micrometres).
    assert np.abs(after[0] - before[0]).max() < 1e-3 and after[1:] == before[1:]
    assert counters.get("bad_input", 0) >= 1
    assert counters.get("wrong_target", 0) >= 3
    assert counters.get("unknown_messages", 0) >= 1
    assert core.vehicle.setpoints_received == 0


def test_garbage_never_redirects_telemetry(sim):
    """Telemetry goes to the configured remote, or to a peer that sent valid MAVLink; garbage from a third
    address moves nothing, on both links."""
    core, server, client, gcs = sim
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger.bind(("127.0.0.1", 0))
    stranger.settimeout(0.5)
    try:
        remotes = [lk.remote for lk in server.links]
        for lk in server.links:
            target = lk.sock.getsockname()
            stranger.sendto(b"\xfd\x09garbage-bytes\x00\xff" * 20, target)
            stranger.sendto(bytes(range(256)), target)
            stranger.sendto(b"\xfe\x05\x00\x01\x01\x00hello", target)  # a v1 header with a broken CRC
        assert client.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_HOME_POSITION) == 0
        assert [lk.remote for lk in server.links] == remotes
        with pytest.raises(TimeoutError):  # the stranger gets no telemetry
            stranger.recv(2048)
        assert core.counters.get("bad_input", 0) >= 3
        client.recv("LOCAL_POSITION_NED", timeout=2)  # the real peer still does

        # A peer that speaks valid MAVLink from a new address is answered there (as PX4's UDP links do).
        peer = mav.MAVLink(None, srcSystem=250, srcComponent=mav.MAV_COMP_ID_MISSIONPLANNER)
        stranger.sendto(peer.heartbeat_encode(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0).pack(peer),
                        server.links[1].sock.getsockname())
        stranger.settimeout(5)
        assert stranger.recv(2048)
        assert server.links[1].remote == stranger.getsockname() and server.links[0].remote == remotes[0]
    finally:
        stranger.close()


def test_nan_params_mean_default_and_arming_checks(sim):
    core, server, client, _ = sim
    nan = math.nan
    # MAVSDK-style arm: param1 = 1, everything else NaN ("use the default"): accepted, then disarm likewise.
    assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1, nan, nan, nan, nan, nan, nan) == 0
    assert client.armed()
    assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, nan, nan, nan, nan, nan, nan) == 0
    assert not client.armed()
    # An arming action that is neither 0 nor 1 is refused as PX4 does, and explained.
    assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 3) == mav.MAV_RESULT_UNSUPPORTED
    client.recv("STATUSTEXT", lambda m: "Unsupported ARM_DISARM param" in m.text, 5)
    # COMMAND_INT with NaN in params 3-4 and INT32_MAX ("unset") in x/y.
    client.conn.mav.command_int_send(1, 1, 0, mav.MAV_CMD_DO_SET_MODE, 0, 0, 1, *LOITER, nan, 2**31 - 1,
                                     2**31 - 1, nan)
    assert client.recv("COMMAND_ACK", lambda m: m.command == mav.MAV_CMD_DO_SET_MODE).result == 0
    # NaN interval = default rate; NaN message id = nothing to stream (denied, not a crash).
    assert client.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE, nan) == 0
    assert client.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, nan, 1e5) == mav.MAV_RESULT_DENIED

    # No position estimate: failure injection is refused until SYS_FAILURE_EN = 1, then arming is
    # TEMPORARILY_REJECTED with PX4's reason, OFFBOARD too, and LOCAL_POSITION_NED stops.
    vio_off = (mav.FAILURE_UNIT_SENSOR_VIO, mav.FAILURE_TYPE_OFF)
    assert client.command(mav.MAV_CMD_INJECT_FAILURE, *vio_off) == mav.MAV_RESULT_DENIED
    client.conn.mav.param_set_send(1, 1, b"SYS_FAILURE_EN", 1.0, mav.MAV_PARAM_TYPE_REAL32)
    client.recv("PARAM_VALUE", lambda m: m.param_id == "SYS_FAILURE_EN" and m.param_value == 1.0)
    assert client.command(mav.MAV_CMD_INJECT_FAILURE, *vio_off) == 0
    assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_TEMPORARILY_REJECTED
    client.recv("STATUSTEXT", lambda m: m.text == "Preflight Fail: No valid local position estimate", 5)
    status = client.recv("SYS_STATUS")
    assert not status.onboard_control_sensors_health & mav.MAV_SYS_STATUS_PREARM_CHECK
    client.drain()
    with pytest.raises(TimeoutError):
        client.recv("LOCAL_POSITION_NED", timeout=0.5)
    assert not client.armed()
    # Forcing (21196) skips the checks, as in PX4; the estimate back, arming works normally.
    assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1, 21196) == 0
    assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0) == 0
    assert client.command(mav.MAV_CMD_INJECT_FAILURE, mav.FAILURE_UNIT_SENSOR_VIO, mav.FAILURE_TYPE_OK) == 0
    client.recv("LOCAL_POSITION_NED", timeout=2)
    assert client.recv("SYS_STATUS").onboard_control_sensors_health & mav.MAV_SYS_STATUS_PREARM_CHECK
    assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    # Losing the estimate in the air is a failsafe: PX4 lands.
    assert client.command(mav.MAV_CMD_NAV_TAKEOFF, nan, nan, nan, nan, nan, nan, 1.0) == 0
    client.recv("EXTENDED_SYS_STATE", lambda m: m.landed_state == mav.MAV_LANDED_STATE_IN_AIR, 30)
    assert client.command(mav.MAV_CMD_INJECT_FAILURE, *vio_off) == 0
    client.wait_mode(LAND, 5)
    # ...and nothing that needs a position can be entered meanwhile.
    assert client.command(mav.MAV_CMD_DO_SET_MODE, 1, *LOITER) == mav.MAV_RESULT_TEMPORARILY_REJECTED
    with core.lock:
        assert core.counters.get("handler_errors", 0) == 0


def test_gripper_on_an_actuator_output(sim):
    core, server, client, _ = sim
    nan = math.nan
    assert client.command(mav.MAV_CMD_DO_SET_ACTUATOR, 1.0, nan, nan, nan, nan, nan, 0) == 0
    client.recv("STATUSTEXT", lambda m: m.text.startswith("Gripper closing"), 5)
    with core.lock:
        assert core.vehicle.gripper_closed
    assert client.command(mav.MAV_CMD_DO_SET_ACTUATOR, nan, 1.0, nan, nan, nan, nan, 0) == 0  # another output
    with core.lock:
        assert core.vehicle.gripper_closed
    assert client.command(mav.MAV_CMD_DO_SET_ACTUATOR, -1.0, nan, nan, nan, nan, nan, 0) == 0
    with core.lock:
        assert not core.vehicle.gripper_closed


def test_failsafe_params_from_the_settings_are_flown_and_reported(monkeypatch):
    """AERMANI_SIM_PX4_PARAMS sets what the vehicle flies on offboard loss; the reported value is the flown
    one, and without it the settings' failsafe_land_delay is COM_FAIL_ACT_T."""
    from services.sim.app import build
    from services.sim.settings import SimSettings

    ports = {f"AERMANI_SIM_{k}": str(free_udp_port()) for k in ("API_LOCAL_PORT", "API_PORT", "GCS_LOCAL_PORT",
                                                               "GCS_PORT")}
    for k, val in {**ports, "AERMANI_SIM_PX4_PARAMS": "COM_OBL_RC_ACT=0", "AERMANI_SIM_FAILSAFE_LAND_DELAY": "2",
                   "AERMANI_SIM_CAMERA": "false"}.items():
        monkeypatch.setenv(k, val)
    core, server = build(SimSettings())
    try:
        assert server.params["COM_OBL_RC_ACT"] == 0.0 and core.vehicle.params.offboard_loss_action == 0
        assert server.params["COM_FAIL_ACT_T"] == 2.0 and core.vehicle.params.failsafe_land_delay == 2.0
    finally:
        server.stop()
    monkeypatch.setenv("AERMANI_SIM_PX4_PARAMS", "COM_OBL_RC_ACT=4,COM_FAIL_ACT_T=1.5")
    core, server = build(SimSettings())
    try:
        assert core.vehicle.params.offboard_loss_action == 4 and core.vehicle.params.failsafe_land_delay == 1.5
    finally:
        server.stop()
