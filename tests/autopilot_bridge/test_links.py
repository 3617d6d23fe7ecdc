"""Links: a serial link (a real pseudo-terminal, the way a flight controller on TELEM2 or USB appears),
connection-string parsing, re-locking only onto the same system id after a link loss, gripper actuation
through DO_SET_ACTUATOR."""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import select
import socket
import threading

import pytest

from services.autopilot_bridge import px4
from services.autopilot_bridge.link import MavlinkLink, parse_connection
from services.autopilot_bridge.settings import BridgeSettings
from shared.errors import MavlinkError
from shared.messages import ArmCommand, GripperCommand, GripperState
from tests.autopilot_bridge.fake_px4 import SAFE_FAILSAFE_PARAMS, FakePX4, mavlink, param_reply
from tests.autopilot_bridge.rig import running_bridge
from tests.autopilot_bridge.test_bridge import bridge_and_fake
from tests.helpers import free_udp_port, wait_until


def test_connection_strings() -> None:
    assert parse_connection("serial:/dev/ttyACM0:921600") == ("/dev/ttyACM0", 921600)
    assert parse_connection("serial:/dev/serial/by-id/usb-CUAV_X7:57600") == ("/dev/serial/by-id/usb-CUAV_X7", 57600)
    assert parse_connection("serial:/dev/ttyAMA0", 115200) == ("/dev/ttyAMA0", 115200)
    assert parse_connection("/dev/ttyACM0", 57600) == ("/dev/ttyACM0", 57600)
    by_path = "/dev/serial/by-path/pci-0000:00:14.0-usb-0:1.2:1.0"
    assert parse_connection(f"serial:{by_path}") == (by_path, 921600)
    assert parse_connection(f"serial:{by_path}:57600") == (by_path, 57600)
    assert parse_connection(by_path, 115200) == (by_path, 115200)
    assert parse_connection("udpin:0.0.0.0:14540") == ("udpin:0.0.0.0:14540", 921600)
    assert parse_connection("tcp:127.0.0.1:5760")[0] == "tcp:127.0.0.1:5760"
    for bad in ("", "serial:", "ttyACM0", "http://px4", "serial:/dev/ttyACM0:99999999"):
        with pytest.raises(MavlinkError):
            parse_connection(bad)
    with pytest.raises(ValueError, match="unknown MAVLink connection"):
        BridgeSettings(connection="bluetooth:drone")
    assert BridgeSettings(connection=" serial:/dev/ttyACM0:921600 ").connection == "serial:/dev/ttyACM0:921600"


class SerialPX4:
    """A PX4 stand-in on the master side of a pseudo-terminal: heartbeats and position out, ACKs back."""

    def __init__(self) -> None:
        self.master, slave = os.openpty()
        self.device = os.ttyname(slave)
        self._slave = slave  # kept open so the pty survives until the bridge opens it
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.received: list = []
        self.armed = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> SerialPX4:
        self._thread.start()
        return self

    def send(self, msg) -> None:
        os.write(self.master, msg.pack(self.mav))

    def _run(self) -> None:
        n = 0
        while not self._stop.is_set():
            n += 1
            if n % 10 == 0:
                base = px4.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (px4.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
                self.send(self.mav.heartbeat_encode(2, px4.MAV_AUTOPILOT_PX4, base,
                                                    px4.encode_custom_mode("POSCTL"), 4))
                self.send(self.mav.local_position_ned_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
            ready, _, _ = select.select([self.master], [], [], 0.02)
            if not ready:
                continue
            try:
                data = os.read(self.master, 4096)
            except OSError:
                return
            for m in self.parser.parse_buffer(data) or []:
                self.received.append(m)
                if m.get_type() == "PARAM_REQUEST_READ" and (reply := param_reply(self.mav, SAFE_FAILSAFE_PARAMS,
                                                                                 m)) is not None:
                    self.send(reply)
                if m.get_type() == "COMMAND_LONG":
                    if m.command == px4.MAV_CMD_COMPONENT_ARM_DISARM:
                        self.armed = m.param1 == 1
                    self.send(self.mav.command_ack_encode(m.command, 0, 0, 0, m.get_srcSystem(),
                                                          m.get_srcComponent()))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        for fd in (self.master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)


@pytest.mark.parametrize("by_path", [False, True], ids=["tty", "by-path name with ':'"])
async def test_bridge_over_a_serial_link(by_path: bool, tmp_path) -> None:
    """Over a pseudo-terminal; as `serial:/dev/serial/by-path/...-usb-0:1.2:1.0` names one too (a symlink with
    the ':' of every by-path name, which pymavlink alone would take for a UDP address)."""
    fc = SerialPX4()
    device = fc.device
    if by_path:
        link_dir = tmp_path / "serial" / "by-path"
        link_dir.mkdir(parents=True)
        device = str(link_dir / "platform-3610000.xhci-usb-0:1.2:1.0")
        os.symlink(fc.device, device)

    s = BridgeSettings(connection=f"serial:{device}:921600", command_timeout_s=0.5, heartbeat_timeout_s=1.0)
    link = MavlinkLink(s.connection, baud=s.baud, source_system=s.source_system,
                       source_component=s.source_component)
    assert not link.is_udp
    fc.start()
    try:
        async with running_bridge(s, link) as bridge:
            await wait_until(lambda: bridge.link_ok and bridge.have_position, 20, what="PX4 over the serial link")
            assert bridge.target_system == 1 and bridge.state().mode == "POSCTL"
            res = await bridge.handle(ArmCommand())
            assert res.ok and res.ack_name == "MAV_RESULT_ACCEPTED", res
            await wait_until(lambda: any(m.get_type() == "HEARTBEAT" for m in fc.received), 5, what="our heartbeat")
            ours = next(m for m in fc.received if m.get_type() == "HEARTBEAT")
            assert (ours.get_srcSystem(), ours.get_srcComponent()) == (1, px4.MAV_COMP_ID_ONBOARD_COMPUTER)
            await wait_until(lambda: bridge.armed, 5, what="armed over serial")
    finally:
        fc.stop()


async def test_after_link_loss_only_the_same_system_is_locked_onto_again() -> None:
    async with bridge_and_fake() as (bridge, fake):
        first_peer = bridge.link.peer
        fake.heartbeats = False
        await wait_until(lambda: not bridge.link_ok, 10, what="link loss")
        port = int(bridge.s.connection.rsplit(":", 1)[1])
        other = FakePX4(port, system=2).start()  # another vehicle appears on the link
        try:
            await asyncio.sleep(1.5)
            assert not bridge.link_ok and bridge.target_system == 1 and bridge.link.peer == first_peer
            assert bridge.counters["wrong_system"] > 0
            same = FakePX4(port, system=1).start()  # our PX4 comes back, from a new address
            try:
                await wait_until(lambda: bridge.link_ok, 10, what="our system back")
                assert bridge.link.peer == ("127.0.0.1", same.port) != first_peer
                assert bridge.target_system == 1
            finally:
                same.stop()
        finally:
            other.stop()


async def test_gripper_through_an_actuator_output() -> None:
    async with bridge_and_fake(gripper_actuation="actuator", gripper_actuator_index=3,
                               gripper_actuator_closed=0.8, gripper_actuator_open=-0.6) as (bridge, fake):
        for action, want in (("close", 0.8), ("open", -0.6)):
            res = await bridge.handle(GripperCommand(action=action))
            assert res.ok, res.message
            cmd = [c for c in fake.commands if c.command == px4.MAV_CMD_DO_SET_ACTUATOR][-1]
            params = [cmd.param1, cmd.param2, cmd.param3, cmd.param4, cmd.param5, cmd.param6]
            assert params[2] == pytest.approx(want)
            assert all(math.isnan(v) for i, v in enumerate(params) if i != 2)  # other outputs untouched
            assert cmd.param7 == 0
        assert bridge.state().gripper == GripperState.OPEN
        assert not [c for c in fake.commands if c.command == px4.MAV_CMD_DO_GRIPPER]



def _outside_address() -> str | None:
    """An address of this machine that is not loopback (the interface a route to a documentation address uses)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("192.0.2.1", 9))  # no packet is sent: connect on UDP only picks the route
            addr = s.getsockname()[0]
        except OSError:
            return None
    return None if addr.startswith("127.") else addr


async def test_the_default_mavlink_port_is_not_reachable_from_outside_loopback() -> None:
    """With the default connection the bridge listens on loopback only: a PX4 (or anyone) sending to the
    machine's other address is never heard, while the same sender on loopback is."""
    outside = _outside_address()
    if outside is None:
        pytest.skip("this machine has no address besides loopback")
    port = free_udp_port()
    default = BridgeSettings.model_fields["connection"].default
    assert default.startswith("udpin:127.0.0.1:")
    link = MavlinkLink(default.rsplit(":", 1)[0] + f":{port}")
    seen: list[str] = []
    link.start(asyncio.get_running_loop(), lambda msg, addr, t: seen.append(msg.get_type()))
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            for _ in range(20):
                tx.sendto(mav.heartbeat_encode(2, px4.MAV_AUTOPILOT_PX4, 0, 0, 4).pack(mav), (outside, port))
                await asyncio.sleep(0.05)
            assert seen == []
            tx.sendto(mav.heartbeat_encode(2, px4.MAV_AUTOPILOT_PX4, 0, 0, 4).pack(mav), ("127.0.0.1", port))
            await wait_until(lambda: "HEARTBEAT" in seen, 10, what="a heartbeat sent to loopback")
    finally:
        link.close()
