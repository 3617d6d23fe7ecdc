"""Export a recorder log as a ROS 2 bag (rosbag2, MCAP storage, CDR): what a ROS 2 team opens with `ros2 bag
play`, rosbags, mcap-ros2-support, Foxglove or PlotJuggler.

Topics (per vehicle `v`; REP 103 frames: the world is ENU, the camera's optical frame x right, y down, z ahead):

| aermani key          | ROS 2 topic                       | type                               |
|----------------------|-----------------------------------|------------------------------------|
| v/camera/color       | /v/camera/color/image/compressed  | sensor_msgs/msg/CompressedImage    |
| v/camera/depth       | /v/camera/depth/image             | sensor_msgs/msg/Image (16UC1, mm)  |
| v/camera/calibration | /v/camera/color/camera_info       | sensor_msgs/msg/CameraInfo         |
| v/tf                 | /tf                               | tf2_msgs/msg/TFMessage             |
| v/autopilot/state    | /v/pose                           | geometry_msgs/msg/PoseStamped      |
| v/reasoner/step      | /v/reasoner/step                  | std_msgs/msg/String (the JSON)     |
| v/reasoner/task_status | /v/reasoner/task_status         | std_msgs/msg/String (the JSON)     |

Message times are the samples' own stamps where they carry one (header.stamp), bag times the recorder's receive
times. Other keys (health, heartbeats, skill statuses...) are counted, not exported.
"""

from __future__ import annotations

import contextlib
import json
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from shared.errors import AermaniError
from shared.mcaplog import iter_samples
from shared.sensors import (
    decode_proto,
    quat_from_rpy,
    stamp_to_ns,
)


class Ros2ExportError(AermaniError):
    """The log cannot be exported (rosbags missing, the output exists, nothing to export)."""


@dataclass
class Ros2Export:
    """What an export wrote."""

    path: Path
    messages: Counter[str] = field(default_factory=Counter)
    """ROS 2 topic -> messages written."""
    skipped: Counter[str] = field(default_factory=Counter)
    """aermani key suffix -> samples not exported (no ROS 2 mapping, or undecodable)."""

    def render(self) -> str:
        lines = [f"wrote {sum(self.messages.values())} messages on {len(self.messages)} topics to {self.path}"]
        lines += [f"  {topic:<42} {n:>7}" for topic, n in sorted(self.messages.items())]
        if self.skipped:
            lines.append("not exported: " + ", ".join(f"{k} ({n})" for k, n in sorted(self.skipped.items())))
        return "\n".join(lines)


# aermani key suffix -> (ROS 2 topic template, ROS 2 type, the _Builder method that converts a payload)
TOPICS: dict[str, tuple[str, str, str]] = {
    "camera/color": ("/{v}/camera/color/image/compressed", "sensor_msgs/msg/CompressedImage", "color"),
    "camera/depth": ("/{v}/camera/depth/image", "sensor_msgs/msg/Image", "depth"),
    "camera/calibration": ("/{v}/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", "calibration"),
    "tf": ("/tf", "tf2_msgs/msg/TFMessage", "tf"),
    "autopilot/state": ("/{v}/pose", "geometry_msgs/msg/PoseStamped", "pose"),
    "reasoner/step": ("/{v}/reasoner/step", "std_msgs/msg/String", "string"),
    "reasoner/task_status": ("/{v}/reasoner/task_status", "std_msgs/msg/String", "string"),
}


def _split(key: str) -> tuple[str, str] | None:
    """'aermani/v1/am1/camera/color' -> ('am1', 'camera/color')."""
    parts = key.split("/")
    if len(parts) < 4 or parts[0] != "aermani":
        return None
    return parts[2], "/".join(parts[3:])


class _Builder:
    """Turns recorded payloads into rosbags message objects of one typestore."""

    def __init__(self, typestore: Any) -> None:
        self.ts = typestore
        t = typestore.types
        self.Time, self.Header = t["builtin_interfaces/msg/Time"], t["std_msgs/msg/Header"]

    def header(self, ns: int, frame_id: str) -> Any:
        return self.Header(stamp=self.Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame_id)

    def color(self, data: bytes) -> Any:
        import numpy as np

        pb = decode_proto(CompressedImage, data)
        return self.ts.types["sensor_msgs/msg/CompressedImage"](
            header=self.header(stamp_to_ns(pb.timestamp), pb.frame_id), format=pb.format or "jpeg",
            data=np.frombuffer(pb.data, dtype=np.uint8))

    def depth(self, data: bytes) -> Any:
        import numpy as np

        pb = decode_proto(RawImage, data)
        return self.ts.types["sensor_msgs/msg/Image"](
            header=self.header(stamp_to_ns(pb.timestamp), pb.frame_id), height=pb.height, width=pb.width,
            encoding=pb.encoding, is_bigendian=0, step=pb.step, data=np.frombuffer(pb.data, dtype=np.uint8))

    def calibration(self, data: bytes) -> Any:
        import numpy as np

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
                    translation=t["geometry_msgs/msg/Vector3"](x=tr.translation.x, y=tr.translation.y,
                                                               z=tr.translation.z),
                    rotation=t["geometry_msgs/msg/Quaternion"](x=tr.rotation.x, y=tr.rotation.y, z=tr.rotation.z,
                                                               w=tr.rotation.w))))
        return t["tf2_msgs/msg/TFMessage"](transforms=out)

    def pose(self, data: bytes) -> Any:
        from shared.messages import VehicleState

        t = self.ts.types
        s = VehicleState.model_validate_json(data)
        qx, qy, qz, qw = quat_from_rpy(s.roll, s.pitch, s.yaw)
        return t["geometry_msgs/msg/PoseStamped"](
            header=self.header(s.stamp_ns, "world"),
            pose=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=s.position.x, y=s.position.y, z=s.position.z),
                orientation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)))

    def string(self, data: bytes) -> Any:
        json.loads(data)  # only well-formed JSON goes into the bag
        return self.ts.types["std_msgs/msg/String"](data=data.decode("utf-8"))


def export_ros2(log: str | Path, out: str | Path, vehicle: str | None = None) -> Ros2Export:
    """Write the log's camera, tf, pose and reasoning samples as a rosbag2 directory `out` (MCAP storage)."""
    try:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:  # pragma: no cover - rosbags is a dependency
        raise Ros2ExportError(f"the ROS 2 export needs rosbags (pip install rosbags): {exc}") from exc
    out = Path(out)
    if out.exists():
        raise Ros2ExportError(f"{out} exists: a rosbag2 export writes a new directory")
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    build = _Builder(typestore)
    result = Ros2Export(out)
    connections: dict[str, Any] = {}
    with contextlib.ExitStack() as stack:
        writer = None  # opened on the first sample to export: a log with none leaves no directory behind
        for s in iter_samples(log):  # streamed: a log's camera frames never sit in memory together
            split = _split(s.key)
            if split is None or vehicle not in (None, split[0]):
                continue
            vid, suffix = split
            if suffix not in TOPICS:
                result.skipped[suffix] += 1
                continue
            template, msgtype, method = TOPICS[suffix]
            topic = template.format(v=vid)
            try:
                msg = getattr(build, method)(s.payload)
            except Exception:  # a malformed sample is counted, never fatal: the rest of the log still exports
                result.skipped[f"{suffix} (undecodable)"] += 1
                continue
            if writer is None:
                writer = stack.enter_context(Writer(out, version=9, storage_plugin=StoragePlugin.MCAP))
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
            writer.write(connections[topic], s.log_time_ns, typestore.serialize_cdr(msg, msgtype))
            result.messages[topic] += 1
    if not result.messages:
        raise Ros2ExportError(f"{log} has no camera, tf, pose or reasoning samples"
                              + (f" of vehicle {vehicle}" if vehicle else ""))
    return result
