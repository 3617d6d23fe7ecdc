"""What the ROS 2 bridge and the rosbag2 export put in their messages, and how the bridge answers StartTask
requests it cannot carry out (a real Zenoh router and bus; the gateway is an address nobody listens on)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aermani.launcher import free_port, open_router
from services.ros2.service import START_TASK, Bridge
from services.ros2.settings import Ros2Settings
from shared.bus import Bus
from shared.messages import Vec3, VehicleState
from shared.ros2.convert import CHANNELS, Converter, ros_token
from shared.ros2.wire import attachment, parse_attachment, store_name, typestore
from shared.sensors import matrix_to_quat, pose_matrix


def test_pose_agrees_with_the_bridge_tf_and_the_odometry_twist_is_in_the_body_frame():
    """Nose up 0.3 rad, heading 0.5 rad, flying along the nose at 1 m/s: /pose's orientation is the bridge's
    tf rotation (its pitch is positive nose up), and /odom's twist is (1, 0, 0) in base_link."""
    pitch, yaw = 0.3, 0.5
    tf_rotation = pose_matrix(0, 0, 0, yaw, 0.0, -pitch)[:3, :3]  # as the bridge publishes world->base_link
    nose = tf_rotation[:, 0]
    assert nose[2] > 0.25  # nose up really points the body's x axis up
    state = VehicleState(pitch=pitch, yaw=yaw, velocity=Vec3(x=nose[0], y=nose[1], z=nose[2]))
    conv = Converter(typestore())
    odom = conv.odometry(state.model_dump_json().encode())
    q = odom.pose.pose.orientation
    expected = matrix_to_quat(tf_rotation)
    assert np.allclose([q.x, q.y, q.z, q.w], expected, atol=1e-9) or \
        np.allclose([q.x, q.y, q.z, q.w], -np.array(expected), atol=1e-9)
    lin = odom.twist.twist.linear
    assert np.allclose([lin.x, lin.y, lin.z], [1.0, 0.0, 0.0], atol=1e-9)
    assert odom.twist.covariance[35] > 1e3  # the angular rate is not measured: its variance says unknown
    pose = conv.pose(state.model_dump_json().encode()).pose.orientation
    assert (pose.x, pose.y, pose.z, pose.w) == (q.x, q.y, q.z, q.w)


@pytest.mark.parametrize(("vehicle", "token"), [("am1", "am1"), ("am-1", "am_1"), ("7x", "v7x")])
def test_vehicle_ids_become_ros2_name_tokens(vehicle, token):
    assert ros_token(vehicle) == token
    assert CHANNELS[0].topic_for(vehicle).startswith(f"/{token}/")


async def _bridge(**settings) -> tuple[Bridge, Bus, object]:
    port = free_port()
    router = open_router(port)
    bus = await Bus.open(connect=[f"tcp/127.0.0.1:{port}"])
    return Bridge(bus, Ros2Settings(gateway_url="http://127.0.0.1:9/api/v1", start_timeout_s=2.0, **settings)), \
        bus, router


def _request(command: str, t_max_s: float) -> bytes:
    ts = typestore()
    name = store_name(f"{START_TASK}_Request")
    return bytes(ts.serialize_cdr(ts.types[name](command=command, t_max_s=t_max_s), name))


def _response(reply) -> tuple[object, tuple[int, int, bytes]]:
    ts = typestore()
    return ts.deserialize_cdr(reply.data, store_name(f"{START_TASK}_Response")), parse_attachment(reply.attachment)


@pytest.mark.parametrize(("data", "why"), [
    (b"\x00\x01\x00\x00garbage", "not a CDR"),
    (b"", "1 to 8192 bytes"),
    (_request("pick up the red cup", math.inf), "t_max_s must be"),
    (_request("pick up the red cup", -5.0), "t_max_s must be"),
    (_request("pick up the red cup", 0.0), "did not answer"),  # well formed: it reaches for the gateway
], ids=["bad_cdr", "empty", "t_max_inf", "t_max_negative", "no_gateway"])
async def test_a_request_it_cannot_carry_out_gets_a_refusal_that_answers_the_caller(data, why):
    bridge, bus, router = await _bridge()
    try:
        gid = bytes(range(16))
        reply = await bridge.start_task(data, attachment(41, 123, gid))
        resp, (seq, _, echoed) = _response(reply)
        assert not resp.accepted and resp.task_id == "" and why in resp.reason, resp.reason
        assert (seq, echoed) == (41, gid)  # rclcpp matches a reply to its request by these
    finally:
        await bridge.http.aclose()
        await bus.close()
        router.close()


async def test_a_request_without_rmw_zenohs_attachment_is_an_error():
    bridge, bus, router = await _bridge()
    try:
        with pytest.raises(ValueError, match="attachment"):
            await bridge.start_task(_request("take off", 0.0), None)
        with pytest.raises(ValueError, match="attachment"):
            await bridge.start_task(_request("take off", 0.0), b'{"name": "gateway"}')
    finally:
        await bridge.http.aclose()
        await bus.close()
        router.close()
