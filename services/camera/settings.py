"""Settings of the camera service (env AERMANI_CAMERA_*)."""

from __future__ import annotations

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from shared.settings import ServiceSettings


class CameraSettings(ServiceSettings):
    """Camera service configuration (AERMANI_CAMERA_*): which source, its device or file, and the frame rate."""

    model_config = SettingsConfigDict(env_prefix="AERMANI_CAMERA_", extra="ignore", populate_by_name=True,
                                      use_attribute_docstrings=True)

    source: str = "none"
    """Where frames come from: realsense, zed, uvc (colour only), file, mcap, or none (the service idles and
    says so in health; the simulator is the camera). `aermani up` starts this service only when it is set."""
    path: str = ""
    """file: a video file or a folder of images (optional `<name>_depth.png` 16-bit millimetres, optional
    calibration.yaml); mcap: an aermani MCAP log with camera/color (and camera/depth)."""
    device: str = ""
    """uvc: /dev/videoN or an index (default 0); realsense / zed: serial number (default the first found)."""
    calibration: str = ""
    """Calibration YAML (width, height, fx, fy, cx, cy, or a ROS camera_info file). Devices that report their
    intrinsics (realsense, zed) ignore it; file/uvc without one assume the simulator's intrinsics scaled."""
    width: int = Field(640, ge=16, le=4096)
    """Frame width, pixels (devices are asked for it; file frames are resized to it)."""
    height: int = Field(480, ge=16, le=4096)
    """Frame height, pixels."""
    fps: float = Field(15.0, gt=0, le=90)
    """Frame rate: devices are asked for it; file and mcap sources are paced to it."""
    jpeg_quality: int = Field(85, ge=10, le=100)
    """JPEG quality of camera/color."""
    loop: bool = True
    """file / mcap: start again at the end (off: the stream stops, and health says the source ended)."""
    mcap_vehicle: str = ""
    """mcap: vehicle id whose frames to replay (empty: the first vehicle with camera/color in the log)."""
    stall_s: float = Field(1.0, gt=0)
    """Health turns not ok when no frame was published for this long, seconds."""
    read_timeout_s: float = Field(2.0, gt=0)
    """A device read that takes longer than this counts as a failure (the device is re-opened)."""
    reopen_s: float = Field(2.0, gt=0)
    """First wait before re-opening an absent or failed device (doubles up to 30 s)."""
    publish_tf: bool = True
    """Publish tf base_link->camera and base_link->gripper from `mount` (AERMANI_MOUNT_*)."""
