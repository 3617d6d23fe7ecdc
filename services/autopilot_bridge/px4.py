"""PX4's MAVLink dialect in pure functions: mode codes, result names, NED<->ENU, setpoint and command fields.

NED exists only inside the bridge: everything that leaves this module towards the stack is ENU/FLU.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# --------------------------------------------------------------------------- MAVLink numbers we use

MAV_AUTOPILOT_PX4 = 12
MAV_AUTOPILOT_INVALID = 8
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_TYPE_GCS = 6
MAV_COMP_ID_ONBOARD_COMPUTER = 191
MAV_COMP_ID_AUTOPILOT1 = 1
MAV_STATE_ACTIVE = 4
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_FRAME_LOCAL_NED = 1

MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_DO_GRIPPER = 211
MAV_CMD_DO_SET_ACTUATOR = 187
MAV_CMD_SET_MESSAGE_INTERVAL = 511
FORCE_ARM_MAGIC = 21196.0

# Message ids whose rates we ask PX4 for.
MSG_SYS_STATUS = 1
MSG_ATTITUDE = 30
MSG_LOCAL_POSITION_NED = 32
MSG_EXTENDED_SYS_STATE = 245

COMMAND_NAMES = {
    MAV_CMD_COMPONENT_ARM_DISARM: "COMPONENT_ARM_DISARM",
    MAV_CMD_DO_SET_MODE: "DO_SET_MODE",
    MAV_CMD_DO_GRIPPER: "DO_GRIPPER",
    MAV_CMD_DO_SET_ACTUATOR: "DO_SET_ACTUATOR",
    MAV_CMD_SET_MESSAGE_INTERVAL: "SET_MESSAGE_INTERVAL",
}

# MAV_RESULT (common.xml); PX4 answers every COMMAND_LONG with one of these.
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_IN_PROGRESS = 5
MAV_RESULT_NAMES = {
    0: "MAV_RESULT_ACCEPTED",
    1: "MAV_RESULT_TEMPORARILY_REJECTED",
    2: "MAV_RESULT_DENIED",
    3: "MAV_RESULT_UNSUPPORTED",
    4: "MAV_RESULT_FAILED",
    5: "MAV_RESULT_IN_PROGRESS",
    6: "MAV_RESULT_CANCELLED",
    7: "MAV_RESULT_COMMAND_LONG_ONLY",
    8: "MAV_RESULT_COMMAND_INT_ONLY",
    9: "MAV_RESULT_COMMAND_UNSUPPORTED_MAV_FRAME",
}
_RESULT_WORDS = {0: "accepted", 1: "temporarily rejected", 2: "denied", 3: "unsupported", 4: "failed",
                 5: "in progress", 6: "cancelled"}


def result_name(code: int | None) -> str:
    if code is None:
        return ""
    return MAV_RESULT_NAMES.get(code, f"MAV_RESULT_{code}")


def result_words(code: int) -> str:
    return _RESULT_WORDS.get(code, f"result {code}")


# EXTENDED_SYS_STATE.landed_state (MAV_LANDED_STATE) -> our LandedState values.
LANDED_STATE_NAMES = {0: "unknown", 1: "on_ground", 2: "in_air", 3: "takeoff", 4: "landing"}

# SET_POSITION_TARGET_LOCAL_NED type_mask: ignore velocity, acceleration and yaw rate; use position + yaw.
TYPE_MASK_POSITION_YAW = 2552  # 0x9F8

# --------------------------------------------------------------------------- PX4 custom modes

MAIN_MANUAL, MAIN_ALTCTL, MAIN_POSCTL, MAIN_AUTO, MAIN_ACRO, MAIN_OFFBOARD, MAIN_STABILIZED = 1, 2, 3, 4, 5, 6, 7
MAIN_NAMES = {1: "MANUAL", 2: "ALTCTL", 3: "POSCTL", 4: "AUTO", 5: "ACRO", 6: "OFFBOARD", 7: "STABILIZED",
              8: "RATTITUDE", 9: "TERMINATION"}
AUTO_SUB_NAMES = {1: "READY", 2: "TAKEOFF", 3: "LOITER", 4: "MISSION", 5: "RTL", 6: "LAND", 7: "RTGS",
                  8: "FOLLOW_TARGET", 9: "PRECLAND", 10: "VTOL_TAKEOFF"}
POSCTL_SUB_NAMES = {0: "", 1: "ORBIT", 2: "SLOW"}

# Mode name -> (main, sub) for DO_SET_MODE.
MODES: dict[str, tuple[int, int]] = {
    "MANUAL": (MAIN_MANUAL, 0), "ALTCTL": (MAIN_ALTCTL, 0), "POSCTL": (MAIN_POSCTL, 0),
    "OFFBOARD": (MAIN_OFFBOARD, 0), "STABILIZED": (MAIN_STABILIZED, 0),
    **{f"AUTO.{name}": (MAIN_AUTO, sub) for sub, name in AUTO_SUB_NAMES.items()},
}


def decode_custom_mode(custom_mode: int) -> str:
    """HEARTBEAT.custom_mode -> PX4 mode name (main mode in bits 16-23, sub-mode in bits 24-31)."""
    main = (custom_mode >> 16) & 0xFF
    sub = (custom_mode >> 24) & 0xFF
    if main == MAIN_AUTO:
        return f"AUTO.{AUTO_SUB_NAMES.get(sub, str(sub))}"
    if main == MAIN_POSCTL and POSCTL_SUB_NAMES.get(sub):
        return f"POSCTL.{POSCTL_SUB_NAMES[sub]}"
    return MAIN_NAMES.get(main, f"UNKNOWN({main}.{sub})")


def encode_custom_mode(name: str) -> int:
    main, sub = MODES[name]
    return (main << 16) | (sub << 24)


def set_mode_params(name: str) -> tuple[float, float, float]:
    """DO_SET_MODE params 1-3 for a PX4 mode name."""
    if name not in MODES:
        raise ValueError(f"unknown PX4 mode {name!r}; known: {sorted(MODES)}")
    main, sub = MODES[name]
    return float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(main), float(sub)


# --------------------------------------------------------------------------- frames


def wrap_pi(a: float) -> float:
    """Angle into (-pi, pi]."""
    a = math.fmod(a + math.pi, 2.0 * math.pi)
    if a <= 0.0:
        a += 2.0 * math.pi
    return a - math.pi


def ned_to_enu(x: float, y: float, z: float) -> tuple[float, float, float]:
    """NED (north, east, down) -> ENU (east, north, up); works for positions and velocities."""
    return (y, x, -z)


def enu_to_ned(x: float, y: float, z: float) -> tuple[float, float, float]:
    return (y, x, -z)


def yaw_ned_to_enu(yaw_ned: float) -> float:
    """Heading clockwise from north -> heading counter-clockwise from east."""
    return wrap_pi(math.pi / 2.0 - yaw_ned)


def yaw_enu_to_ned(yaw_enu: float) -> float:
    return wrap_pi(math.pi / 2.0 - yaw_enu)


def all_finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


@dataclass(frozen=True)
class SetpointNED:
    """A SET_POSITION_TARGET_LOCAL_NED position+yaw setpoint, ready to send."""

    x: float
    y: float
    z: float
    yaw: float

    @classmethod
    def from_enu(cls, x: float, y: float, z: float, yaw: float) -> SetpointNED:
        n, e, d = enu_to_ned(x, y, z)
        return cls(n, e, d, yaw_enu_to_ned(yaw))

    def fields(self, time_boot_ms: int, target_system: int, target_component: int) -> tuple:
        """Positional arguments of `mav.set_position_target_local_ned_encode`."""
        return (time_boot_ms & 0xFFFFFFFF, target_system, target_component, MAV_FRAME_LOCAL_NED,
                TYPE_MASK_POSITION_YAW, self.x, self.y, self.z, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, self.yaw, 0.0)
