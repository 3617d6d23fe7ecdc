"""A tiny PX4 stand-in on raw pymavlink over real UDP, for the bridge's protocol tests (the real simulator is
used by the integration tests): heartbeats with PX4 custom modes, ACKs, offboard that needs a stream."""

from __future__ import annotations

import os
import socket
import threading
import time

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil  # noqa: E402

from services.autopilot_bridge import px4  # noqa: E402

mavutil.set_dialect("common")
mavlink = mavutil.mavlink


# Failsafe parameters as a safely configured airframe reports them (the bridge's preflight reads them).
SAFE_FAILSAFE_PARAMS = {"COM_OBL_RC_ACT": 5.0, "COM_OF_LOSS_T": 0.5, "GF_ACTION": 2.0, "GF_MAX_HOR_DIST": 6.0,
                        "GF_MAX_VER_DIST": 3.0}


def param_reply(mav, params: dict[str, float], request):
    """PX4's PARAM_VALUE answer to a PARAM_REQUEST_READ by name, or None for a parameter it does not have."""
    pid = request.param_id
    name = pid.rstrip("\x00") if isinstance(pid, str) else pid.decode().rstrip("\x00")
    if name not in params:
        return None
    names = list(params)
    return mav.param_value_encode(name.encode(), params[name], mavlink.MAV_PARAM_TYPE_REAL32, len(names),
                                  names.index(name))


class FakePX4:
    """Sends to the bridge's UDP port like PX4 SITL's offboard link; records everything it receives."""

    def __init__(self, bridge_port: int, system: int = 1, component: int = 1, signing_key: bytes | None = None,
                 link_id: int = 0) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.02)
        self.addr = ("127.0.0.1", bridge_port)
        self.mav = mavlink.MAVLink(None, srcSystem=system, srcComponent=component)
        self.mav.robust_parsing = True
        if signing_key is not None:  # as PX4 with a key on its SD card: signs all, accepts only signed frames
            self.mav.signing.secret_key = signing_key
            self.mav.signing.link_id = link_id
            self.mav.signing.timestamp = int((time.time() - 1420070400) * 100_000)
            self.mav.signing.sign_outgoing = True
        self.system = system
        self.lock = threading.Lock()
        self.received: list = []
        self.setpoints: list = []
        self.commands: list = []
        self.armed = False
        self.mode = "POSCTL"
        self.ned = [0.0, 0.0, 0.0]
        self.yaw_ned = 0.0
        self.deny_arm = False
        self.deny_offboard = False
        self.heartbeats = True
        self.ack_commands = True
        self.follow_setpoints = True  # False: OFFBOARD setpoints move nothing (a climb that never arrives)
        self.last_setpoint_t = 0.0
        self.params = dict(SAFE_FAILSAFE_PARAMS)
        self._stop = threading.Event()
        self._send_lock = threading.Lock()
        self._threads = [threading.Thread(target=self._rx, daemon=True), threading.Thread(target=self._tx, daemon=True)]

    @property
    def port(self) -> int:
        return self.sock.getsockname()[1]

    def start(self) -> FakePX4:
        for t in self._threads:
            t.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2)
        self.sock.close()

    def send(self, msg, mav=None) -> None:
        # One frame at a time, as PX4 serialises a link's output: the receive thread (acks, replies) and the send
        # thread (streams) both send, and signing stamps each frame with an increasing timestamp in pack(), so two
        # threads packing at once could put a later-stamped frame on the wire first; the bridge then rightly drops
        # the other as a replay (a bad signature, 1 run in ~20 of the signing test).
        with self._send_lock:
            buf = msg.pack(mav or self.mav)
            (mav or self.mav).seq = ((mav or self.mav).seq + 1) % 256
            self.sock.sendto(buf, self.addr)

    def names(self) -> list[str]:
        with self.lock:
            return [m.get_type() for m in self.received]

    def _tx(self) -> None:
        n = 0
        while not self._stop.is_set():
            n += 1
            if self.heartbeats and n % 5 == 0:
                base = px4.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (px4.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
                self.send(self.mav.heartbeat_encode(2, px4.MAV_AUTOPILOT_PX4, base,
                                                    px4.encode_custom_mode(self.mode), 4))
            if self.heartbeats:
                x, y, z = self.ned
                self.send(self.mav.local_position_ned_encode(0, x, y, z, 0.0, 0.0, 0.0))
                self.send(self.mav.attitude_encode(0, 0.0, 0.0, self.yaw_ned, 0.0, 0.0, 0.0))
                landed = 2 if (self.armed and z < -0.1) else 1
                self.send(self.mav.extended_sys_state_encode(0, landed))
            time.sleep(0.02)

    def _rx(self) -> None:
        while not self._stop.is_set():
            try:
                data, _ = self.sock.recvfrom(2048)
            except (TimeoutError, OSError):
                continue
            try:
                msgs = self.mav.parse_buffer(data) or []
            except Exception:
                continue
            for m in msgs:
                with self.lock:
                    self.received.append(m)
                self._handle(m)

    def _handle(self, m) -> None:
        t = m.get_type()
        if t == "SET_POSITION_TARGET_LOCAL_NED":
            with self.lock:
                self.setpoints.append(m)
            self.last_setpoint_t = time.monotonic()
            if self.mode == "OFFBOARD" and self.armed and self.follow_setpoints:
                self.ned = [m.x, m.y, m.z]
                self.yaw_ned = m.yaw
        elif t == "PARAM_REQUEST_READ":
            reply = param_reply(self.mav, self.params, m)
            if reply is not None:
                self.send(reply)
        elif t == "COMMAND_LONG":
            with self.lock:
                self.commands.append(m)
            if not self.ack_commands:
                return
            result = 0
            if m.command == px4.MAV_CMD_COMPONENT_ARM_DISARM:
                if m.param1 == 1 and self.deny_arm:
                    result = 2
                else:
                    self.armed = m.param1 == 1
            elif m.command == px4.MAV_CMD_DO_SET_MODE:
                name = px4.decode_custom_mode((int(m.param2) << 16) | (int(m.param3) << 24))
                if name == "OFFBOARD" and (self.deny_offboard or time.monotonic() - self.last_setpoint_t > 0.5):
                    result = 2
                    self.send(self.mav.statustext_encode(4, b"Switching to Offboard is currently not available"))
                else:
                    self.mode = name
            self.send(self.mav.command_ack_encode(m.command, result, 0, 0, m.get_srcSystem(), m.get_srcComponent()))
