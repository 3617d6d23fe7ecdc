"""The bridge against a tiny raw-pymavlink PX4 over real UDP: handshake, commands, NED setpoints, bad input,
link and offboard loss. No Zenoh here (see test_bus.py and the integration tests)."""

from __future__ import annotations

import asyncio
import contextlib
import math
import socket

import pytest

from services.autopilot_bridge import px4
from services.autopilot_bridge.bridge import Bridge
from services.autopilot_bridge.link import MavlinkLink
from services.autopilot_bridge.settings import BridgeSettings
from shared.messages import (
    ArmCommand,
    GotoCommand,
    GripperCommand,
    HoldCommand,
    LandCommand,
    TakeoffCommand,
    Vec3,
)
from tests.autopilot_bridge.fake_px4 import FakePX4, mavlink
from tests.helpers import free_udp_port, wait_until


@contextlib.asynccontextmanager
async def bridge_and_fake(fake_init=None, **overrides):
    """`fake_init(fake)` sets the fake PX4's state before its first message (e.g. already flying)."""
    port = free_udp_port()
    s = BridgeSettings(**{"connection": f"udpin:127.0.0.1:{port}", "command_timeout_s": 0.5,
                          "offboard_warmup_s": 0.3, "heartbeat_timeout_s": 1.0, "takeoff_timeout_s": 20.0,
                          **overrides})
    link = MavlinkLink(s.connection, source_system=s.source_system, source_component=s.source_component)
    bridge = Bridge(None, s, link)
    stop = asyncio.Event()
    link.start(asyncio.get_running_loop(), bridge.on_message)
    hb = asyncio.create_task(bridge.heartbeat_loop(stop))
    fake = FakePX4(port)
    if fake_init is not None:
        fake_init(fake)
    fake.start()
    try:
        await wait_until(lambda: bridge.link_ok and bridge.have_position, 20, what="bridge sees the fake PX4")
        yield bridge, fake
    finally:
        stop.set()
        hb.cancel()
        for t in list(bridge._tasks):
            t.cancel()
        bridge.stream.stop()
        link.close()
        fake.stop()


async def test_handshake_heartbeat_and_message_rates() -> None:
    async with bridge_and_fake() as (bridge, fake):
        assert bridge.target_system == 1 and bridge.target_component == 1
        assert bridge.link.peer == ("127.0.0.1", fake.port)
        await wait_until(lambda: "HEARTBEAT" in fake.names(), 10, what="our heartbeat")
        hb = next(m for m in fake.received if m.get_type() == "HEARTBEAT")
        assert (hb.type, hb.autopilot) == (px4.MAV_TYPE_ONBOARD_CONTROLLER, px4.MAV_AUTOPILOT_INVALID)
        # Its own identity: a companion component of the vehicle's system, never a ground station's 255.
        assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, px4.MAV_COMP_ID_ONBOARD_COMPUTER)

        def intervals() -> dict[int, float]:
            return {int(c.param1): c.param2 for c in list(fake.commands)
                    if c.command == px4.MAV_CMD_SET_MESSAGE_INTERVAL}

        await wait_until(lambda: len(intervals()) >= 4, 10, what="rate requests")
        assert intervals()[px4.MSG_LOCAL_POSITION_NED] == 20000.0
        assert intervals()[px4.MSG_ATTITUDE] == 20000.0
        st = bridge.state()
        assert st.link_ok and st.mode == "POSCTL" and not st.armed and st.landed_state == "on_ground"


async def test_arm_ack_accepted_and_denied() -> None:
    async with bridge_and_fake() as (bridge, fake):
        fake.deny_arm = True
        res = await bridge.handle(ArmCommand())
        assert not res.ok and res.ack_code == 2 and res.ack_name == "MAV_RESULT_DENIED"
        assert "denied" in res.message
        fake.deny_arm = False
        res = await bridge.handle(ArmCommand())
        assert res.ok and res.ack_code == 0 and res.ack_name == "MAV_RESULT_ACCEPTED"
        await wait_until(lambda: bridge.state().armed, 10, what="armed in HEARTBEAT")


async def test_configured_identity_is_used_and_acks_for_others_are_ignored() -> None:
    async with bridge_and_fake(source_system=7, source_component=192) as (bridge, fake):
        await wait_until(lambda: "HEARTBEAT" in fake.names(), 10, what="our heartbeat")
        hb = next(m for m in fake.received if m.get_type() == "HEARTBEAT")
        assert (hb.get_srcSystem(), hb.get_srcComponent()) == (7, 192)
        # An ACK addressed to another component of our system (or to a GCS) does not answer our command.
        fake.ack_commands = False
        task = asyncio.create_task(bridge.handle(GripperCommand(action="close")))
        await wait_until(lambda: any(c.command == px4.MAV_CMD_DO_GRIPPER for c in fake.commands), 5,
                         what="gripper command")
        cmd = next(c for c in fake.commands if c.command == px4.MAV_CMD_DO_GRIPPER)
        assert (cmd.get_srcSystem(), cmd.get_srcComponent()) == (7, 192)
        fake.send(fake.mav.command_ack_encode(px4.MAV_CMD_DO_GRIPPER, 0, 0, 0, 7, 191))
        fake.send(fake.mav.command_ack_encode(px4.MAV_CMD_DO_GRIPPER, 0, 0, 0, 255, 190))
        await asyncio.sleep(0.2)
        assert not task.done()
        fake.send(fake.mav.command_ack_encode(px4.MAV_CMD_DO_GRIPPER, 0, 0, 0, 7, 192))
        res = await task
        assert res.ok, res.message


async def test_no_ack_gives_clear_failure_after_retries() -> None:
    async with bridge_and_fake(command_attempts=2) as (bridge, fake):
        fake.ack_commands = False
        res = await bridge.handle(GripperCommand(action="close"))
        assert not res.ok and res.ack_code is None and "no COMMAND_ACK" in res.message
        sent = [c for c in fake.commands if c.command == px4.MAV_CMD_DO_GRIPPER]
        assert [c.confirmation for c in sent] == [0, 1]


async def test_takeoff_goto_hold_gripper_land_in_ned() -> None:
    async with bridge_and_fake() as (bridge, fake):
        res = await bridge.handle(TakeoffCommand(altitude=1.5))
        assert res.ok, res.message
        assert fake.mode == "OFFBOARD" and fake.armed
        # OFFBOARD was requested only after setpoints had been streaming.
        mode_cmd = next(c for c in fake.commands if c.command == px4.MAV_CMD_DO_SET_MODE)
        assert mode_cmd is not None and fake.setpoints
        sp = fake.setpoints[-1]
        assert (sp.coordinate_frame, sp.type_mask) == (px4.MAV_FRAME_LOCAL_NED, 2552)
        assert math.isclose(sp.z, -1.5)
        st = bridge.state()
        assert st.offboard_ok and st.mode == "OFFBOARD" and math.isclose(st.position.z, 1.5)

        res = await bridge.handle(GotoCommand(position=Vec3(x=1.0, y=2.0, z=1.2), yaw=0.0))
        assert res.ok, res.message
        await wait_until(lambda: math.dist(bridge.position, (1.0, 2.0, 1.2)) < 1e-5, 10, what="fake follows the goto")
        sp = fake.setpoints[-1]
        assert (sp.x, sp.y, sp.z) == pytest.approx((2.0, 1.0, -1.2))  # north, east, down (float32)
        assert sp.yaw == pytest.approx(math.pi / 2)
        await wait_until(lambda: math.isclose(bridge.state().yaw, 0.0, abs_tol=1e-6), 10, what="yaw ENU")

        res = await bridge.handle(GotoCommand(position=Vec3(x=3.0, y=2.0, z=1.2), yaw=1.0, max_speed=20.0))
        assert not res.ok and "above the limit 1.00 m/s" in res.message  # the envelope's speed limit
        res = await bridge.handle(GotoCommand(position=Vec3(x=3.0, y=2.0, z=1.2), yaw=1.0, max_speed=0.5))
        assert res.ok and "0.50 m/s" in res.message

        res = await bridge.handle(HoldCommand())
        assert res.ok and "OFFBOARD" in res.message

        res = await bridge.handle(GripperCommand(action="close"))
        assert res.ok and res.ack_name == "MAV_RESULT_ACCEPTED" and bridge.state().gripper == "closed"
        grip = [c for c in fake.commands if c.command == px4.MAV_CMD_DO_GRIPPER][-1]
        assert (grip.param1, grip.param2) == (1.0, 1.0)

        res = await bridge.handle(LandCommand())
        assert res.ok and fake.mode == "AUTO.LAND"
        assert not bridge.stream.running
        await asyncio.sleep(0.3)
        assert "offboard lost" not in bridge.state().message


async def test_bad_commands_change_nothing() -> None:
    async with bridge_and_fake() as (bridge, fake):
        res = await bridge.handle(GotoCommand(position=Vec3(x=1.0, y=0.0, z=1.0), yaw=0.0))
        assert not res.ok and "not airborne" in res.message
        res = await bridge.handle(TakeoffCommand(altitude=1.0))
        assert res.ok
        before = list(fake.setpoints)[-1]
        # The message models refuse non-finite numbers at the bus; the bridge still checks, for a caller that
        # builds the command without validation (model_construct) in the same process.
        for bad in (GotoCommand.model_construct(position=Vec3.model_construct(x=float("nan"), y=0.0, z=1.0),
                                                yaw=0.0, max_speed=None),
                    GotoCommand.model_construct(position=Vec3(x=1.0, y=0.0, z=1.0), yaw=float("inf"),
                                                max_speed=None)):
            res = await bridge.handle(bad)
            assert not res.ok and "non-finite" in res.message
        await asyncio.sleep(0.2)
        after = fake.setpoints[-1]
        assert (after.x, after.y, after.z, after.yaw) == (before.x, before.y, before.z, before.yaw)


async def test_bad_mavlink_input_changes_nothing() -> None:
    async with bridge_and_fake() as (bridge, fake):
        peer = bridge.link.peer
        port = int(bridge.s.connection.rsplit(":", 1)[1])
        st0 = bridge.state()
        intruder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        other = mavlink.MAVLink(None, srcSystem=42, srcComponent=1)
        try:
            for _ in range(20):
                intruder.sendto(b"\xfd\x09garbage\x00\xff" * 5, ("127.0.0.1", port))
            # Another system claiming to be armed in OFFBOARD somewhere else.
            intruder.sendto(other.heartbeat_encode(2, px4.MAV_AUTOPILOT_PX4, 129,
                                                   px4.encode_custom_mode("OFFBOARD"), 4).pack(other),
                            ("127.0.0.1", port))
            intruder.sendto(other.local_position_ned_encode(0, 9.0, 9.0, -9.0, 0, 0, 0).pack(other),
                            ("127.0.0.1", port))
            # Our system id but from a stranger's address.
            spoof = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
            intruder.sendto(spoof.local_position_ned_encode(0, 7.0, 7.0, -7.0, 0, 0, 0).pack(spoof),
                            ("127.0.0.1", port))
            # From the real autopilot: an ACK for a command we never sent, and a message we do not use.
            fake.send(fake.mav.command_ack_encode(px4.MAV_CMD_DO_GRIPPER, 0, 0, 0, 1, 191))
            fake.send(fake.mav.vibration_encode(0, 0.1, 0.1, 0.1, 0, 0, 0))
            await wait_until(lambda: bridge.counters["unexpected_acks"] >= 1 and bridge.counters["bad_data"] >= 1
                             and bridge.counters["wrong_system"] >= 2 and bridge.counters["wrong_address"] >= 1,
                             10, what=f"bad input counted: {dict(bridge.counters)}")
        finally:
            intruder.close()
        await asyncio.sleep(0.2)
        st = bridge.state()
        assert bridge.link.peer == peer and bridge.target_system == 1
        assert (st.armed, st.mode, st.position, st.gripper) == (st0.armed, st0.mode, st0.position, st0.gripper)
        assert st.link_ok
        # Our writes still go to the autopilot, not to the intruder.
        res = await bridge.handle(ArmCommand())
        assert res.ok, res.message


async def test_link_loss_and_offboard_loss_are_reported() -> None:
    async with bridge_and_fake() as (bridge, fake):
        assert (await bridge.handle(TakeoffCommand(altitude=1.0))).ok
        fake.mode = "AUTO.LOITER"  # e.g. an RC override or a failsafe
        await wait_until(lambda: "offboard lost" in bridge.state().message, 10, what="offboard loss")
        st = bridge.state()
        assert not st.offboard_ok and "AUTO.LOITER" in st.message
        res = await bridge.handle(HoldCommand())
        assert res.ok and "AUTO.LOITER" in res.message
        fake.heartbeats = False
        await wait_until(lambda: not bridge.state().link_ok, 10, what="link loss")
        st = bridge.state()
        assert "link lost" in st.message and not st.offboard_ok
        res = await bridge.handle(ArmCommand())
        assert not res.ok and "no link" in res.message
        fake.heartbeats = True
        await wait_until(lambda: bridge.state().link_ok, 10, what="link restored")


def _holding_in_failsafe(fake) -> None:
    fake.armed, fake.mode, fake.ned = True, "AUTO.LOITER", [0.5, 0.2, -1.4]  # PX4's offboard-loss Hold


async def test_a_restarted_bridge_finds_px4_holding_and_leaves_it_until_an_operator_command() -> None:
    """The bridge died in flight and PX4's offboard-loss failsafe holds (COM_OBL_RC_ACT=5): the new bridge
    latches that as PX4's takeover (the task that was flying ends on it), sends PX4 no mode and no setpoint
    by itself; a land is obeyed (a new task's goto takes it back too, next test)."""
    async with bridge_and_fake(fake_init=_holding_in_failsafe) as (bridge, fake):
        st = bridge.state()
        assert st.armed and st.mode == "AUTO.LOITER" and st.override_ns > 0
        assert "found PX4 flying in AUTO.LOITER" in st.override, st.override
        res = await bridge.handle(HoldCommand())
        assert res.ok and "AUTO.LOITER" in res.message, res.message
        await asyncio.sleep(0.5)
        assert not any(c.command == px4.MAV_CMD_DO_SET_MODE for c in fake.commands) and not fake.setpoints
        assert fake.mode == "AUTO.LOITER"
        res = await bridge.handle(LandCommand())  # landing is always allowed, latched takeover or not
        assert res.ok, res.message
        assert fake.mode == "AUTO.LAND"


async def test_after_a_restart_a_new_task_flies_the_held_vehicle_again() -> None:
    async with bridge_and_fake(fake_init=_holding_in_failsafe) as (bridge, fake):
        assert bridge.state().override
        res = await bridge.handle(GotoCommand(position=Vec3(x=0.5, y=0.0, z=1.4), yaw=0.0, task_id="task-new"))
        assert res.ok, res.message
        assert fake.mode == "OFFBOARD" and bridge.state().override == ""


async def test_pilot_takeover_is_respected_until_a_new_operator_command() -> None:
    async with bridge_and_fake() as (bridge, fake):
        assert (await bridge.handle(TakeoffCommand(altitude=1.0, task_id="task-a"))).ok
        assert (await bridge.handle(GotoCommand(position=Vec3(x=1, y=0, z=1), yaw=0.0, task_id="task-a"))).ok
        fake.mode = "POSCTL"  # the pilot flips the mode switch
        await wait_until(lambda: bridge.state().override != "", 10, what="takeover latched")
        st = bridge.state()
        assert st.override.startswith("PX4 switched from OFFBOARD to POSCTL") and st.override_ns > 0
        assert not bridge.stream.running  # no setpoints fighting the pilot
        # Hold does not take the pilot's mode away, and the task cannot fly on.
        n_modes = sum(1 for c in fake.commands if c.command == px4.MAV_CMD_DO_SET_MODE)
        res = await bridge.handle(HoldCommand())
        assert res.ok and "not overriding" in res.message
        for cmd in (GotoCommand(position=Vec3(x=0, y=0, z=1), yaw=0.0, task_id="task-a"),
                    TakeoffCommand(altitude=1.0, task_id="task-a"), ArmCommand(task_id="task-a")):
            res = await bridge.handle(cmd)
            assert not res.ok and "a new operator command is needed" in res.message, res
        await asyncio.sleep(0.3)
        assert fake.mode == "POSCTL"  # nothing asked PX4 for another mode, nothing armed
        assert sum(1 for c in fake.commands if c.command == px4.MAV_CMD_DO_SET_MODE) == n_modes
        # A new task is a new operator command: it may take control again.
        res = await bridge.handle(GotoCommand(position=Vec3(x=0, y=0, z=1), yaw=0.0, task_id="task-b"))
        assert res.ok, res.message
        assert bridge.state().override == "" and fake.mode == "OFFBOARD"
        assert sum(1 for c in fake.commands if c.command == px4.MAV_CMD_DO_SET_MODE) == n_modes + 1
        # PX4 leaving OFFBOARD again (an RTL failsafe) latches again.
        fake.mode = "AUTO.RTL"
        await wait_until(lambda: "AUTO.RTL" in bridge.state().override, 10, what="RTL takeover")


async def test_offboard_refusal_carries_ack_and_px4_reason() -> None:
    async with bridge_and_fake() as (bridge, fake):
        fake.deny_offboard = True
        res = await bridge.handle(TakeoffCommand(altitude=1.5))
        assert not res.ok and res.command == "takeoff"
        assert res.ack_code == 2 and res.ack_name == "MAV_RESULT_DENIED"
        assert "OFFBOARD denied" in res.message and "not available" in res.message
        assert not bridge.stream.running and fake.mode == "POSCTL"
        st = bridge.state()
        assert not st.offboard_ok


async def test_abort_without_executor_holds_through_px4_hold_mode() -> None:
    from shared.messages import Abort

    async with bridge_and_fake(abort_hold="px4_hold") as (bridge, fake):
        assert (await bridge.handle(TakeoffCommand(altitude=1.0, task_id="task-a"))).ok
        ack = await bridge.on_abort(Abort(reason="stop", source="test", task_id="task-a"))
        assert ack.service == "autopilot_bridge" and ack.message == "holding in AUTO.LOITER (PX4 Hold)", ack
        await wait_until(lambda: bridge.state().mode == "AUTO.LOITER", 5, what="PX4 in Hold")
        assert not bridge.stream.running
        st = bridge.state()
        assert st.override == "aborted by test: stop" and not st.offboard_ok
        # The aborted task stays grounded in Hold; a new task takes control again, and that switch (asked
        # for by the bridge itself) is not mistaken for a takeover.
        res = await bridge.handle(GotoCommand(position=Vec3(x=0, y=0, z=1), yaw=0.0, task_id="task-a"))
        assert not res.ok and "a new operator command is needed" in res.message
        assert res.aborted  # the executor ends the skill ABORTED even if it has not seen the abort itself
        res = await bridge.handle(GotoCommand(position=Vec3(x=0, y=0, z=1), yaw=0.0, task_id="task-b"))
        assert res.ok, res.message
        await asyncio.sleep(0.5)
        assert bridge.state().override == "" and bridge.state().mode == "OFFBOARD"


async def test_an_abort_right_after_the_bridges_own_land_command_says_it_is_landing() -> None:
    """PX4 sends its HEARTBEAT at 1 Hz: just after a land command was accepted the bridge may still read OFFBOARD.
    An abort then must not answer "PX4 has control in OFFBOARD: left to it" (ci26: the executor's land on the abort
    reached the bridge before the abort did): the vehicle lands on the bridge's own command."""
    from shared.messages import Abort

    async with bridge_and_fake() as (bridge, fake):
        assert (await bridge.handle(TakeoffCommand(altitude=1.0, task_id="task-a"))).ok
        fake.heartbeats = False  # the next HEARTBEAT, showing AUTO.LAND, is still to come
        assert (await bridge.handle(LandCommand())).ok
        assert bridge.mode == "OFFBOARD" and fake.mode == "AUTO.LAND"
        ack = await bridge.on_abort(Abort(reason="stop", source="test", task_id="task-a"))
        assert ack.message.startswith("landing"), ack.message
        assert fake.mode == "AUTO.LAND"  # not switched to Hold: an abort does not stop a landing
        fake.heartbeats = True


async def test_a_takeoff_stopped_by_an_abort_answers_aborted() -> None:
    """The executor may get the abort after the bridge: the takeoff the bridge stopped says why (`aborted`)."""
    from shared.messages import Abort

    async with bridge_and_fake() as (bridge, fake):
        # The fake would reach the altitude at its next setpoint, a climb too short to be caught on a loaded
        # machine (2 runs in 12 missed it): here the climb lasts until the abort.
        fake.follow_setpoints = False
        takeoff = asyncio.create_task(bridge.handle(TakeoffCommand(altitude=1.5, task_id="task-a")))
        await wait_until(lambda: bridge.climbing, 10, what="the climb")
        await bridge.on_abort(Abort(reason="stop", source="test", task_id="task-a"))
        res = await asyncio.wait_for(takeoff, 10)
        assert not res.ok and res.aborted and "aborted by test: stop" in res.message, res


async def test_a_landing_whose_first_heartbeat_is_disarmed_leaves_no_mode_request_behind() -> None:
    """PX4 can touch down and auto-disarm before the bridge's next HEARTBEAT (1 Hz) shows AUTO.LAND armed: the
    land's request is confirmed by a disarmed heartbeat. The next task arms in the mode PX4 now shows (Hold after
    a landing, or a simulator's reset); that must not read as PX4 switching away from the bridge's AUTO.LAND.
    The fake's telemetry pauses stay well inside the link timeout however slow the machine."""
    async with bridge_and_fake(heartbeat_timeout_s=10.0) as (bridge, fake):
        assert (await bridge.handle(TakeoffCommand(altitude=1.0, task_id="task-a"))).ok
        fake.heartbeats = False  # the landing and the disarm fall between two heartbeats
        assert (await bridge.handle(LandCommand())).ok and fake.mode == "AUTO.LAND"
        fake.armed, fake.ned = False, [0.0, 0.0, 0.0]
        fake.heartbeats = True
        await wait_until(lambda: not bridge.armed and bridge.mode == "AUTO.LAND", 10, what="disarmed in AUTO.LAND")
        fake.heartbeats = False  # PX4 is in Hold again and the next takeoff arms before a heartbeat shows it
        fake.mode = "AUTO.LOITER"
        takeoff = asyncio.create_task(bridge.handle(TakeoffCommand(altitude=1.0, task_id="task-b")))
        await wait_until(lambda: fake.armed, 10, what="armed by the takeoff")
        fake.heartbeats = True  # the first heartbeat: armed, AUTO.LOITER, before OFFBOARD is asked for
        res = await takeoff
        assert res.ok, res.message
        assert bridge.state().override == "" and fake.mode == "OFFBOARD"


async def test_a_takeoff_after_a_crash_stopped_the_motors_in_offboard_arms_again() -> None:
    """A crash stops the motors while PX4 stays in OFFBOARD and the bridge's stream still runs: the next task's
    takeoff must arm (not wait on a disarmed vehicle that cannot climb and report it disarmed)."""
    async with bridge_and_fake() as (bridge, fake):
        assert (await bridge.handle(TakeoffCommand(altitude=1.0, task_id="task-a"))).ok
        fake.armed, fake.ned = False, [0.0, 0.0, 0.0]  # motors stopped, on the floor, mode still OFFBOARD
        await wait_until(lambda: not bridge.armed, 10, what="the bridge sees the disarm")
        assert fake.mode == "OFFBOARD" and bridge.stream.running

        def arms() -> int:
            return sum(1 for c in fake.commands if c.command == px4.MAV_CMD_COMPONENT_ARM_DISARM and c.param1 == 1)

        n_arms = arms()
        res = await bridge.handle(TakeoffCommand(altitude=1.0, task_id="task-b"))
        assert res.ok, res.message
        assert fake.armed and arms() == n_arms + 1
        assert bridge.state().offboard_ok and math.isclose(bridge.state().position.z, 1.0)
