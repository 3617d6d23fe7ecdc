"""Vehicle geometry shared by the simulator and the stack: camera intrinsics and the camera and gripper mounts.

The mounts (the paper's camera and gripper frames on the body) are configured in ONE place, `Mount`
(env `AERMANI_MOUNT_*`), which every service's settings carry as `settings.mount`: the camera service and the
simulator publish it on `tf` (base_link->camera, base_link->gripper), perception reads it from `tf`, the
executor plans standoffs and grasp heights with it. Consumers read live intrinsics from `camera/calibration`;
`DEFAULT_INTRINSICS` is what the simulator publishes and what is assumed before a calibration arrives.
"""

from __future__ import annotations

import math
from typing import Annotated

import numpy as np
from pydantic import Field, ValidationInfo, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

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


Vec3Tuple = Annotated[tuple[float, float, float], NoDecode]


class Mount(BaseSettings):
    """Where the camera and the gripper sit on the body (FLU, metres), from `AERMANI_MOUNT_*`. The defaults are
    the simulator's airframe; a real airframe measures its own (docs/hardware.md)."""

    model_config = SettingsConfigDict(env_prefix="AERMANI_MOUNT_", extra="ignore", frozen=True,
                                      use_attribute_docstrings=True)

    camera_offset: Vec3Tuple = CAMERA_OFFSET_BODY
    """Camera optical centre in the body frame (x forward, y left, z up), metres, e.g. `0.12,0,-0.05`."""
    camera_pitch_deg: float = Field(math.degrees(CAMERA_PITCH_DOWN), ge=-10.0, le=90.0)
    """Camera pitch below the horizon, degrees (0 looks straight ahead, 90 straight down)."""
    gripper_offset: Vec3Tuple = GRIPPER_OFFSET_BODY
    """Gripper capture point in the body frame, metres, e.g. `0,0,-0.22` (below the body origin)."""

    @field_validator("camera_offset", "gripper_offset", "camera_pitch_deg", mode="before")
    @classmethod
    def _vec3(cls, v: object, info: ValidationInfo) -> object:
        if isinstance(v, str) and not v.strip():  # compose passes unset variables as "": keep the default
            return cls.model_fields[str(info.field_name)].default
        if isinstance(v, str) and info.field_name != "camera_pitch_deg":
            parts = [p for p in v.replace("[", " ").replace("]", " ").replace(",", " ").split() if p]
            if len(parts) != 3:
                raise ValueError(f"expected three numbers x,y,z (metres), got {v!r}")
            return tuple(float(p) for p in parts)
        return v

    def base_to_camera(self) -> np.ndarray:
        """4x4 pose of the camera optical frame in the body frame."""
        return base_to_camera(math.radians(self.camera_pitch_deg), self.camera_offset)

    def base_to_gripper(self) -> np.ndarray:
        """4x4 pose of the gripper capture point in the body frame."""
        return base_to_gripper(self.gripper_offset)
