"""rmw_zenoh's wire format as `shared.ros2.wire` writes it, checked against values a real ROS 2 Jazzy system
produces and against zenoh-ros2-sdk, an implementation the project did not write."""

from __future__ import annotations

import pytest
from rosbags.typesys import Stores, get_typestore

from shared.ros2 import wire

# Type hashes a ROS 2 Jazzy install computes (the keys in rmw_zenoh's design document: `ros2 topic pub
# /chatter std_msgs/msg/String` and the add_two_ints demo service).
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"


def test_message_hash_is_the_one_ros2_computes():
    assert wire.rihs01("std_msgs/msg/String") == STRING_HASH


def test_service_hash_is_the_one_ros2_computes():
    """A service's hash covers its request, response and event types; ServiceEventInfo's `char[16]` gid is a
    uint8 array to rosidl (rosbags' own hash_rihs01 takes it for a char and gets every service hash wrong)."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    ts.register(wire.service_types("example_interfaces/srv/AddTwoInts", "int64 a\nint64 b\n---\nint64 sum\n"))
    assert wire.rihs01("example_interfaces/srv/AddTwoInts", ts) == ADD_TWO_INTS_HASH


def test_a_service_without_request_fields_gets_rosidl_placeholder_member():
    """std_srvs/srv/Trigger's request is empty (the .srv starts with its '---'): rosidl gives such a struct one
    uint8 member, so the hash is the one of a request that declares it."""
    empty, declared = get_typestore(Stores.ROS2_JAZZY), get_typestore(Stores.ROS2_JAZZY)
    empty.register(wire.service_types("std_srvs/srv/Trigger", "---\nbool success\nstring message\n"))
    declared.register(wire.service_types("std_srvs/srv/Trigger", f"uint8 {wire.EMPTY_MEMBER}\n---\nbool success\n"
                                                                 "string message\n"))
    assert wire.rihs01("std_srvs/srv/Trigger", empty) == wire.rihs01("std_srvs/srv/Trigger", declared)


def test_every_bridged_type_hashes_as_the_sdk_computes_it(tmp_path):
    from zenoh_ros2_sdk.utils import compute_service_type_hash, get_type_hash

    from shared.ros2.convert import CHANNELS
    from tests.ros2.msgdefs import write_definitions

    types = sorted({c.ros_type for c in CHANNELS})
    root = write_definitions(tmp_path, types)
    for t in types:
        pkg, _, name = t.split("/")
        deps = {}
        for f in root.rglob("*.msg"):
            deps[f"{f.parts[-3]}/msg/{f.stem}"] = f.read_text()
        assert get_type_hash(t, msg_definition=(root / pkg / "msg" / f"{name}.msg").read_text(),
                             dependencies=deps) == wire.rihs01(t), t
    text = (wire.INTERFACES / "aermani_msgs" / "srv" / "StartTask.srv").read_text()
    request, _, response = text.partition("\n---\n")
    assert compute_service_type_hash("aermani_msgs/srv/StartTask", request, response) == \
        wire.rihs01("aermani_msgs/srv/StartTask")


def test_keys_and_tokens_match_the_sdk():
    from zenoh_ros2_sdk.entity import EndpointEntity, EntityKind, NodeEntity
    from zenoh_ros2_sdk.keyexpr import endpoint_liveliness_keyexpr, node_liveliness_keyexpr, topic_keyexpr

    h = wire.rihs01("geometry_msgs/msg/PoseStamped")
    assert wire.data_key(0, "/am1/pose", "geometry_msgs/msg/PoseStamped", h) == topic_keyexpr(
        0, "/am1/pose", "geometry_msgs::msg::dds_::PoseStamped_", h)
    node = NodeEntity(domain_id=0, session_id="abc123", node_id=0, node_name="aermani_am1", namespace="/")
    assert wire.node_token(0, "abc123", 0, "/", "aermani_am1") == node_liveliness_keyexpr(node)
    ep = EndpointEntity(node=node, entity_id=3, kind=EntityKind.PUBLISHER, name="/am1/pose",
                        dds_type_name="geometry_msgs::msg::dds_::PoseStamped_", type_hash=h,
                        qos=wire.SENSOR_QOS.encode())
    assert wire.endpoint_token(0, "abc123", 0, 3, "MP", "/", "aermani_am1", "/am1/pose",
                               "geometry_msgs/msg/PoseStamped", h, wire.SENSOR_QOS) == endpoint_liveliness_keyexpr(ep)


def test_qos_tokens_decode_as_the_sdk_reads_them():
    from zenoh_ros2_sdk.qos import QosProfile, QosReliability

    sensor = QosProfile.decode(wire.SENSOR_QOS.encode())
    assert sensor.reliability == QosReliability.BEST_EFFORT and sensor.history_depth == 5
    default = QosProfile.decode(wire.DEFAULT_QOS.encode())
    assert default.reliability == QosReliability.RELIABLE and default.history_depth == 10


def test_attachment_round_trip_and_the_sdk_reads_it():
    from zenoh_ros2_sdk.attachment import Attachment

    gid = bytes(range(16))
    data = wire.attachment(7, 123456789, gid)
    assert wire.parse_attachment(data) == (7, 123456789, gid)
    theirs = Attachment.from_bytes(data)
    assert (theirs.sequence_id, theirs.timestamp_ns, theirs.gid) == (7, 123456789, gid)
    assert Attachment(sequence_id=7, timestamp_ns=123456789, gid=gid).to_bytes() == data


@pytest.mark.parametrize("bad", [b"", b"\x00" * 16, wire.attachment(1, 2, bytes(16))[:-1],
                                 wire.attachment(1, 2, bytes(16)) + b"\x00"])
def test_a_malformed_attachment_is_refused(bad):
    with pytest.raises(ValueError):
        wire.parse_attachment(bad)


def test_names_inside_tokens_are_mangled():
    assert wire.mangle("/am1/camera/depth/image") == "%am1%camera%depth%image"
    assert wire.mangle("") == "%"
    assert wire.dds_type("aermani_msgs/srv/StartTask") == "aermani_msgs::srv::dds_::StartTask_"
    with pytest.raises(ValueError):
        wire.endpoint_token(0, "z", 0, 1, "XX", "/", "n", "/t", "std_msgs/msg/String", STRING_HASH, wire.DEFAULT_QOS)
