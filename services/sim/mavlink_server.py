"""PX4 SITL-like MAVLink endpoints over UDP: a thread that reads commands, runs the physics and streams telemetry."""

from __future__ import annotations

import logging
import math
import select
import socket
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mav

from services.sim.core import SimCore
from services.sim.vehicle import (
    ACCEPTED,
    DENIED,
    FORCE_MAGIC,
    MAIN_AUTO,
    MAIN_OFFBOARD,
    MAIN_POSCTL,
    SUB_LOITER,
    SUB_RTL,
    UNSUPPORTED,
    Vehicle,
    yaw_ned_to_enu,
)
from shared.errors import MavlinkError

log = logging.getLogger("aermani.sim.mavlink")

SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
SYSTEM_ID = 1
COMPONENT_ID = mav.MAV_COMP_ID_AUTOPILOT1

# Default telemetry rates in Hz (what PX4's onboard/API link streams, roughly).
DEFAULT_RATES: dict[int, float] = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 50.0,
    mav.MAVLINK_MSG_ID_ATTITUDE: 50.0,
    mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 20.0,
    mav.MAVLINK_MSG_ID_ODOMETRY: 10.0,
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    mav.MAVLINK_MSG_ID_SYS_STATUS: 2.0,
    mav.MAVLINK_MSG_ID_BATTERY_STATUS: 1.0,
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    mav.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    # The gripper's own sensing (finger opening, both pads in contact), as a payload reports it: DEBUG_VECT
    # "GRIPPER" x = opening (m), y = holding (1/0), z = closing commanded (1/0).
    mav.MAVLINK_MSG_ID_DEBUG_VECT: 10.0,
}
GRIPPER_DEBUG_NAME = b"GRIPPER"
STREAMABLE = set(DEFAULT_RATES)

# Types of SET_POSITION_TARGET_LOCAL_NED.type_mask bits (set = ignore that field).
IGNORE_POS = 0b111
IGNORE_VEL = 0b111000
IGNORE_YAW = 1024
IGNORE_YAW_RATE = 2048

# Home of the simulated world, only for GLOBAL_POSITION_INT/HOME_POSITION (AMSL 0 so that takeoff
# altitudes read the same relative or absolute).
HOME_LAT, HOME_LON = 47.3977419, 8.5455938
EARTH_R = 6_378_137.0

PARAMS: dict[str, float] = {
    "MIS_TAKEOFF_ALT": 1.5,
    "COM_OF_LOSS_T": 0.5,
    "COM_DISARM_LAND": 2.0,
    "MPC_XY_VEL_MAX": 2.0,
    "MPC_Z_VEL_MAX_UP": 1.0,
    "MPC_Z_VEL_MAX_DN": 1.0,
    "MPC_LAND_SPEED": 0.7,
    "MPC_YAWRAUTO_MAX": 90.0,
    "RTL_RETURN_ALT": 2.0,
    "SYS_FAILURE_EN": 0.0,  # PX4 answers MAV_CMD_INJECT_FAILURE only when this is 1
    "SIM_GRIP_ACT_SET": 1.0,  # the gripper is on "Peripheral via Actuator Set N" for MAV_CMD_DO_SET_ACTUATOR
    # Failsafe configuration, checked by the bridge's preflight. The vehicle flies COM_OBL_RC_ACT and
    # COM_FAIL_ACT_T (services.sim.vehicle.OFFBOARD_LOSS_ACTIONS); the geofence ones are reported only.
    "COM_OBL_RC_ACT": 5.0,  # offboard loss: Hold (Land would put a held object down on the furniture below)
    "COM_FAIL_ACT_T": 3.0,  # s of hold before a failsafe action beyond Hold
    "GF_ACTION": 2.0,  # geofence breach: Hold
    "GF_MAX_HOR_DIST": 6.0,
    "GF_MAX_VER_DIST": 3.0,
}
FAILSAFE_PARAMS = ("COM_OBL_RC_ACT", "COM_FAIL_ACT_T", "GF_ACTION", "GF_MAX_HOR_DIST", "GF_MAX_VER_DIST")
"""The failsafe names AERMANI_SIM_PX4_PARAMS may set at start (PARAM_SET may too): COM_OBL_RC_ACT and
COM_FAIL_ACT_T are flown, the geofence ones only reported (the simulator has no geofence)."""

# MAV_CMD_INJECT_FAILURE units that take the local position estimate away (GPS outdoors, VIO indoors).
POSITION_SENSORS = {mav.FAILURE_UNIT_SENSOR_GPS, mav.FAILURE_UNIT_SENSOR_VIO}
# Messages acted on only when addressed to us (target system/component 0 or ours).
_TARGETED = ("SET_POSITION_TARGET_LOCAL_NED", "COMMAND_LONG", "COMMAND_INT", "PARAM_REQUEST_LIST",
             "PARAM_REQUEST_READ", "PARAM_SET", "MISSION_REQUEST_LIST")
# Commands answered with a message (after the COMMAND_ACK) when accepted.
_REQUESTS = (mav.MAV_CMD_REQUEST_MESSAGE, mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, mav.MAV_CMD_GET_HOME_POSITION)
INT32_MAX = 2**31 - 1


def command_arg(p: list[float], i: int, default: float) -> float:
    """Param i of a COMMAND_LONG/COMMAND_INT, or `default` where the sender left it NaN (PX4: "use the
    default"; MAVSDK sends NaN in every parameter it does not set) or INT32_MAX (COMMAND_INT x/y unset)."""
    v = p[i]
    if not math.isfinite(v) or (i in (4, 5) and v == INT32_MAX):
        return default
    return v


@dataclass
class LinkSettings:
    """One MAVLink UDP link of the simulated autopilot: local port and the remote peer."""

    name: str
    local_port: int
    remote_host: str
    remote_port: int
    bind_host: str = "127.0.0.1"


@dataclass
class Link:
    """One UDP endpoint: sends to the configured remote; a peer that writes from elsewhere is answered there."""

    cfg: LinkSettings
    sock: socket.socket
    mav: mav.MAVLink
    remote: tuple[str, int]
    intervals: dict[int, float] = field(default_factory=dict)  # message id -> seconds (0 = off)
    next_due: dict[int, float] = field(default_factory=dict)
    received: int = 0
    sent: int = 0
    silent_until: float = 0.0  # injected MAVLink signal loss: nothing goes out or in until then (monotonic)

    @property
    def silent(self) -> bool:
        return time.monotonic() < self.silent_until

    def send(self, msg: mav.MAVLink_message) -> None:
        if self.silent:
            return
        try:
            self.sock.sendto(msg.pack(self.mav), self.remote)
            self.sent += 1
        except OSError:  # nobody listens yet (ICMP port unreachable on loopback): PX4 keeps sending too
            pass


class MavlinkServer:
    """Speaks MAVLink like PX4 on UDP for the simulated vehicle: heartbeats, telemetry, commands, offboard setpoints."""

    def __init__(self, core: SimCore, links: list[LinkSettings], speed_factor: float = 1.0,
                 physics_rate: float = 200.0, params: dict[str, float] | None = None) -> None:
        self.core = core
        self.speed_factor = speed_factor
        self.physics_dt = 1.0 / physics_rate
        self.links: list[Link] = []
        for cfg in links:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            # No SO_REUSEADDR: two simulators on one port must fail loudly, not split the traffic.
            sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            try:
                sock.bind((cfg.bind_host, cfg.local_port))
            except OSError as exc:
                sock.close()
                for link in self.links:
                    link.sock.close()
                raise MavlinkError(f"cannot bind the MAVLink {cfg.name} link to udp {cfg.bind_host}:"
                                   f"{cfg.local_port}: {exc}. Is another simulator or PX4 SITL running? Set "
                                   f"AERMANI_SIM_{cfg.name.upper()}_LOCAL_PORT to a free port.") from exc
            sock.setblocking(False)
            m = mav.MAVLink(None, srcSystem=SYSTEM_ID, srcComponent=COMPONENT_ID)
            m.robust_parsing = True
            self.links.append(Link(cfg, sock, m, (cfg.remote_host, cfg.remote_port),
                                   {k: 1.0 / v for k, v in DEFAULT_RATES.items()}))
        # What the vehicle flies is what is reported: its own settings first, then the given PX4 parameters.
        self.params = {**PARAMS, **self.flown_params(core.vehicle.params), **(params or {})}
        self._apply_params()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._boot = time.monotonic()
        self._log_budget: dict[str, int] = {}

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name="sim-mavlink", daemon=True)
        self._thread.start()
        for link in self.links:
            log.info("MAVLink %s link: local udp %s:%d -> %s:%d", link.cfg.name, link.cfg.bind_host,
                     link.cfg.local_port, *link.remote)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        for link in self.links:
            link.sock.close()

    def _loop(self) -> None:
        last = time.monotonic()
        next_tick = last
        socks = [lk.sock for lk in self.links]
        by_sock = {lk.sock: lk for lk in self.links}
        while not self._stop.is_set():
            timeout = max(0.0, next_tick - time.monotonic())
            try:
                ready, _, _ = select.select(socks, [], [], timeout)
            except (OSError, ValueError):
                if self._stop.is_set():
                    return
                raise
            for s in ready:
                self._drain(by_sock[s])
            now = time.monotonic()
            if now < next_tick:
                continue
            next_tick = max(next_tick + self.physics_dt, now - self.physics_dt)
            dt_sim = min(now - last, 0.1) * self.speed_factor
            last = now
            try:
                with self.core.lock:
                    v = self.core.vehicle
                    v.update_modes(now)
                    n = max(1, math.ceil(dt_sim / v.max_step_s))  # substeps the vehicle's controller needs
                    for _ in range(n):
                        v.step(dt_sim / n)
                    events, v.events = v.events, []
                for sev, text in events:
                    self._statustext(sev, text)
                for link in self.links:
                    self._stream(link, now)
            except Exception:  # a bug must not silently kill the vehicle: log and keep flying
                log.exception("simulation tick failed")

    # ------------------------------------------------------------------ receive

    def _drain(self, link: Link) -> None:
        while True:
            try:
                data, anc, _flags, addr = link.sock.recvmsg(65535, socket.CMSG_SPACE(16))
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return  # ICMP errors from earlier sends surface here on Linux
            if link.silent:  # the injected signal loss eats what arrives too
                self.core.count("dropped_signal_lost")
                continue
            rx_ns = time.time_ns()
            for level, kind, cdata in anc:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(cdata) >= 16:
                    sec, nsec = struct.unpack("qq", cdata[:16])
                    rx_ns = sec * 1_000_000_000 + nsec
            link.received += 1
            try:
                msgs = link.mav.parse_buffer(data) or []
            except Exception as exc:  # pymavlink raises on some malformed frames even when robust
                msgs = []
                self._bad(f"unparseable datagram from {addr}: {exc}")
            if link.mav.buf_len() > 0:
                # A UDP datagram carries whole packets: a truncated tail is garbage, and keeping it would
                # make the parser swallow the next valid datagram.
                self._bad(f"{link.mav.buf_len()} trailing bytes from {addr}")
            link.mav.buf = bytearray()
            link.mav.buf_index = 0
            link.mav.expected_length = mav.HEADER_LEN_V1 + 2
            link.mav.have_prefix_error = False
            if addr != link.remote and any(m.get_type() != "BAD_DATA" for m in msgs):
                # Like PX4's UDP links: telemetry goes to the configured remote until a peer speaks valid
                # MAVLink (a whole frame with a good CRC) from elsewhere. Garbage never redirects it.
                log.info("MAVLink %s link: peer at %s:%d, answering there", link.cfg.name, *addr)
                link.remote = addr
            for msg in msgs:
                try:
                    self._handle(link, msg, rx_ns)
                except Exception:
                    self.core.count("handler_errors")
                    log.exception("MAVLink %s handler failed; input ignored", msg.get_type())

    def _bad(self, what: str) -> None:
        self.core.count("bad_input")
        self._log_limited("bad", logging.WARNING, "ignored bad MAVLink input: %s", what)

    def _log_limited(self, key: str, level: int, fmt: str, *args: object) -> None:
        n = self._log_budget.get(key, 0)
        self._log_budget[key] = n + 1
        if n < 20 or n % 100 == 0:
            log.log(level, fmt + ("" if n < 20 else f" ({n} so far)"), *args)

    def _for_us(self, msg: mav.MAVLink_message) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        if ts not in (0, SYSTEM_ID) or tc not in (0, COMPONENT_ID):
            self.core.count("wrong_target")
            self._log_limited("target", logging.WARNING, "ignored %s for system %d component %d (we are %d/%d)",
                              msg.get_type(), ts, tc, SYSTEM_ID, COMPONENT_ID)
            return False
        return True

    def _handle(self, link: Link, msg: mav.MAVLink_message, rx_ns: int) -> None:
        t = msg.get_type()
        self.core.count(f"rx_{t}")
        if t == "BAD_DATA":
            self._bad(f"{getattr(msg, 'reason', 'bad data')} ({len(msg.get_msgbuf())} bytes)")
            return
        if t == "HEARTBEAT":
            return
        if t in _TARGETED:
            if self._for_us(msg):
                self._handle_targeted(link, msg, t, rx_ns)
            return
        if t == "SET_MODE":
            if msg.target_system == SYSTEM_ID:
                main, sub = (msg.custom_mode >> 16) & 0xFF, (msg.custom_mode >> 24) & 0xFF
                with self.core.lock:
                    self.core.vehicle.set_mode(main, sub, time.monotonic())
            return
        if t == "TIMESYNC":
            if msg.tc1 == 0:
                link.send(link.mav.timesync_encode(time.monotonic_ns(), msg.ts1))
            return
        if t in ("SYSTEM_TIME", "PING", "MANUAL_CONTROL", "RC_CHANNELS_OVERRIDE"):
            return
        self.core.count("unknown_messages")
        self._log_limited(f"unknown-{t}", logging.INFO, "ignored unsupported MAVLink message %s", t)

    def _handle_targeted(self, link: Link, msg: mav.MAVLink_message, t: str, rx_ns: int) -> None:
        """A message of `_TARGETED` addressed to us: setpoints, commands, parameters, the mission list."""
        if t == "SET_POSITION_TARGET_LOCAL_NED":
            self._setpoint(msg, rx_ns)
        elif t == "COMMAND_LONG":
            self._command(link, msg, msg.command, [msg.param1, msg.param2, msg.param3, msg.param4,
                                                   msg.param5, msg.param6, msg.param7])
        elif t == "COMMAND_INT":
            self._command(link, msg, msg.command, [msg.param1, msg.param2, msg.param3, msg.param4,
                                                   msg.x, msg.y, msg.z])
        elif t == "MISSION_REQUEST_LIST":
            link.send(link.mav.mission_count_encode(msg.get_srcSystem(), msg.get_srcComponent(), 0,
                                                    getattr(msg, "mission_type", 0)))
        else:  # PARAM_REQUEST_LIST, PARAM_REQUEST_READ, PARAM_SET
            self._param(link, msg)

    def _setpoint(self, msg: mav.MAVLink_message, rx_ns: int) -> None:
        if msg.coordinate_frame != mav.MAV_FRAME_LOCAL_NED:
            self.core.count("setpoint_bad_frame")
            self._log_limited("frame", logging.WARNING, "ignored setpoint in frame %d (only LOCAL_NED=1)",
                              msg.coordinate_frame)
            return
        mask = msg.type_mask
        pos = None if mask & IGNORE_POS == IGNORE_POS else np.array([msg.x, msg.y, msg.z], dtype=float)
        vel = None if mask & IGNORE_VEL == IGNORE_VEL else np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        yaw = None if mask & IGNORE_YAW else float(msg.yaw)
        rate = None if mask & IGNORE_YAW_RATE else float(msg.yaw_rate)
        for arr in (pos, vel):
            if arr is not None and not np.all(np.isfinite(arr)):
                self._bad("setpoint with non-finite values")
                return
        if yaw is not None and not math.isfinite(yaw):
            yaw = None
        if pos is None and vel is None and yaw is None and rate is None:
            self._bad(f"setpoint type_mask {mask} ignores everything")
            return
        with self.core.lock:
            self.core.vehicle.setpoint(time.monotonic(), pos, vel, yaw, rate)
            self.core.setpoint_arrivals_ns.append(rx_ns)

    # ------------------------------------------------------------------ commands

    def _command(self, link: Link, msg: mav.MAVLink_message, cmd: int, p: list[float]) -> None:
        v = self.core.vehicle
        with self.core.lock:
            result, out = self._execute(link, cmd, p)
            events, v.events = v.events, []
        link.send(link.mav.command_ack_encode(cmd, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
        if cmd in _REQUESTS and result == ACCEPTED and out is not None:
            link.send(out)
        if result == UNSUPPORTED:
            self._log_limited(f"cmd-{cmd}", logging.INFO, "unsupported command %d", cmd)
        else:
            log.info("command %d %s from %d/%d -> result %d", cmd, [round(x, 3) for x in p[:3]],
                     msg.get_srcSystem(), msg.get_srcComponent(), result)
        for sev, text in events:
            self._statustext(sev, text)

    def _execute(self, link: Link, cmd: int, p: list[float]) -> tuple[int, Any]:
        """Carry out one command (under the core lock) -> (MAV_RESULT, the message a request asked for or None)."""
        now = time.monotonic()
        v = self.core.vehicle

        def arg(i: int, default: float = 0.0) -> float:
            return command_arg(p, i, default)

        if cmd == mav.MAV_CMD_COMPONENT_ARM_DISARM:
            action = arg(0, -1.0)
            if round(action) not in (0, 1):
                v._event(mav.MAV_SEVERITY_CRITICAL, f"Unsupported ARM_DISARM param: {action:.3f}")
                return UNSUPPORTED, None
            return v.arm(round(action) == 1, force=round(arg(1)) == FORCE_MAGIC), None
        if cmd == mav.MAV_CMD_DO_SET_MODE:
            if int(arg(0)) & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return v.set_mode(int(arg(1)), int(arg(2)), now), None
            return DENIED, None
        if cmd == mav.MAV_CMD_NAV_TAKEOFF:
            return v.takeoff(arg(6, math.nan)), None
        if cmd == mav.MAV_CMD_NAV_LAND:
            return v.land(), None
        if cmd == mav.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return v.set_mode(MAIN_AUTO, SUB_RTL, now), None
        if cmd == mav.MAV_CMD_NAV_LOITER_UNLIM:
            return v.set_mode(MAIN_AUTO, SUB_LOITER, now), None
        if cmd == mav.MAV_CMD_DO_GRIPPER:
            return v.gripper(round(arg(1, mav.GRIPPER_ACTION_RELEASE)) == mav.GRIPPER_ACTION_GRAB), None
        if cmd == mav.MAV_CMD_DO_SET_ACTUATOR:
            # The gripper servo sits on output function "Peripheral via Actuator Set N" (SIM_GRIP_ACT_SET):
            # > 0 closes, < 0 opens, NaN leaves it alone (PX4's semantics for params 1-6).
            n = int(self.params.get("SIM_GRIP_ACT_SET", 1.0))
            value = p[n - 1] if 1 <= n <= 6 and int(arg(6)) == 0 else math.nan
            return (ACCEPTED if not math.isfinite(value) or value == 0.0 else v.gripper(value > 0.0)), None
        if cmd == mav.MAV_CMD_INJECT_FAILURE:
            return self._inject_failure(int(arg(0, -1)), int(arg(1, -1))), None
        if cmd == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(link, int(arg(0, -1)), arg(1)), None
        if cmd in _REQUESTS:
            want = {mav.MAV_CMD_REQUEST_MESSAGE: int(arg(0, -1)),
                    mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                    mav.MAV_CMD_GET_HOME_POSITION: mav.MAVLINK_MSG_ID_HOME_POSITION}[cmd]
            out = self._build(link, want)
            return (ACCEPTED if out is not None else DENIED), out
        return UNSUPPORTED, None

    def _inject_failure(self, unit: int, kind: int) -> int:
        """MAV_CMD_INJECT_FAILURE as PX4 SITL answers it (only with SYS_FAILURE_EN = 1)."""
        v = self.core.vehicle
        if self.params.get("SYS_FAILURE_EN", 0.0) < 0.5:
            v._event(mav.MAV_SEVERITY_CRITICAL, "Failure injection disabled (SYS_FAILURE_EN)")
            return DENIED
        if kind not in (mav.FAILURE_TYPE_OK, mav.FAILURE_TYPE_OFF):
            return UNSUPPORTED
        if unit in POSITION_SENSORS:
            v.set_estimate_valid(kind == mav.FAILURE_TYPE_OK)
            return ACCEPTED
        if unit == mav.FAILURE_UNIT_SYSTEM_BATTERY and kind == mav.FAILURE_TYPE_OFF:
            v.battery_failsafe()
            return ACCEPTED
        return UNSUPPORTED

    def lose_signal(self, duration_s: float) -> None:
        """Failure injection `mavlink_signal off` (PX4 SITL's `failure mavlink_signal off`): every link stops
        sending and drops what it receives for `duration_s` seconds (inf: until `lose_signal(0)`), while the
        vehicle flies on and PX4's own failsafes (offboard loss: hold, then land) act. 0 restores the links."""
        until = time.monotonic() + duration_s if duration_s > 0 else 0.0
        for link in self.links:
            link.silent_until = until
        log.warning("MAVLink signal %s", f"lost for {duration_s:.1f} s (injected)" if duration_s > 0 else "restored")

    def _set_interval(self, link: Link, msg_id: int, interval_us: float) -> int:
        if msg_id not in STREAMABLE:
            return DENIED
        if interval_us < 0:
            link.intervals[msg_id] = 0.0
        elif interval_us == 0:
            link.intervals[msg_id] = 1.0 / DEFAULT_RATES[msg_id]
        else:
            link.intervals[msg_id] = max(interval_us / 1e6, 0.002)  # cap at 500 Hz
        link.next_due.pop(msg_id, None)
        return ACCEPTED

    def _param(self, link: Link, msg: mav.MAVLink_message) -> None:
        names = list(self.params)
        t = msg.get_type()

        def value(i: int) -> mav.MAVLink_message:
            name = names[i]
            return link.mav.param_value_encode(name.encode(), float(self.params[name]),
                                               mav.MAV_PARAM_TYPE_REAL32, len(names), i)

        if t == "PARAM_REQUEST_LIST":
            for i in range(len(names)):
                link.send(value(i))
            return
        pid = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else msg.param_id
        if t == "PARAM_REQUEST_READ":
            i = msg.param_index if msg.param_index >= 0 else (names.index(pid) if pid in names else -1)
            if 0 <= i < len(names):
                link.send(value(i))
            return
        if pid in self.params and math.isfinite(msg.param_value):
            self.params[pid] = float(msg.param_value)
            self._apply_params()
            link.send(value(names.index(pid)))

    @staticmethod
    def flown_params(p: Any) -> dict[str, float]:
        """The PX4 parameters a VehicleParams flies, by PX4 name."""
        return {"MIS_TAKEOFF_ALT": p.takeoff_alt, "COM_OF_LOSS_T": p.offboard_loss_timeout,
                "COM_DISARM_LAND": p.disarm_after_land, "MPC_XY_VEL_MAX": p.max_speed_h,
                "MPC_Z_VEL_MAX_UP": p.max_speed_up, "MPC_Z_VEL_MAX_DN": p.max_speed_down,
                "MPC_LAND_SPEED": p.land_speed, "MPC_YAWRAUTO_MAX": math.degrees(p.yaw_rate),
                "RTL_RETURN_ALT": p.rtl_alt, "COM_OBL_RC_ACT": float(p.offboard_loss_action),
                "COM_FAIL_ACT_T": p.failsafe_land_delay}

    def _apply_params(self) -> None:
        with self.core.lock:
            p = self.core.vehicle.params
            p.takeoff_alt = self.params["MIS_TAKEOFF_ALT"]
            p.offboard_loss_timeout = self.params["COM_OF_LOSS_T"]
            p.disarm_after_land = self.params["COM_DISARM_LAND"]
            p.max_speed_h = self.params["MPC_XY_VEL_MAX"]
            p.max_speed_up = self.params["MPC_Z_VEL_MAX_UP"]
            p.max_speed_down = self.params["MPC_Z_VEL_MAX_DN"]
            p.land_speed = self.params["MPC_LAND_SPEED"]
            p.yaw_rate = math.radians(self.params["MPC_YAWRAUTO_MAX"])
            p.rtl_alt = self.params["RTL_RETURN_ALT"]
            p.offboard_loss_action = int(self.params["COM_OBL_RC_ACT"])
            p.failsafe_land_delay = max(0.0, self.params["COM_FAIL_ACT_T"])

    # ------------------------------------------------------------------ send

    def _statustext(self, severity: int, text: str) -> None:
        for link in self.links:
            link.send(link.mav.statustext_encode(severity, text.encode()[:50]))

    def _stream(self, link: Link, now: float) -> None:
        for msg_id, interval in link.intervals.items():
            if interval <= 0:
                continue
            due = link.next_due.get(msg_id, now)
            if now >= due:
                out = self._build(link, msg_id)
                if out is not None:
                    link.send(out)
                link.next_due[msg_id] = max(due + interval, now)

    def _build(self, link: Link, msg_id: int) -> mav.MAVLink_message | None:
        m = link.mav
        with self.core.lock:
            v = self.core.vehicle
            boot_ms = int(v.sim_time * 1000)  # time since boot runs on simulated time
            if msg_id == mav.MAVLINK_MSG_ID_HEARTBEAT:
                return self._heartbeat(m, v)
            if msg_id in (mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
                          mav.MAVLINK_MSG_ID_ODOMETRY) and not v.estimate_valid:
                return None  # PX4 publishes no position it does not have
            if msg_id == mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
                return m.local_position_ned_encode(boot_ms, *(float(x) for x in v.p), *(float(x) for x in v.v))
            if msg_id == mav.MAVLINK_MSG_ID_ATTITUDE:
                return m.attitude_encode(boot_ms, float(v.roll), float(v.pitch), float(v.yaw), *v.rates)
            if msg_id == mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
                return m.attitude_quaternion_encode(boot_ms, *v.attitude_quaternion(), *v.rates)
            if msg_id == mav.MAVLINK_MSG_ID_ODOMETRY:
                return self._odometry(m, v)
            if msg_id == mav.MAVLINK_MSG_ID_DEBUG_VECT:
                return m.debug_vect_encode(GRIPPER_DEBUG_NAME, boot_ms * 1000, float(v.finger_width),
                                           1.0 if v.holding else 0.0, 1.0 if v.gripper_closed else 0.0)
            if msg_id == mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
                return m.extended_sys_state_encode(mav.MAV_VTOL_STATE_UNDEFINED, v.landed_state)
            if msg_id == mav.MAVLINK_MSG_ID_SYS_STATUS:
                return self._sys_status(m, v)
            if msg_id == mav.MAVLINK_MSG_ID_BATTERY_STATUS:
                cell = int(v.battery_voltage * 1000 / 3)
                return m.battery_status_encode(0, mav.MAV_BATTERY_FUNCTION_ALL, mav.MAV_BATTERY_TYPE_LIPO,
                                               2500, [cell] * 3 + [65535] * 7, 800 if v.armed else 50, -1, -1,
                                               int(v.battery))
            if msg_id == mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
                lat, lon = self._latlon(v.p[0], v.p[1])
                alt_mm = int(-v.p[2] * 1000)
                hdg = int((math.degrees(v.yaw) % 360) * 100)
                return m.global_position_int_encode(boot_ms, lat, lon, alt_mm, alt_mm, int(v.v[0] * 100),
                                                    int(v.v[1] * 100), int(v.v[2] * 100), hdg)
            if msg_id == mav.MAVLINK_MSG_ID_HOME_POSITION:
                lat, lon = self._latlon(v.home[0], v.home[1])
                return m.home_position_encode(lat, lon, int(-v.home[2] * 1000), *(float(x) for x in v.home),
                                              [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0)
            if msg_id == mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
                caps = (mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                        | mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                        | mav.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT | mav.MAV_PROTOCOL_CAPABILITY_MISSION_INT)
                version = (1 << 24) | (15 << 16) | (0 << 8) | 255  # 1.15.0 release
                return m.autopilot_version_encode(caps, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0,
                                                  0x41455253494D)
        return None

    @staticmethod
    def _odometry(m: mav.MAVLink, v: Vehicle) -> mav.MAVLink_message:
        """PX4's ODOMETRY: the estimate's pose in LOCAL_NED, velocity and rates in the body (FRD) frame."""
        qw, qx, qy, qz = v.attitude_quaternion()
        # NED velocity rotated into FRD: the transpose of the body-to-NED rotation.
        r = np.array([[1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
                      [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
                      [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)]])
        vb = r.T @ v.v
        nan21 = [float("nan")] * 21  # covariances unknown (MAVLink: NaN in the first element)
        return m.odometry_encode(int(v.sim_time * 1e6), mav.MAV_FRAME_LOCAL_NED, mav.MAV_FRAME_BODY_FRD,
                                 *(float(x) for x in v.p), [qw, qx, qy, qz], *(float(x) for x in vb), *v.rates,
                                 nan21, nan21, 0, mav.MAV_ESTIMATOR_TYPE_VIO, 100)

    @staticmethod
    def _heartbeat(m: mav.MAVLink, v: Vehicle) -> mav.MAVLink_message:
        """PX4's HEARTBEAT: base mode flags from the flight mode and arming state, the custom mode, the state."""
        base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mav.MAV_MODE_FLAG_STABILIZE_ENABLED
        if v.main_mode in (MAIN_AUTO, MAIN_OFFBOARD):
            base |= mav.MAV_MODE_FLAG_GUIDED_ENABLED
        if v.main_mode == MAIN_AUTO:
            base |= mav.MAV_MODE_FLAG_AUTO_ENABLED
        if v.main_mode == MAIN_POSCTL:
            base |= mav.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        if v.armed:
            base |= mav.MAV_MODE_FLAG_SAFETY_ARMED
        status = mav.MAV_STATE_ACTIVE if v.armed else mav.MAV_STATE_STANDBY
        return m.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, base, v.custom_mode, status)

    @staticmethod
    def _sys_status(m: mav.MAVLink, v: Vehicle) -> mav.MAVLink_message:
        """SYS_STATUS: sensor health (GPS unhealthy without a position estimate), the pre-arm check, battery."""
        # PREARM_CHECK healthy = the arming checks pass (MAVSDK's health.is_armable reads it).
        sensors = 0x3FFFFF | mav.MAV_SYS_STATUS_PREARM_CHECK
        health = sensors if v.estimate_valid else sensors & ~mav.MAV_SYS_STATUS_SENSOR_GPS
        if v.armed or v.arming_check() is not None:
            health &= ~mav.MAV_SYS_STATUS_PREARM_CHECK
        return m.sys_status_encode(sensors, sensors, health, 200, int(v.battery_voltage * 1000),
                                   800 if v.armed else 50, int(v.battery), 0, 0, 0, 0, 0, 0)

    @staticmethod
    def _latlon(north: float, east: float) -> tuple[int, int]:
        lat = HOME_LAT + math.degrees(north / EARTH_R)
        lon = HOME_LON + math.degrees(east / (EARTH_R * math.cos(math.radians(HOME_LAT))))
        return int(lat * 1e7), int(lon * 1e7)

    def state_summary(self) -> dict:
        with self.core.lock:
            v = self.core.vehicle
            return {"mode": v.mode_name, "armed": v.armed, "landed_state": v.landed_state,
                    "position_ned": [float(x) for x in v.p], "yaw_enu": yaw_ned_to_enu(v.yaw),
                    "links": {lk.cfg.name: {"remote": f"{lk.remote[0]}:{lk.remote[1]}", "received": lk.received,
                                            "sent": lk.sent} for lk in self.links}}

