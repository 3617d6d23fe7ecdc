"""The bridge proper: PX4 telemetry -> VehicleState, AutopilotCommand -> MAVLink commands and offboard setpoints."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import sys
import time
from collections import defaultdict
from collections.abc import Awaitable, Callable
from typing import Any, Literal

from services.autopilot_bridge import px4
from services.autopilot_bridge.link import MavlinkLink
from services.autopilot_bridge.preflight import PARAM_NAMES, ParamReader, VehicleFacts, check_params, check_state
from services.autopilot_bridge.preflight import summary as preflight_summary
from services.autopilot_bridge.settings import BridgeSettings
from services.autopilot_bridge.stream import SetpointStream, Target
from shared.bus import Bus, Caller
from shared.envelope import altitude_problem, geofence_problem, speed_problem
from shared.errors import BusError
from shared.keys import FLEET_ABORT, BoundTopic
from shared.messages import (
    ABORT_OVERRIDE,
    Abort,
    AbortAck,
    ArmCommand,
    AutopilotResult,
    DisarmCommand,
    GotoCommand,
    GripperCommand,
    GripperState,
    Health,
    HoldCommand,
    LandCommand,
    LandedState,
    PreflightCheck,
    PreflightCommand,
    PreflightReport,
    TakeoffCommand,
    Vec3,
    VehicleState,
    now_ns,
)
from shared.sensors import BODY_FRAME, WORLD_FRAME, pose_matrix, transforms_message
from shared.service import announce

log = logging.getLogger("aermani.autopilot_bridge")

SERVICE = "autopilot_bridge"
AUTO_TF_GRACE_S = 2.5
"""publish_tf `auto`: how long after start the bridge waits for the simulator's health before publishing tf."""
AUTO_TF_SIM_FRESH_S = 3.0
"""publish_tf `auto`: a simulator health that says it publishes tf counts for this long."""
UINT16_MAX = 65535
REFUSED_LOGGED = 32
"""Refused autopilots (system, component, address) remembered and logged; more are only counted."""


class RateLimitedLog:
    """Log a recurring problem at most once per `period` seconds, with the count of suppressed repeats."""

    def __init__(self, period: float = 5.0) -> None:
        self.period = period
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = defaultdict(int)

    def __call__(self, key: str, text: str, *args: Any) -> None:
        now = time.monotonic()
        if now - self._last.get(key, -1e9) >= self.period:
            extra = self._suppressed.pop(key, 0)
            log.warning(text + (f" ({extra} more since the last report)" if extra else ""), *args)
            self._last[key] = now
        else:
            self._suppressed[key] += 1


class Bridge:
    """All state lives on the event loop; the reader thread only hands messages over and the stream thread
    only reads `stream.target`."""

    def __init__(self, bus: Bus | None, settings: BridgeSettings, link: MavlinkLink) -> None:
        self.bus = bus
        self.s = settings
        self.link = link
        self.keys = settings.keys
        self.loop: asyncio.AbstractEventLoop | None = None
        self.t0 = time.monotonic()
        self.sim_tf_mono: float | None = None
        """When the vehicle's simulator last said it publishes tf (publish_tf `auto`)."""
        self.stream = SetpointStream(self._send_setpoint, settings.stream_rate_hz,
                                     realtime_priority=settings.stream_realtime_priority)
        # autopilot identity: the configured system/component, set once its first PX4 HEARTBEAT is heard
        self.target_system: int | None = None
        self.target_component = settings.target_component
        self.refused_autopilots: set[tuple[int, int, str]] = set()
        """Other autopilots heard on the link (system, component, address), each logged once."""
        # telemetry
        self.last_hb_mono = 0.0
        self.last_hb_ns = 0
        self.armed = False
        self.mode = "UNKNOWN"
        self.landed_state = LandedState.UNKNOWN
        self.have_position = False
        self.position = (0.0, 0.0, 0.0)
        self.velocity = (0.0, 0.0, 0.0)
        self.yaw = 0.0
        self.roll = 0.0
        self.pitch = 0.0
        self.battery_voltage: float | None = None
        self.battery_remaining: float | None = None
        self.gripper = GripperState.UNKNOWN
        self.gripper_width: float | None = None
        self.gripper_holding: bool | None = None
        self.message = ""
        self.last_statustext = ""
        self.last_statustext_mono = 0.0
        # control
        self.offboard_expected = False  # we put PX4 in OFFBOARD and have not asked it to leave
        # PX4's authority: the mode we last asked for; a switch to anything else while armed means PX4 (a
        # failsafe) or the pilot took over, and latches `override` until a new operator command.
        self.mode_requested: str | None = None
        self.climbing = False
        """A take-off is climbing to its altitude (an abort then lands instead of holding)."""
        self.mode_pending: str | None = None  # asked for, not yet seen in a HEARTBEAT
        self.override = ""
        self.override_ns = 0
        self.override_task: str | None = None  # the task that was flying when control was taken
        self.seen_mode = False  # a HEARTBEAT with PX4's mode arrived (the first one may find it flying without us)
        self.last_task: str | None = None  # task id of the newest motion command
        self.aborted_tasks: set[str] = set()  # tasks named by an abort (or flying at one): never command again
        self.link_was_ok = False
        self.epoch = 0  # bumped by every motion command so a running takeoff knows it was superseded
        self._pending: dict[int, asyncio.Future[int]] = {}
        self._cmd_locks: dict[int, asyncio.Lock] = defaultdict(asyncio.Lock)
        self._flight_lock = asyncio.Lock()
        self._changed = asyncio.Event()
        self.counters: dict[str, int] = defaultdict(int)
        self.warn = RateLimitedLog()
        self._tasks: set[asyncio.Task] = set()
        self.params = ParamReader(link.send, link.mav)

    # ------------------------------------------------------------------ helpers

    @property
    def link_ok(self) -> bool:
        return self.last_hb_mono > 0 and time.monotonic() - self.last_hb_mono <= self.s.heartbeat_timeout_s

    @property
    def offboard_ok(self) -> bool:
        fresh = time.monotonic() - self.stream.last_sent_at <= 3 * self.stream.period
        return self.link_ok and self.mode == "OFFBOARD" and self.stream.running and fresh

    @property
    def airborne(self) -> bool:
        return self.armed and self.landed_state in (LandedState.IN_AIR, LandedState.TAKEOFF, LandedState.LANDING)

    def time_boot_ms(self) -> int:
        return int((time.monotonic() - self.t0) * 1000)

    def _notify(self) -> None:
        ev, self._changed = self._changed, asyncio.Event()
        ev.set()

    async def wait_for(self, pred: Callable[[], bool], timeout: float) -> bool:
        """Wait until `pred()` holds, re-checking whenever a message arrives (and at least every 0.2 s)."""
        deadline = time.monotonic() + timeout
        while not pred():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            ev = self._changed
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(ev.wait(), min(remaining, 0.2))
        return True

    def _send_setpoint(self, sp: px4.SetpointNED) -> bool:  # runs on the stream thread
        if self.target_system is None:
            return False
        return self.link.send(self.link.mav.set_position_target_local_ned_encode(
            *sp.fields(self.time_boot_ms(), self.target_system, self.target_component)))

    def current_target(self) -> Target:
        x, y, z = self.position
        return Target(x, y, z, self.yaw)

    def _status_hint(self) -> str:
        if self.last_statustext and time.monotonic() - self.last_statustext_mono < 3.0:
            return f"; PX4 says: {self.last_statustext}"
        return ""

    # ------------------------------------------------------------------ MAVLink input (on the loop)

    def on_message(self, msg: Any, addr: tuple[str, int] | None, _t: float) -> None:
        mtype = msg.get_type()
        self.counters["mavlink_received"] += 1
        if mtype == "BAD_DATA" and "signature" in str(getattr(msg, "reason", "")):
            self.counters["bad_signature"] += 1
            self.warn("signature", "ignored an unsigned or wrongly signed MAVLink frame from %s (signing is on)",
                      addr or self.s.connection)
            return
        if mtype == "BAD_DATA":
            self.counters["bad_data"] += 1
            self.warn("bad", "ignored undecodable MAVLink bytes from %s", addr)
            return
        src, comp = msg.get_srcSystem(), msg.get_srcComponent()
        if (src, comp) != (self.s.target_system, self.s.target_component):
            # Another vehicle, a camera or gimbal of ours, or something pretending to be an autopilot: never the
            # vehicle's state, and never the one we lock onto.
            self.counters["wrong_system" if src != self.s.target_system else "other_component"] += 1
            if mtype == "HEARTBEAT" and self._is_px4(msg):
                self._refuse_autopilot(src, comp, addr, f"not the configured autopilot {self.s.target_system}/"
                                                        f"{self.s.target_component}")
            elif src != self.s.target_system:
                self.warn("sysid", "ignored %s from system %d (we talk to system %d)", mtype, src,
                          self.s.target_system)
            return
        if self.target_system is None:
            if mtype == "HEARTBEAT" and self._is_px4(msg):
                self._learn(msg, addr)
            else:
                self.counters["ignored_before_heartbeat"] += 1
                return
        peer = self.link.peer
        if addr is not None and peer is not None and tuple(addr) != peer:
            if mtype == "HEARTBEAT" and not self.link_ok and self._is_px4(msg):
                log.warning("autopilot system %d came back from %s (was %s)", src, addr, peer)
                self.link.lock_peer(addr)
            else:
                self.counters["wrong_address"] += 1
                if mtype == "HEARTBEAT" and self._is_px4(msg):
                    self._refuse_autopilot(src, comp, addr, f"the autopilot holds the link from {peer[0]}:{peer[1]}")
                else:
                    self.warn("addr", "ignored %s from %s: the autopilot is at %s", mtype, addr, peer)
                return
        handler = getattr(self, f"_on_{mtype.lower()}", None)
        if handler is None:
            self.counters["unhandled"] += 1
            return
        handler(msg)
        self._notify()

    @staticmethod
    def _is_px4(msg: Any) -> bool:
        return msg.autopilot == px4.MAV_AUTOPILOT_PX4 and msg.type not in (px4.MAV_TYPE_GCS,
                                                                           px4.MAV_TYPE_ONBOARD_CONTROLLER)

    def _refuse_autopilot(self, system: int, component: int, addr: tuple[str, int] | None, why: str) -> None:
        """A HEARTBEAT that claims to be an autopilot but is not ours: counted, and logged once per system,
        component and address (a flood of spoofed addresses is counted, not logged, past REFUSED_LOGGED)."""
        self.counters["refused_autopilot"] += 1
        where = f"{addr[0]}:{addr[1]}" if addr is not None else self.s.connection
        key = (system, component, where)
        if key in self.refused_autopilots or len(self.refused_autopilots) >= REFUSED_LOGGED:
            return
        self.refused_autopilots.add(key)
        log.warning("refused a second autopilot: system %d component %d at %s (%s); its messages are ignored",
                    system, component, where, why)

    def _learn(self, msg: Any, addr: tuple[str, int] | None) -> None:
        self.target_system = msg.get_srcSystem()
        self.target_component = msg.get_srcComponent()
        if addr is not None:
            self.link.lock_peer(addr)
        log.info("talking to PX4 system %d component %d at %s", self.target_system, self.target_component,
                 addr or self.s.connection)

    def _on_heartbeat(self, msg: Any) -> None:
        if not self.link_ok:
            was_lost = self.link_was_ok
            self.last_hb_mono = time.monotonic()
            self.message = "link restored" if was_lost else "link up"
            log.info("autopilot heartbeat %s", "restored" if was_lost else "received")
            self.link_was_ok = True
            self._spawn(self.request_rates())
        self.last_hb_mono = time.monotonic()
        self.last_hb_ns = now_ns()
        self.armed = bool(msg.base_mode & px4.MAV_MODE_FLAG_SAFETY_ARMED)
        if msg.base_mode & px4.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            mode = px4.decode_custom_mode(msg.custom_mode)
        else:
            mode = "UNKNOWN"
        if mode != self.mode:
            log.info("mode %s -> %s", self.mode, mode)
        previous, self.mode = self.mode, mode
        first, self.seen_mode = not self.seen_mode and mode != "UNKNOWN", self.seen_mode or mode != "UNKNOWN"
        if first and self.armed and self.mode_requested is None and self.mode_pending is None:
            # Armed before this bridge ever commanded it (this bridge restarted in flight): PX4 flies its own
            # choice, e.g. the offboard-loss Hold. Latch it, as if it had been seen taking over, so the task that
            # was flying ends and nothing re-enters OFFBOARD until a new operator command (a new task, or a
            # direct command) takes the vehicle back, e.g. to land clear of the furniture.
            self.take_over(f"found PX4 flying in {mode} at the bridge's start (its failsafe or the pilot has "
                           f"control){self._status_hint()}")
        if self.offboard_expected and mode != "OFFBOARD":
            self.offboard_expected = False
            self.mode_requested = None
            self.stream.stop()  # PX4 ignores our setpoints outside OFFBOARD; stopping them keeps it that way
            self.message = f"offboard lost: PX4 switched to {mode}{self._status_hint()}"
            log.warning("%s", self.message)
            self.take_over(f"PX4 switched from OFFBOARD to {mode}{self._status_hint()}")
        elif mode == self.mode_pending:
            self.mode_requested, self.mode_pending = mode, None  # the switch we asked for
        elif self.armed and mode != previous and previous == self.mode_requested and mode != self.mode_requested:
            self.mode_requested = None
            self.take_over(f"PX4 switched from {previous} to {mode}{self._status_hint()}")
        if not self.armed:
            # A mode request never outlives a disarm, also when the heartbeat that confirms it (a short AUTO.LAND)
            # already shows the vehicle disarmed: kept, the next arming's mode would read as PX4 taking over.
            self.mode_requested = None

    def _finite(self, msg: Any, *values: float) -> bool:
        if px4.all_finite(*values):
            return True
        self.counters["nonfinite_telemetry"] += 1
        self.warn("nan", "ignored %s with non-finite values", msg.get_type())
        return False

    def _on_local_position_ned(self, msg: Any) -> None:
        if not self._finite(msg, msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz):
            return
        self.position = px4.ned_to_enu(msg.x, msg.y, msg.z)
        self.velocity = px4.ned_to_enu(msg.vx, msg.vy, msg.vz)
        self.have_position = True

    def _on_attitude(self, msg: Any) -> None:
        if not self._finite(msg, msg.roll, msg.pitch, msg.yaw):
            return
        # PX4 FRD roll and pitch keep their sign in our convention (roll right-wing-down, pitch nose-up).
        self.roll, self.pitch, self.yaw = msg.roll, msg.pitch, px4.yaw_ned_to_enu(msg.yaw)

    def _on_extended_sys_state(self, msg: Any) -> None:
        self.landed_state = LandedState(px4.LANDED_STATE_NAMES.get(msg.landed_state, "unknown"))

    def _on_sys_status(self, msg: Any) -> None:
        self.battery_voltage = None if msg.voltage_battery in (0, UINT16_MAX) else msg.voltage_battery / 1000.0
        self.battery_remaining = None if msg.battery_remaining < 0 else float(msg.battery_remaining)

    def _on_debug_vect(self, msg: Any) -> None:
        """The gripper's sensing (the simulator's payload, or a real gripper reporting the same way): DEBUG_VECT
        named GRIPPER, x = finger opening (m), y = holding (1/0), z = closing commanded (1/0). The gripper's
        own word sets its state, so a restarted bridge knows at once that it holds (it said "unknown" until
        its first gripper command, and a restarted executor then opened the fingers on a held cup)."""
        name = msg.name.rstrip("\x00") if isinstance(msg.name, str) else bytes(msg.name).rstrip(b"\x00").decode()
        if name != "GRIPPER" or not self._finite(msg, msg.x, msg.y, msg.z):
            return
        self.gripper_width = float(msg.x)
        self.gripper_holding = msg.y > 0.5
        self.gripper = GripperState.CLOSED if msg.z > 0.5 else GripperState.OPEN

    def _on_statustext(self, msg: Any) -> None:
        text = msg.text.rstrip("\x00") if isinstance(msg.text, str) else str(msg.text)
        self.last_statustext = text
        self.last_statustext_mono = time.monotonic()
        self.message = text
        log.info("PX4: %s", text)

    def _on_param_value(self, msg: Any) -> None:
        self.params.on_param_value(msg)

    def _on_command_ack(self, msg: Any) -> None:
        if getattr(msg, "target_system", 0) not in (0, self.s.source_system) or \
                getattr(msg, "target_component", 0) not in (0, self.s.source_component):
            return  # an answer to a ground station or another component on the same link
        fut = self._pending.get(msg.command)
        if fut is None or fut.done():
            self.counters["unexpected_acks"] += 1
            self.warn("ack", "ignored COMMAND_ACK for command %d (result %d) that we are not waiting for",
                      msg.command, msg.result)
            return
        if msg.result == px4.MAV_RESULT_IN_PROGRESS:
            return  # the final ACK follows
        fut.set_result(int(msg.result))

    # ------------------------------------------------------------------ PX4's authority

    def take_over(self, why: str, task_id: str | None = None) -> None:
        """PX4, the pilot or an abort took control: latch it. Nothing re-enters OFFBOARD, arms or takes off
        for the task that was flying; a command of another task, or an operator's own (no task), clears it."""
        if self.override:
            return
        self.override = why
        self.override_ns = now_ns()
        self.override_task = task_id or self.last_task
        if not self.message.startswith("offboard lost"):
            self.message = why
        log.warning("control taken from the stack: %s (task %s); waiting for a new operator command", why,
                    self.override_task or "-")

    def authority_refusal(self, command: str, task_id: str | None) -> AutopilotResult | None:
        """None when `command` may take control; else the refusal. A new task or an operator's direct command
        (task_id None) is the new operator command that ends a takeover."""
        if task_id is not None and task_id in self.aborted_tasks:
            return self._result(command, False, f"{command} refused: task {task_id} was aborted; a new operator "
                                "command is needed", aborted=True)
        if self.override and task_id is not None and task_id == self.override_task:
            return self._result(command, False, f"{command} refused: the autopilot has control ({self.override}); "
                                "the stack does not take it back within this task, a new operator command is needed",
                                aborted=self.override.startswith(ABORT_OVERRIDE))
        if self.override:
            log.info("new operator command (%s, task %s): the stack may fly again after: %s", command,
                     task_id or "operator", self.override)
            self.override, self.override_ns, self.override_task = "", 0, None
        if task_id is not None:
            self.last_task = task_id
        return None

    async def on_abort(self, abort: Abort) -> AbortAck:
        """Obey an abort without the executor: hold (`abort_hold`: our own setpoint frozen in OFFBOARD, or PX4's
        AUTO.LOITER), latch a takeover, and refuse every later command of the aborted task."""
        for task in (abort.task_id, None if abort.task_id else self.last_task):
            if task:
                self.aborted_tasks.add(task)
        if abort.task_id and self.last_task and abort.task_id != self.last_task:
            ack = AbortAck(abort_stamp_ns=abort.stamp_ns, service=SERVICE,
                           message=f"not flying for task {abort.task_id} (its commands are refused from now on); "
                                   "nothing else done")
        else:
            mid_takeoff = self.armed and (self.climbing or self.landed_state is LandedState.TAKEOFF)
            self.epoch += 1  # ends a takeoff that is waiting for its altitude
            self.take_over(f"{ABORT_OVERRIDE}{abort.source}: {abort.reason}", abort.task_id)
            # Mid-takeoff a hold would leave the vehicle armed a few centimetres up, in ground effect, below
            # every skill's minimum altitude: it lands (the executor does the same).
            what = await (self.land_on_abort() if mid_takeoff else self.hold_through_px4())
            ack = AbortAck(abort_stamp_ns=abort.stamp_ns, service=SERVICE, message=what)
        log.warning("abort from %s (%s): %s", abort.source, abort.reason, ack.message)
        if self.bus is not None:
            self.bus.publish(self.keys.abort_ack, ack)
        return ack

    async def land_on_abort(self) -> str:
        if not self.link_ok:
            return "no link to PX4: cannot command a landing"
        res = await self.land(LandCommand())
        return "landing (aborted mid-takeoff)" if res.ok else f"{res.message}; {await self.hold_through_px4()}"

    async def hold_through_px4(self) -> str:
        if not self.link_ok:
            return "no link to PX4: cannot command a hold"
        if not self.armed:
            self.stream.stop()
            return "disarmed: nothing to hold"
        if self.mode == "AUTO.LAND" or self.mode_requested == "AUTO.LAND":
            # Also when PX4 accepted our own land command and its next HEARTBEAT (1 Hz) still has to say so.
            return "landing (AUTO.LAND): an abort does not stop a landing"
        in_our_hands = self.offboard_expected or (self.mode_requested is not None and self.mode == self.mode_requested)
        if not in_our_hands:
            return f"PX4 has control in {self.mode}: left to it"
        if self.stream.running:
            t = self.current_target()
            self.stream.set_target(t)  # hold here at once, whatever PX4 answers next
            if self.s.abort_hold == "offboard" and self.mode == "OFFBOARD":
                return f"holding at ({t.x:.2f}, {t.y:.2f}, {t.z:.2f}) in OFFBOARD (the bridge's own setpoints)"
        if self.mode == "AUTO.LOITER":
            return "holding in AUTO.LOITER (PX4 Hold)"
        self.offboard_expected = False
        code = await self.set_mode("AUTO.LOITER")
        if code == px4.MAV_RESULT_ACCEPTED:
            self.mode_requested = "AUTO.LOITER"
            self.stream.stop()
            return "holding in AUTO.LOITER (PX4 Hold)"
        self.offboard_expected = self.stream.running and self.mode == "OFFBOARD"
        what = "no answer" if code is None else px4.result_name(code)
        return f"AUTO.LOITER refused ({what}{self._status_hint()}); holding the position in OFFBOARD"

    # ------------------------------------------------------------------ MAVLink output

    def send_heartbeat(self) -> None:
        self.link.send(self.link.mav.heartbeat_encode(px4.MAV_TYPE_ONBOARD_CONTROLLER, px4.MAV_AUTOPILOT_INVALID,
                                                      0, 0, px4.MAV_STATE_ACTIVE))

    async def command_long(self, command: int, *params: float) -> int | None:
        """Send a COMMAND_LONG and wait for its final COMMAND_ACK result; None if PX4 never answered.

        Resends with an incremented `confirmation` on timeout, as the MAVLink command protocol asks."""
        if self.target_system is None:
            return None
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        async with self._cmd_locks[command]:
            fut: asyncio.Future[int] = asyncio.get_running_loop().create_future()
            self._pending[command] = fut
            try:
                for confirmation in range(self.s.command_attempts):
                    self.link.send(self.link.mav.command_long_encode(self.target_system, self.target_component,
                                                                     command, confirmation, *p))
                    with contextlib.suppress(TimeoutError):
                        return await asyncio.wait_for(asyncio.shield(fut), self.s.command_timeout_s)
                return None
            finally:
                self._pending.pop(command, None)

    async def request_rates(self) -> None:
        """Ask PX4 for the telemetry we publish, at the rates we need (applies to this link only)."""
        fast = 1e6 / self.s.telemetry_rate_hz
        for msg_id, interval_us in ((px4.MSG_LOCAL_POSITION_NED, fast), (px4.MSG_ATTITUDE, fast),
                                    (px4.MSG_EXTENDED_SYS_STATE, 200_000), (px4.MSG_SYS_STATUS, 500_000)):
            code = await self.command_long(px4.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us)
            if code != px4.MAV_RESULT_ACCEPTED:
                log.warning("SET_MESSAGE_INTERVAL for message %d: %s", msg_id,
                            "no answer" if code is None else px4.result_name(code))

    def _spawn(self, coro: Any) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # ------------------------------------------------------------------ commands

    def _result(self, command: str, ok: bool, message: str, code: int | None = None, *,
                aborted: bool = False) -> AutopilotResult:
        (log.info if ok else log.warning)("%s -> %s: %s", command, "ok" if ok else "failed", message)
        return AutopilotResult(ok=ok, command=command, ack_code=code, ack_name=px4.result_name(code),
                               message=message, aborted=aborted)

    def _stopped(self, command: str, code: int | None = None) -> AutopilotResult:
        """`command` stopped by the latched takeover (or superseded); `aborted` when an abort latched it."""
        return self._result(command, False, f"{command} stopped: {self.override or 'superseded'}", code,
                            aborted=self.override.startswith(ABORT_OVERRIDE))

    def _ack_result(self, command: str, code: int | None, what: str, done: str) -> AutopilotResult:
        if code is None:
            return self._result(command, False, f"{what}: no COMMAND_ACK from PX4 after "
                                f"{self.s.command_attempts} tries")
        if code == px4.MAV_RESULT_ACCEPTED:
            return self._result(command, True, done, code)
        return self._result(command, False, f"{what} {px4.result_words(code)} by PX4 ({px4.result_name(code)})"
                            f"{self._status_hint()}", code)

    def envelope_problem(self, cmd: Any) -> str | None:
        """Why `cmd` would leave the flight envelope (geofence, altitude band, speed) or drop the vehicle, or
        None. Checked here too, not only in the executor, so a command that bypasses it cannot leave it."""
        if isinstance(cmd, GotoCommand):
            p = cmd.position
            if not px4.all_finite(p.x, p.y, p.z, cmd.yaw):
                return None  # goto() answers non-finite input with its own message
            return (geofence_problem(p, self.s, "goto target") or altitude_problem(p.z, self.s, what="goto target")
                    or speed_problem(cmd.max_speed, self.s, "goto"))
        if isinstance(cmd, TakeoffCommand):
            x, y, _z = self.position
            target = Vec3(x=x, y=y, z=cmd.altitude)
            return (altitude_problem(cmd.altitude, self.s, what="takeoff")
                    or geofence_problem(target, self.s, "takeoff target"))
        if isinstance(cmd, DisarmCommand) and not cmd.kill and (self.airborne or (
                self.armed and self.offboard_expected and self.position[2] > 0.15)):
            return (f"disarm refused: the vehicle is in the air (landed_state={self.landed_state.value}, "
                    f"z={self.position[2]:.2f} m) and would fall; land first, or send kill=true to stop the "
                    "motors in an emergency")
        return None

    async def handle(self, cmd: Any, caller: Caller | str = "local") -> AutopilotResult:
        """Serve one AutopilotCommand; never raises for a bad command, answers ok=False instead. Every
        command is logged with `caller` (who sent it) and its outcome."""
        kind = getattr(cmd, "kind", type(cmd).__name__)
        self.counters["commands"] += 1
        what = cmd.model_dump_json(exclude={"schema_version"}) if hasattr(cmd, "model_dump_json") else repr(cmd)
        problem = self.envelope_problem(cmd)
        if problem is not None:
            self.counters["refused_envelope"] += 1
            log.warning("REFUSED %s from %s: %s", what, caller, problem)
            return self._result(str(kind), False, problem)
        if isinstance(cmd, DisarmCommand) and cmd.kill:
            log.critical("KILL: disarm with kill=true from %s (armed=%s, landed_state=%s, z=%.2f m)", caller,
                         self.armed, self.landed_state.value, self.position[2])
        else:
            log.info("command %s from %s", what, caller)
        res = await self._dispatch(cmd, kind)
        log.info("command %s from %s -> %s: %s", kind, caller, "ok" if res.ok else "failed", res.message)
        return res

    async def _dispatch(self, cmd: Any, kind: str) -> AutopilotResult:
        if not self.link_ok:
            age = time.monotonic() - self.last_hb_mono if self.last_hb_mono else None
            why = "no HEARTBEAT received yet" if age is None else f"no HEARTBEAT for {age:.1f} s"
            return self._result(kind, False, f"no link to PX4 ({why}) on {self.s.connection}")
        handlers: dict[type, Callable[[Any], Awaitable[AutopilotResult]]] = {
            ArmCommand: self.arm, DisarmCommand: self.disarm, TakeoffCommand: self.takeoff, GotoCommand: self.goto,
            HoldCommand: self.hold, LandCommand: self.land, GripperCommand: self.gripper_cmd,
            PreflightCommand: self.preflight}
        handler = handlers.get(type(cmd))
        if handler is None:
            return self._result(str(kind), False, f"unknown autopilot command {kind!r}")
        return await handler(cmd)

    async def run_preflight(self, trigger: Literal["request", "arm", "takeoff"]) -> list[PreflightCheck]:
        """Every preflight check (services.autopilot_bridge.preflight): PX4's failsafe parameters, read now,
        and the vehicle's state. The verdict is published on autopilot/preflight (the flight's log keeps it)."""
        target = (self.target_system or self.s.target_system, self.target_component)
        params = await self.params.read(target, PARAM_NAMES, self.s.command_timeout_s, self.s.command_attempts)
        facts = VehicleFacts(self.link_ok, self.have_position, self.armed, self.landed_state,
                             self.battery_remaining, self.override)
        checks = [*check_params(params), *check_state(facts, self.s.preflight_min_battery)]
        ok = all(c.ok for c in checks)
        overridden = not ok and trigger != "request" and self.s.preflight_override
        self._publish_report(PreflightReport(
            vehicle_id=self.s.vehicle_id, trigger=trigger, ok=ok, checks=tuple(checks), overridden=overridden,
            override_reason=(self.s.preflight_override_reason or "no reason given") if overridden else ""))
        return checks

    def _publish_report(self, report: PreflightReport) -> None:
        if self.bus is not None:
            with contextlib.suppress(BusError):  # the record is best effort: a closing bus never stops the gate
                self.bus.publish(self.keys.autopilot_preflight, report)

    async def preflight(self, _cmd: PreflightCommand) -> AutopilotResult:
        checks = await self.run_preflight("request")
        ok = all(c.ok for c in checks)
        return self._result("preflight", ok, preflight_summary(checks)).model_copy(update={"checks": tuple(checks)})

    async def preflight_refusal(self, command: Literal["arm", "takeoff"]) -> AutopilotResult | None:
        """None when the vehicle may arm: the preflight passed, or it failed and the operator overrode it (the
        override and its reason are in the published verdict)."""
        checks = await self.run_preflight(command)
        if all(c.ok for c in checks):
            return None
        text = preflight_summary(checks)
        if self.s.preflight_override:
            log.warning("arming with a failed preflight (%s; AERMANI_AUTOPILOT_BRIDGE_PREFLIGHT_OVERRIDE=1, reason: "
                        "%s): %s", command, self.s.preflight_override_reason or "no reason given", text)
            return None
        res = self._result(command, False, f"{text}. Fix the autopilot's configuration, or set "
                           "AERMANI_AUTOPILOT_BRIDGE_PREFLIGHT_OVERRIDE=1 (with "
                           "AERMANI_AUTOPILOT_BRIDGE_PREFLIGHT_OVERRIDE_REASON) to fly anyway")
        return res.model_copy(update={"checks": tuple(checks)})

    async def arm(self, cmd: ArmCommand) -> AutopilotResult:
        refused = self.authority_refusal("arm", cmd.task_id)
        if refused is not None:
            return refused
        if not self.armed and (refused := await self.preflight_refusal("arm")) is not None:
            return refused
        code = await self.command_long(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        if code == px4.MAV_RESULT_ACCEPTED:
            self.armed = True  # PX4 acks after arming; its next HEARTBEAT (1 Hz) confirms
        return self._ack_result("arm", code, "arm", "armed")

    async def disarm(self, cmd: DisarmCommand) -> AutopilotResult:
        self.epoch += 1
        code = await self.command_long(px4.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                       px4.FORCE_ARM_MAGIC if cmd.force or cmd.kill else 0)
        if code == px4.MAV_RESULT_ACCEPTED:
            self.armed = False
            self.offboard_expected = False
            self.stream.stop()
        return self._ack_result("disarm", code, "disarm", "disarmed")

    async def set_mode(self, name: str) -> int | None:
        self.mode_pending = name
        code = await self.command_long(px4.MAV_CMD_DO_SET_MODE, *px4.set_mode_params(name))
        if code != px4.MAV_RESULT_ACCEPTED and self.mode_pending == name:
            self.mode_pending = None
        return code

    async def enter_offboard(self, target: Target) -> AutopilotResult | None:
        """Stream `target`, and once the stream has run long enough, switch to OFFBOARD. None on success."""
        self.stream.start(target)
        warm = await self.wait_for(lambda: self.stream.running_for() >= self.s.offboard_warmup_s,
                                   self.s.offboard_warmup_s + 2.0)
        if not warm:
            return self._result("offboard", False, "OFFBOARD not requested: the setpoint stream did not start")
        if self.mode != "OFFBOARD":
            code = await self.set_mode("OFFBOARD")
            if code != px4.MAV_RESULT_ACCEPTED:
                res = self._ack_result("offboard", code, "OFFBOARD", "")
                self.stream.stop()
                return res
        if not await self.wait_for(lambda: self.mode == "OFFBOARD", self.s.mode_timeout_s):
            self.stream.stop()
            return self._result("offboard", False, f"OFFBOARD accepted but PX4 still reports {self.mode} after "
                                f"{self.s.mode_timeout_s:.0f} s", px4.MAV_RESULT_ACCEPTED)
        self.offboard_expected = True
        self.mode_requested = "OFFBOARD"
        return None

    async def takeoff(self, cmd: TakeoffCommand) -> AutopilotResult:
        if not self.have_position:
            return self._result("takeoff", False, "no LOCAL_POSITION_NED from PX4 yet: cannot take off without "
                                "a position estimate")
        refused = self.authority_refusal("takeoff", cmd.task_id)
        if refused is not None:
            return refused
        if not self.armed and (refused := await self.preflight_refusal("takeoff")) is not None:
            return refused
        async with self._flight_lock:
            self.epoch += 1
            epoch = self.epoch
            x, y, z = self.position
            yaw = self.yaw
            code: int | None = None
            if not (self.armed and self.offboard_ok and self.offboard_expected):
                if not self.armed:
                    # Disarmed with our stream still running (a crash stopped the motors in OFFBOARD): the old
                    # offboard flight is over; arm and enter OFFBOARD anew rather than wait on a vehicle that
                    # cannot climb.
                    self.offboard_expected = False
                    # Stream first so PX4 sees setpoints while it arms (it auto-disarms if idle too long).
                    self.stream.start(Target(x, y, z, yaw))
                    code = await self.command_long(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1)
                    if code != px4.MAV_RESULT_ACCEPTED:
                        self.stream.stop()
                        return self._ack_result("takeoff", code, "arm", "")
                    self.armed = True
                failed = await self.enter_offboard(Target(x, y, z, yaw))
                if failed is not None:
                    return failed.model_copy(update={"command": "takeoff"})
                code = px4.MAV_RESULT_ACCEPTED
            if epoch != self.epoch or self.override:
                return self._stopped("takeoff", code)
            alt = cmd.altitude
            self.stream.set_target(Target(x, y, alt, yaw))
            tol = self.s.arrival_tolerance_m

            def settled() -> bool:
                px, py, pz = self.position
                there = math.dist((px, py, pz), (x, y, alt)) <= tol and self.landed_state == LandedState.IN_AIR
                return there or epoch != self.epoch or not self.offboard_expected or not self.armed

            self.climbing = True
            try:
                reached = await self.wait_for(settled, self.s.takeoff_timeout_s)
            finally:
                self.climbing = False
            if self.override:
                return self._stopped("takeoff", code)
            if epoch != self.epoch:
                return self._result("takeoff", False, "takeoff superseded by a newer command", code)
            if not self.armed:
                return self._result("takeoff", False, f"vehicle disarmed during takeoff{self._status_hint()}", code)
            if not self.offboard_expected:
                return self._result("takeoff", False, f"offboard lost during takeoff: PX4 switched to {self.mode}"
                                    f"{self._status_hint()}", code)
            if not reached:
                return self._result("takeoff", False, f"altitude {alt:.2f} m not reached within "
                                    f"{self.s.takeoff_timeout_s:.0f} s (z = {self.position[2]:.2f} m, "
                                    f"landed_state={self.landed_state.value})", code)
            return self._result("takeoff", True, f"airborne at {self.position[2]:.2f} m, holding in OFFBOARD", code)

    async def goto(self, cmd: GotoCommand) -> AutopilotResult:
        p = cmd.position
        if not px4.all_finite(p.x, p.y, p.z, cmd.yaw) or (cmd.max_speed is not None
                                                           and not math.isfinite(cmd.max_speed)):
            return self._result("goto", False, f"goto rejected: non-finite value in position ({p.x}, {p.y}, {p.z})"
                                f", yaw {cmd.yaw} or max_speed {cmd.max_speed}")
        # PX4's land detector lags a climb by a second or two, so our own offboard takeoff also counts.
        if not (self.armed and (self.airborne or (self.offboard_expected and self.stream.running))):
            return self._result("goto", False, f"goto rejected: the vehicle is not airborne (armed={self.armed}, "
                                f"landed_state={self.landed_state.value}); take off first")
        refused = self.authority_refusal("goto", cmd.task_id)
        if refused is not None:
            return refused
        self.epoch += 1
        if not (self.offboard_ok and self.offboard_expected):
            failed = await self.enter_offboard(self.current_target())
            if failed is not None:
                return failed.model_copy(update={"command": "goto"})
            if self.override:
                return self._stopped("goto")
        # The envelope check already refused a faster max_speed; none given means the envelope's limit, so a
        # goto never jumps the setpoint and flies at the autopilot's own (higher) speed.
        speed = self.s.max_speed if cmd.max_speed is None else min(cmd.max_speed, self.s.max_speed)
        start = None
        if speed is not None:
            # Ramp from where the setpoint is now (not the measured position) so the setpoint never jumps.
            prev = self.stream.target
            start = prev.at(time.monotonic())[:3] if prev is not None else self.position
        self.stream.set_target(Target(p.x, p.y, p.z, px4.wrap_pi(cmd.yaw), start=start, speed=speed,
                                      t0=time.monotonic()))
        how = f" at {speed:.2f} m/s" if speed is not None else ""
        return self._result("goto", True, f"target set to ({p.x:.2f}, {p.y:.2f}, {p.z:.2f}) yaw {cmd.yaw:.2f}{how}",
                            px4.MAV_RESULT_ACCEPTED)

    async def hold(self, _cmd: HoldCommand) -> AutopilotResult:
        self.epoch += 1
        if self.offboard_expected and self.stream.running:
            t = self.current_target()
            self.stream.set_target(t)
            return self._result("hold", True, f"holding at ({t.x:.2f}, {t.y:.2f}, {t.z:.2f}) in OFFBOARD")
        if self.airborne and self.mode == "AUTO.LOITER":
            return self._result("hold", True, "holding in AUTO.LOITER")
        if self.airborne and self.mode_requested is not None and self.mode == self.mode_requested:
            code = await self.set_mode("AUTO.LOITER")
            if code == px4.MAV_RESULT_ACCEPTED:
                self.mode_requested = "AUTO.LOITER"
            return self._ack_result("hold", code, "AUTO.LOITER", "holding in AUTO.LOITER")
        if self.airborne:
            # PX4 (a failsafe, RTL) or the pilot (POSCTL) chose this mode: holding would override them.
            return self._result("hold", True, f"PX4 has control in {self.mode}: not overriding it"
                                + (f" ({self.override})" if self.override else ""))
        return self._result("hold", True, f"on the ground (landed_state={self.landed_state.value}): nothing to hold")

    async def land(self, _cmd: LandCommand) -> AutopilotResult:
        self.epoch += 1
        was_expected = self.offboard_expected
        self.offboard_expected = False  # leaving OFFBOARD on purpose is not an offboard loss
        code = await self.set_mode("AUTO.LAND")
        if code == px4.MAV_RESULT_ACCEPTED:
            self.stream.stop()
            self.mode_requested = "AUTO.LAND"
        else:
            self.offboard_expected = was_expected
        return self._ack_result("land", code, "AUTO.LAND", "landing (AUTO.LAND)")

    async def gripper_cmd(self, cmd: GripperCommand) -> AutopilotResult:
        grab = cmd.action == "close"
        if self.s.gripper_actuation == "actuator":
            # DO_SET_ACTUATOR: params 1-6 drive "Peripheral via Actuator Set 1..6"; NaN leaves an output alone.
            values = [math.nan] * 6 + [0.0]  # param 7: index of the actuator set (0 = 1..6)
            values[self.s.gripper_actuator_index - 1] = (self.s.gripper_actuator_closed if grab
                                                         else self.s.gripper_actuator_open)
            code = await self.command_long(px4.MAV_CMD_DO_SET_ACTUATOR, *values)
        else:
            code = await self.command_long(px4.MAV_CMD_DO_GRIPPER, self.s.gripper_id, 1 if grab else 0)
        if code == px4.MAV_RESULT_ACCEPTED:
            self.gripper = GripperState.CLOSED if grab else GripperState.OPEN
        return self._ack_result("gripper", code, f"gripper {cmd.action}",
                                "gripper closed (grab)" if grab else "gripper opened (release)")

    # ------------------------------------------------------------------ outputs on the bus

    def state(self) -> VehicleState:
        link_ok = self.link_ok
        if self.link_was_ok and not link_ok and not self.message.startswith("link lost"):
            self.message = (f"link lost: no HEARTBEAT from system {self.target_system} for "
                            f"{self.s.heartbeat_timeout_s:.1f} s")
            log.warning("%s", self.message)
        return VehicleState(
            vehicle_id=self.s.vehicle_id, position=Vec3(x=self.position[0], y=self.position[1], z=self.position[2]),
            velocity=Vec3(x=self.velocity[0], y=self.velocity[1], z=self.velocity[2]), yaw=self.yaw,
            roll=self.roll, pitch=self.pitch, armed=self.armed, mode=self.mode, landed_state=self.landed_state,
            battery_voltage=self.battery_voltage, battery_remaining=self.battery_remaining, gripper=self.gripper,
            gripper_width=self.gripper_width, gripper_holding=self.gripper_holding, link_ok=link_ok,
            offboard_ok=self.offboard_ok and self.offboard_expected,
            last_heartbeat_ns=self.last_hb_ns, message=self.message, override=self.override,
            override_ns=self.override_ns,
        )

    def health(self) -> Health:
        details: dict[str, Any] = {**self.stream.stats(), **self.counters, "mavlink_sent": self.link.sent,
                                   "target_system": self.target_system, "mode": self.mode,
                                   "refused_autopilots": sorted(f"{sy}/{co} at {wh}"
                                                                for sy, co, wh in self.refused_autopilots)[:8],
                                   "override": self.override,
                                   "peer": f"{self.link.peer[0]}:{self.link.peer[1]}" if self.link.peer else None,
                                   "connection": self.s.connection, "publishes_tf": self.publishes_tf(),
                                   "signing": self.link.signing}
        ok = self.link_ok
        return Health(service=SERVICE, ok=ok, message="" if ok else (self.message or "no autopilot link"),
                      details=details)

    async def publish_state_loop(self, stop: asyncio.Event) -> None:
        period = 1.0 / self.s.state_rate_hz
        next_t = time.monotonic()
        while not stop.is_set():
            st = self.state()
            assert self.bus is not None
            self.bus.publish(self.keys.autopilot_state, st, reliable=False)
            if self.have_position and self.publishes_tf():
                # The message's pitch is nose-up positive; FLU's rotation about +y (left) is nose-down.
                T = pose_matrix(*self.position, self.yaw, self.roll, -self.pitch)  # noqa: N806
                self.bus.publish(self.keys.tf, transforms_message([(WORLD_FRAME, BODY_FRAME, T)], st.stamp_ns),
                                 reliable=False)
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -period:
                next_t = time.monotonic()
            await asyncio.sleep(max(0.0, delay))

    def publishes_tf(self, now: float | None = None) -> bool:
        """Whether world->base_link is ours to publish now (settings.publish_tf; `auto`: unless the vehicle's
        simulator reported within AUTO_TF_SIM_FRESH_S that it publishes tf, decided after AUTO_TF_GRACE_S)."""
        if self.s.publish_tf != "auto":
            return bool(self.s.publish_tf)
        now = time.monotonic() if now is None else now
        if now - self.t0 < AUTO_TF_GRACE_S:
            return False
        return self.sim_tf_mono is None or now - self.sim_tf_mono > AUTO_TF_SIM_FRESH_S

    async def sim_health_loop(self, stop: asyncio.Event) -> None:
        """publish_tf `auto`: note when the vehicle's simulator says it publishes the camera and tf."""
        assert self.bus is not None
        sub = self.bus.subscribe(self.keys.health("sim"), maxsize=4, overflow="drop_oldest")
        while not stop.is_set():
            health = await sub.recv()
            if health.details.get("camera") is True:
                if self.sim_tf_mono is None:
                    log.info("publish_tf auto: the simulator publishes tf; the bridge does not")
                self.sim_tf_mono = time.monotonic()

    async def heartbeat_loop(self, stop: asyncio.Event) -> None:
        while not stop.is_set():
            self.send_heartbeat()
            await asyncio.sleep(1.0)

    async def health_loop(self, stop: asyncio.Event) -> None:
        while not stop.is_set():
            assert self.bus is not None
            self.bus.publish(self.keys.health(SERVICE), self.health())
            await asyncio.sleep(self.s.health_period_s)

    async def abort_loop(self, stop: asyncio.Event, key: BoundTopic[Abort]) -> None:
        """Aborts reach the bridge directly (not only through the executor), so a dead executor cannot leave
        the vehicle flying to its last target; the fleet-wide key is obeyed like the vehicle's own."""
        assert self.bus is not None
        sub = self.bus.subscribe(key, maxsize=16, overflow="drop_newest")
        while not stop.is_set():
            abort = await sub.recv()
            self._spawn(self.on_abort(abort))

    async def serve_command(self, cmd: Any, caller: Caller) -> AutopilotResult:
        return await self.handle(cmd, caller)

    async def run(self, stop: asyncio.Event) -> None:
        assert self.bus is not None
        self.loop = asyncio.get_running_loop()
        self.link.start(self.loop, self.on_message)
        self.bus.serve(self.keys.autopilot_command, self.serve_command, with_caller=True)
        announce(self.bus, self.s, "autopilot_bridge")  # alive once it answers commands
        log.info("bridge on %s; serving %s", self.s.connection, self.keys.autopilot_command)
        loops = [asyncio.create_task(c) for c in (self.publish_state_loop(stop), self.heartbeat_loop(stop),
                                                  self.health_loop(stop), self.abort_loop(stop, self.keys.abort),
                                                  self.abort_loop(stop, FLEET_ABORT))]
        if self.s.publish_tf == "auto":
            loops.append(asyncio.create_task(self.sim_health_loop(stop)))
        stopper = asyncio.create_task(stop.wait())
        try:
            done, _ = await asyncio.wait([*loops, stopper], return_when=asyncio.FIRST_COMPLETED)
            for t in done:
                if t is not stopper:
                    t.result()  # a crashed loop ends the service with its error
        finally:
            for t in [*loops, stopper, *self._tasks]:
                t.cancel()
            await asyncio.gather(*loops, stopper, return_exceptions=True)
            self.stream.stop()
            self.link.close()


async def run(bus: Bus, settings: BridgeSettings, stop: asyncio.Event) -> None:
    # The setpoint thread waits for the GIL whenever another thread holds it; Python's default 5 ms switch
    # interval would show up directly as stream jitter.
    sys.setswitchinterval(settings.gil_switch_interval_s)
    link = MavlinkLink(settings.connection, baud=settings.baud, source_system=settings.source_system,
                       source_component=settings.source_component, signing_key=settings.signing_key_bytes)
    await Bridge(bus, settings, link).run(stop)
