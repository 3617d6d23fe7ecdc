"""ROS 2's Zenoh middleware (rmw_zenoh, ROS 2 Jazzy) on the wire, as its design document describes it:

- data: a topic or service is the key `<domain>/<name without leading />/<dds type>/<type hash>`, e.g.
  `0/am1/pose/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_<sha256>`; payloads are CDR (little endian, with
  the 4-byte encapsulation header); every publication and service request/reply carries an attachment:
  int64 sequence number, int64 source timestamp (ns), the 16-byte source gid behind its length;
- discovery: liveliness tokens under `@ros2_lv/<domain>/<session zid>/<node id>/...`, one per node (`NN`) and
  one per publisher (`MP`), subscriber (`MS`), service server (`SS`) or client (`SC`), with the names mangled
  (`/` -> `%`) and the endpoint's QoS encoded;
- type hashes: RIHS01, the SHA-256 of the type description (REP 2011) in rosidl's JSON form.

This module knows only the format; what aermani publishes on it is in `shared.ros2.convert` and the
`services.ros2` bridge. Type definitions come from rosbags' Jazzy typestore (the standard messages) and
`shared/ros2/aermani_msgs/` (aermani's own interfaces, also a ROS 2 package a team can build with colcon).
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from functools import cache
from hashlib import sha256
from pathlib import Path
from typing import Any

from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import TIDMAP

ADMIN_SPACE = "@ros2_lv"
INTERFACES = Path(__file__).resolve().parent  # holds aermani_msgs/ (package.xml, CMakeLists.txt, srv/)
EMPTY_MEMBER = "structure_needs_at_least_one_member"  # rosidl's member of a message without fields


@cache
def typestore() -> Any:
    """rosbags' ROS 2 Jazzy typestore with aermani's interfaces registered (one per process, built once)."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    for srv in sorted((INTERFACES / "aermani_msgs" / "srv").glob("*.srv")):
        ts.register(service_types(f"aermani_msgs/srv/{srv.stem}", srv.read_text(encoding="utf-8")))
    return ts


def service_types(srv_type: str, text: str) -> dict[str, Any]:
    """The message types of a service definition (`pkg/srv/Name` and its .srv text): Name_Request,
    Name_Response, Name_Event (what rosidl generates for service introspection) and Name itself, the type
    whose description a service's type hash is taken over (request_message, response_message, event_message)."""
    lines = text.splitlines()
    cut = next((i for i, line in enumerate(lines) if line.strip() == "---"), None)
    if cut is None:
        raise ValueError(f"{srv_type}: a .srv definition has a '---' line between request and response")
    name = srv_type.rsplit("/", 1)[1]
    out: dict[str, Any] = {}
    out.update(get_types_from_msg("\n".join(lines[:cut]), f"{srv_type}_Request"))
    out.update(get_types_from_msg("\n".join(lines[cut + 1:]), f"{srv_type}_Response"))
    out.update(get_types_from_msg(f"service_msgs/ServiceEventInfo info\n{name}_Request[<=1] request\n"
                                  f"{name}_Response[<=1] response", f"{srv_type}_Event"))
    out.update(get_types_from_msg(f"{name}_Request request_message\n{name}_Response response_message\n"
                                  f"{name}_Event event_message", srv_type))
    return out


def store_name(ros_type: str) -> str:
    """The typestore's name of a ROS 2 type: rosbags files a service's types under `pkg/srv/msg/Name`."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}/srv/msg/{name}" if kind == "srv" else ros_type


def ros_name(store_type: str) -> str:
    """Inverse of `store_name`: `pkg/srv/msg/Name` -> `pkg/srv/Name`."""
    return store_type.replace("/srv/msg/", "/srv/")


def rihs01(ros_type: str, ts: Any | None = None) -> str:
    """The RIHS01 type hash of a message or service type, as rosidl computes it: the type description with
    every referenced type, sorted by name, as compact JSON with ', ' and ': ' separators, SHA-256.

    rosbags has a `hash_rihs01` of its own; it differs from rosidl in two places that matter here: a .msg
    `char` is a uint8 to rosidl (type id 3, not 13: `service_msgs/ServiceEventInfo.client_gid`, so every
    service hash), and service types keep their `pkg/srv/Name` names."""
    ts = ts or typestore()
    described: dict[str, dict[str, Any]] = {}

    def field(name: str, desc: Any) -> dict[str, Any]:
        offset = capacity = string_capacity = 0
        nested = ""
        if desc[0] == Nodetype.ARRAY:
            offset, capacity = 48, desc[1][1]
            kind, rest = desc[1][0]
        elif desc[0] == Nodetype.SEQUENCE:
            capacity = desc[1][1]
            offset = 96 if capacity else 144
            kind, rest = desc[1][0]
        else:
            kind, rest = desc
        if kind == Nodetype.NAME:
            type_id, nested = offset + 1, ros_name(rest)
            describe(rest)
        elif rest[0] == "string" and rest[1]:
            type_id, string_capacity = offset + TIDMAP["bounded_string"], rest[1]
        else:
            type_id = offset + TIDMAP["uint8" if rest[0] == "char" else rest[0]]
        return {"name": name, "type": {"type_id": type_id, "capacity": capacity,
                                       "string_capacity": string_capacity, "nested_type_name": nested}}

    def describe(store_type: str) -> None:
        if store_type in described:
            return
        described[store_type] = {}  # placed first: a type that refers back to itself is described once
        fields = ts.fielddefs[store_type][1] or [(EMPTY_MEMBER, (Nodetype.BASE, ("uint8", 0)))]
        described[store_type].update(type_name=ros_name(store_type), fields=[field(n, d) for n, d in fields])

    top = store_name(ros_type)
    describe(top)
    referenced = sorted((d for t, d in described.items() if t != top), key=lambda d: str(d["type_name"]))
    doc = {"type_description": described[top], "referenced_type_descriptions": referenced}
    return "RIHS01_" + sha256(json.dumps(doc, separators=(", ", ": ")).encode()).hexdigest()


def dds_type(ros_type: str) -> str:
    """`sensor_msgs/msg/Image` -> `sensor_msgs::msg::dds_::Image_` (the type part of a key)."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    """A name inside a liveliness token: `/` is `%` (an empty namespace or enclave is `%` too)."""
    return name.replace("/", "%") if name else "%"


def data_key(domain: int, name: str, ros_type: str, type_hash: str) -> str:
    """The data key of a topic or service `name` (`/am1/pose`)."""
    return f"{domain}/{name.strip('/')}/{dds_type(ros_type)}/{type_hash}"


@dataclass(frozen=True)
class Qos:
    """The QoS a liveliness token announces (what `ros2 topic info -v` shows): reliability and the history
    depth; durability volatile, keep-last history, no deadline, lifespan or liveliness lease."""

    reliable: bool = True
    depth: int = 10

    def encode(self) -> str:
        """rmw_zenoh's form `<reliability>:<durability>:<history>,<depth>:<deadline>:<lifespan>:<liveliness>`,
        a field equal to rmw's default left empty (reliable, volatile, keep-last)."""
        return f"{'' if self.reliable else 2}::,{self.depth}:,:,:,,"


SENSOR_QOS = Qos(reliable=False, depth=5)  # rclcpp's SensorDataQoS: images and poses
DEFAULT_QOS = Qos()


def node_token(domain: int, zid: str, node_id: int, namespace: str, node: str) -> str:
    """A node's liveliness token (kind NN, enclave none)."""
    return f"{ADMIN_SPACE}/{domain}/{zid}/{node_id}/{node_id}/NN/%/{mangle(namespace)}/{node}"


ENDPOINT_KINDS = ("MP", "MS", "SS", "SC")  # publisher, subscriber, service server, service client


def endpoint_token(domain: int, zid: str, node_id: int, entity_id: int, kind: str, namespace: str, node: str,
                   name: str, ros_type: str, type_hash: str, qos: Qos) -> str:
    """An endpoint's liveliness token: how `ros2 topic list` and `ros2 service list` find it."""
    if kind not in ENDPOINT_KINDS:
        raise ValueError(f"endpoint kind {kind!r} is not one of {ENDPOINT_KINDS}")
    return (f"{ADMIN_SPACE}/{domain}/{zid}/{node_id}/{entity_id}/{kind}/%/{mangle(namespace)}/{node}/"
            f"{mangle(name)}/{dds_type(ros_type)}/{type_hash}/{qos.encode()}")


GID_BYTES = 16


def attachment(sequence: int, stamp_ns: int, gid: bytes) -> bytes:
    """What every publication, request and reply carries: sequence number, source time, source gid."""
    if len(gid) != GID_BYTES:
        raise ValueError(f"a gid is {GID_BYTES} bytes, not {len(gid)}")
    return struct.pack("<qqB", sequence, stamp_ns, GID_BYTES) + gid


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source time ns, gid) of an attachment; ValueError when it is not one."""
    if len(data) < 17:
        raise ValueError(f"an rmw_zenoh attachment is at least 17 bytes, got {len(data)}")
    sequence, stamp_ns, n = struct.unpack_from("<qqB", data)
    if len(data) != 17 + n:
        raise ValueError(f"attachment says its gid is {n} bytes, {len(data) - 17} follow")
    return sequence, stamp_ns, bytes(data[17:])
