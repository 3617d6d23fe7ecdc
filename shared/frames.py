"""Default vehicle geometry shared by the simulator and the stack: camera intrinsics and mounts.

Consumers read the live values from `camera/calibration` and `tf`; these defaults are what the simulator
publishes and what the executor assumes when no transform has arrived yet.
"""

from __future__ import annotations

import math

import numpy as np

from shared.sensors import Intrinsics

# ZED-like RGB-D camera at 640x480 (about 85 deg horizontal field of view).
DEFAULT_INTRINSICS = Intrinsics(width=640, height=480, fx=350.0, fy=350.0, cx=319.5, cy=239.5)

CAMERA_OFFSET_BODY = (0.12, 0.0, -0.05)  # camera optical centre in the body frame (FLU), metres
CAMERA_PITCH_DOWN = math.radians(35.0)  # camera looks forward and down
GRIPPER_OFFSET_BODY = (0.0, 0.0, -0.22)  # gripper capture point in the body frame (FLU), metres

# Body FLU -> camera optical (x right, y down, z forward) when the camera looks straight ahead.
_FLU_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def base_to_camera(pitch_down: float = CAMERA_PITCH_DOWN,
                   offset: tuple[float, float, float] = CAMERA_OFFSET_BODY) -> np.ndarray:
    """4x4 pose of the camera optical frame in the body frame (maps optical -> body)."""
    c, s = math.cos(pitch_down), math.sin(pitch_down)
    # Positive pitch about body y (left) tilts the x axis down.
    r_pitch = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    T = np.eye(4)  # noqa: N806
    T[:3, :3] = r_pitch @ _FLU_FROM_OPTICAL
    T[:3, 3] = offset
    return T


def base_to_gripper(offset: tuple[float, float, float] = GRIPPER_OFFSET_BODY) -> np.ndarray:
    T = np.eye(4)  # noqa: N806
    T[:3, 3] = offset
    return T
