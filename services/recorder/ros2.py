"""Export a recorder log as a ROS 2 bag (rosbag2, MCAP storage, CDR): what a ROS 2 team opens with `ros2 bag
play`, rosbags, mcap-ros2-support, Foxglove or PlotJuggler.

Topics and message types: `shared.ros2.convert` (the table the live ROS 2 bridge publishes too). Bag
times are the recorder's receive times. Other keys (health, heartbeats, skill statuses...) are counted, not
exported.
"""

from __future__ import annotations

import contextlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from shared.errors import AermaniError
from shared.mcaplog import iter_samples
from shared.ros2.convert import Converter, channels_for, split_key


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
    convert = Converter(typestore)
    result = Ros2Export(out)
    connections: dict[str, Any] = {}
    with contextlib.ExitStack() as stack:
        writer = None  # opened on the first sample to export: a log with none leaves no directory behind
        for s in iter_samples(log):  # streamed: a log's camera frames never sit in memory together
            split = split_key(s.key)
            if split is None or vehicle not in (None, split[0]):
                continue
            vid, suffix = split
            channels = channels_for(suffix)
            if not channels:
                result.skipped[suffix] += 1
                continue
            for channel in channels:
                try:
                    msg = convert.convert(channel, s.payload)
                except Exception:  # a malformed sample is counted, never fatal: the rest of the log still exports
                    result.skipped[f"{suffix} (undecodable)"] += 1
                    continue
                if writer is None:
                    writer = stack.enter_context(Writer(out, version=9, storage_plugin=StoragePlugin.MCAP))
                topic = channel.topic_for(vid)
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, channel.ros_type, typestore=typestore)
                writer.write(connections[topic], s.log_time_ns, typestore.serialize_cdr(msg, channel.ros_type))
                result.messages[topic] += 1
    if not result.messages:
        raise Ros2ExportError(f"{log} has no camera, tf, pose or reasoning samples"
                              + (f" of vehicle {vehicle}" if vehicle else ""))
    return result
