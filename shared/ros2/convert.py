"""aermani's bus payloads as ROS 2 messages: one table of channels, one converter per payload kind. The
recorder's `log export --ros2` writes them into a rosbag2, the ROS 2 bridge (`services.ros2`) publishes them
live over rmw_zenoh; both read this table, so a bag and a live topic carry the same message.

Topics (per vehicle `v`; REP 103 frames: the world is ENU, the camera's optical frame x right, y down, z ahead):

| aermani key            | ROS 2 topic                       | type                               |
|------------------------|-----------------------------------|------------------------------------|
| v/camera/color         | /v/camera/color/image/compressed  | sensor_msgs/msg/CompressedImage    |
| v/camera/depth         | /v/camera/depth/image             | sensor_msgs/msg/Image (16UC1, mm)  |
| v/camera/calibration   | /v/camera/color/camera_info       | sensor_msgs/msg/CameraInfo         |
| v/tf                   | /tf                               | tf2_msgs/msg/TFMessage             |
| v/autopilot/state      | /v/pose                           | geometry_msgs/msg/PoseStamped      |
| v/autopilot/state      | /v/odom                           | nav_msgs/msg/Odometry (twist in base_link) |
| v/perception/detections| /v/detections                     | std_msgs/msg/String (the JSON)     |
| v/reasoner/step        | /v/reasoner/step                  | std_msgs/msg/String (the JSON)     |
| v/reasoner/task_status | /v/reasoner/task_status           | std_msgs/msg/String (the JSON)     |

Message times are the samples' own stamps (header.stamp). The JSON strings are the messages of
docs/messages.md as the bus carries them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms

from shared.sensors import (
    BODY_FRAME,
    WORLD_FRAME,
    body_quat,
    decode_depth,
    decode_proto,
    quat_to_matrix,
    stamp_to_ns,
)

UNKNOWN_VARIANCE = 1e6  # a covariance entry for a quantity not measured (ROS's convention: very large)


@dataclass(frozen=True)
class Channel:
    """One ROS 2 topic fed by one aermani key."""

    suffix: str
    """The aermani key after `aermani/v1/<vehicle>/`."""
    topic: str
    """The ROS 2 topic, `{v}` standing for the vehicle id."""
    ros_type: str
    """The ROS 2 message type."""
    method: str
    """The `Converter` method that turns a payload into the message."""
    sensor: bool = False
    """Sensor data (best effort, shallow history, as rclcpp's SensorDataQoS)."""

    def topic_for(self, vehicle: str) -> str:
        return self.topic.format(v=ros_token(vehicle))


def ros_token(vehicle: str) -> str:
    """A vehicle id as a ROS 2 name token (letters, digits, underscores, not starting with a digit): `am-1` ->
    `am_1`, `7x` -> `v7x`."""
    token = vehicle.replace("-", "_")
    return f"v{token}" if token[:1].isdigit() else token


CHANNELS: tuple[Channel, ...] = (
    Channel("camera/color", "/{v}/camera/color/image/compressed", "sensor_msgs/msg/CompressedImage", "color",
            sensor=True),
    Channel("camera/depth", "/{v}/camera/depth/image", "sensor_msgs/msg/Image", "depth", sensor=True),
    Channel("camera/calibration", "/{v}/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", "calibration",
            sensor=True),
    Channel("tf", "/tf", "tf2_msgs/msg/TFMessage", "tf"),
    Channel("autopilot/state", "/{v}/pose", "geometry_msgs/msg/PoseStamped", "pose", sensor=True),
    Channel("autopilot/state", "/{v}/odom", "nav_msgs/msg/Odometry", "odometry", sensor=True),
    Channel("perception/detections", "/{v}/detections", "std_msgs/msg/String", "string"),
    Channel("reasoner/step", "/{v}/reasoner/step", "std_msgs/msg/String", "string"),
    Channel("reasoner/task_status", "/{v}/reasoner/task_status", "std_msgs/msg/String", "string"),
)


def channels_for(suffix: str) -> tuple[Channel, ...]:
    """The channels one aermani key feeds (none: the key has no ROS 2 counterpart)."""
    return tuple(c for c in CHANNELS if c.suffix == suffix)


def split_key(key: str) -> tuple[str, str] | None:
    """'aermani/v1/am1/camera/color' -> ('am1', 'camera/color'); None for a key outside aermani/v1/<vehicle>/."""
    parts = key.split("/")
    if len(parts) < 4 or parts[0] != "aermani":
        return None
    return parts[2], "/".join(parts[3:])


class Converter:
    """Turns bus payloads into rosbags message objects of one typestore (`typestore.serialize_cdr` makes the
    CDR bytes). Each method raises on a payload it cannot read; callers count those, never stop on them."""

    def __init__(self, typestore: Any) -> None:
        self.ts = typestore
        t = typestore.types
        self.Time, self.Header = t["builtin_interfaces/msg/Time"], t["std_msgs/msg/Header"]

    def convert(self, channel: Channel, payload: bytes) -> Any:
        return getattr(self, channel.method)(payload)

    def header(self, ns: int, frame_id: str) -> Any:
        return self.Header(stamp=self.Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame_id)

    def color(self, data: bytes) -> Any:
        pb = decode_proto(CompressedImage, data)
        return self.ts.types["sensor_msgs/msg/CompressedImage"](
            header=self.header(stamp_to_ns(pb.timestamp), pb.frame_id), format=pb.format or "jpeg",
            data=np.frombuffer(pb.data, dtype=np.uint8))

    def depth(self, data: bytes) -> Any:
        """The bus's 16-bit PNG (or an older log's RawImage) -> sensor_msgs/Image 16UC1, what ROS depth consumers
        (depth_image_proc, RViz) read without an image_transport plugin."""
        stamp, frame_id, img = decode_depth(data)
        h, w = img.shape
        return self.ts.types["sensor_msgs/msg/Image"](
            header=self.header(stamp, frame_id), height=h, width=w, encoding="16UC1", is_bigendian=0,
            step=w * 2, data=np.frombuffer(np.ascontiguousarray(img, dtype="<u2").tobytes(), dtype=np.uint8))

    def calibration(self, data: bytes) -> Any:
        pb = decode_proto(CameraCalibration, data)
        roi = self.ts.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                               do_rectify=False)
        return self.ts.types["sensor_msgs/msg/CameraInfo"](
            header=self.header(stamp_to_ns(pb.timestamp), pb.frame_id), height=pb.height, width=pb.width,
            distortion_model=pb.distortion_model or "plumb_bob", d=np.array(pb.D, dtype=np.float64),
            k=np.array(pb.K, dtype=np.float64), r=np.array(pb.R or [1, 0, 0, 0, 1, 0, 0, 0, 1], dtype=np.float64),
            p=np.array(pb.P, dtype=np.float64), binning_x=0, binning_y=0, roi=roi)

    def tf(self, data: bytes) -> Any:
        t = self.ts.types
        pb = decode_proto(FrameTransforms, data)
        out = []
        for tr in pb.transforms:
            out.append(t["geometry_msgs/msg/TransformStamped"](
                header=self.header(stamp_to_ns(tr.timestamp), tr.parent_frame_id), child_frame_id=tr.child_frame_id,
                transform=t["geometry_msgs/msg/Transform"](
                    translation=self._vector(tr.translation.x, tr.translation.y, tr.translation.z),
                    rotation=t["geometry_msgs/msg/Quaternion"](x=tr.rotation.x, y=tr.rotation.y, z=tr.rotation.z,
                                                               w=tr.rotation.w))))
        return t["tf2_msgs/msg/TFMessage"](transforms=out)

    def _vector(self, x: float, y: float, z: float) -> Any:
        return self.ts.types["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))

    def _pose(self, data: bytes) -> tuple[Any, Any, tuple[float, float, float, float]]:
        from shared.messages import VehicleState

        t = self.ts.types
        s = VehicleState.model_validate_json(data)
        q = body_quat(s.roll, s.pitch, s.yaw)
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=s.position.x, y=s.position.y, z=s.position.z),
            orientation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
        return s, pose, q

    def pose(self, data: bytes) -> Any:
        s, pose, _ = self._pose(data)
        return self.ts.types["geometry_msgs/msg/PoseStamped"](header=self.header(s.stamp_ns, WORLD_FRAME), pose=pose)

    def odometry(self, data: bytes) -> Any:
        """nav_msgs/Odometry: the pose in the world frame, the twist in base_link (REP 105: the twist is in
        the child frame). The state carries no covariance (zero: not estimated) and no angular rate (zero, with
        a huge variance on the diagonal: unknown)."""
        t = self.ts.types
        s, pose, q = self._pose(data)
        body_velocity = quat_to_matrix(q).T @ np.array([s.velocity.x, s.velocity.y, s.velocity.z])
        twist = t["geometry_msgs/msg/Twist"](linear=self._vector(*body_velocity), angular=self._vector(0, 0, 0))
        twist_cov = np.zeros(36, dtype=np.float64)
        twist_cov[[21, 28, 35]] = UNKNOWN_VARIANCE
        return t["nav_msgs/msg/Odometry"](
            header=self.header(s.stamp_ns, WORLD_FRAME), child_frame_id=BODY_FRAME,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36, dtype=np.float64)),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=twist_cov))

    def string(self, data: bytes) -> Any:
        json.loads(data)  # only well-formed JSON goes out
        return self.ts.types["std_msgs/msg/String"](data=data.decode("utf-8"))
