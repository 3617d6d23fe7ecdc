"""Issue 30's live ROS 2 line on the real stack: the simulator, autopilot bridge, perception, executor, reasoner
(rules policy), the gateway and the ROS 2 bridge as processes; a ROS 2 peer the project did not write
(zenoh-ros2-sdk, in its own process) finds the bridge's topics in the ROS graph, decodes the live camera, tf,
pose and odometry, and starts a task through the StartTask service."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from aermani.launcher import available_services
from shared.messages import VehicleState
from shared.ros2.convert import CHANNELS
from shared.ros2.wire import data_key, rihs01
from tests.gateway.conftest import TOKEN
from tests.gateway.test_process import GatewayProcess
from tests.helpers import arun, bus_for, run_stack
from tests.ros2.msgdefs import write_definitions

VEHICLE = ["sim", "autopilot_bridge", "perception", "executor", "reasoner", "ros2"]
MISSING = [s for s in VEHICLE if s not in available_services()]
pytestmark = [pytest.mark.integration, pytest.mark.slow,
              pytest.mark.skipif(bool(MISSING), reason=f"services not in this checkout: {MISSING}")]
PEER = Path(__file__).with_name("sdk_peer.py")
ENV = {"AERMANI_SIM_SPEED_FACTOR": "2", "AERMANI_SIM_FPS": "5", "AERMANI_REASONER_BACKEND": "rules",
       "AERMANI_REASONER_T_MAX_S": "240"}
TERMINAL = {"succeeded", "failed", "aborted", "timeout"}


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ros2")
    gw = GatewayProcess(tmp, endpoint="")  # its URL goes to the ROS 2 bridge, its router once the stack runs
    env = {**ENV, "AERMANI_ROS2_GATEWAY_URL": gw.url, "AERMANI_GATEWAY_TOKEN": TOKEN}
    with run_stack(VEHICLE, tmp, env=env, timeout=180) as stack:
        gw.env["AERMANI_ZENOH_CONNECT"] = stack.endpoint
        gw.start(timeout=120)
        try:
            yield stack, gw, write_definitions(tmp / "msgdefs", sorted({c.ros_type for c in CHANNELS})
                                               + ["service_msgs/msg/ServiceEventInfo"])
        finally:
            gw.stop()


def _peer(*args: str, timeout: float) -> list[dict]:
    """Run the SDK peer to its end; its JSON lines."""
    out = subprocess.run([sys.executable, str(PEER), *args], capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr[-3000:]
    return [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]


def _port(stack) -> str:
    return stack.endpoint.rsplit(":", 1)[1]


@pytest.mark.timeout(600)
def test_a_ros2_peer_sees_the_graph_and_decodes_the_live_camera_tf_pose_and_odometry(live):
    stack, _, msgdir = live
    topics = {"/am1/camera/color/image/compressed": "sensor_msgs/msg/CompressedImage",
              "/am1/camera/depth/image": "sensor_msgs/msg/Image",
              "/am1/camera/color/camera_info": "sensor_msgs/msg/CameraInfo",
              "/tf": "tf2_msgs/msg/TFMessage", "/am1/pose": "geometry_msgs/msg/PoseStamped",
              "/am1/odom": "nav_msgs/msg/Odometry"}
    graph = _peer("graph", _port(stack), str(msgdir), timeout=120)[-1]
    assert {t: ty for t, ty in graph["topics"].items() if t in topics} == topics, graph  # `ros2 topic list -t`
    assert graph["services"].get("/am1/start_task") == "aermani_msgs/srv/StartTask", graph
    got = _peer("listen", _port(stack), str(msgdir), "2", *(f"{t}={ty}" for t, ty in topics.items()), timeout=240)
    by_topic: dict[str, list[dict]] = {}
    for line in got:
        if "topic" in line:
            by_topic.setdefault(line["topic"], []).append(line["msg"])
    assert set(by_topic) == set(topics), f"nothing decoded on {set(topics) - set(by_topic)}"

    color = by_topic["/am1/camera/color/image/compressed"][0]
    assert color["format"] == "jpeg" and color["data"]["head"].startswith("ffd8")  # a JPEG's start of image
    depth = by_topic["/am1/camera/depth/image"][0]
    assert depth["encoding"] == "16UC1" and depth["step"] == depth["width"] * 2
    assert depth["data"]["len"] == depth["height"] * depth["step"] > 0
    info = by_topic["/am1/camera/color/camera_info"][0]
    assert (info["width"], info["height"]) == (depth["width"], depth["height"]) and info["k"]["values"][0] > 0
    frames = {(t["header"]["frame_id"], t["child_frame_id"]) for m in by_topic["/tf"] for t in m["transforms"]}
    assert {("world", "base_link"), ("base_link", "camera"), ("base_link", "gripper")} <= frames, frames

    async def state() -> VehicleState:
        async with bus_for(stack) as bus:
            from shared.keys import Keys

            return await bus.subscribe(Keys("am1").autopilot_state).recv(timeout=10)

    truth = arun(state(), 30)
    pose = by_topic["/am1/pose"][-1]["pose"]["position"]
    assert np.allclose([pose["x"], pose["y"], pose["z"]], [truth.position.x, truth.position.y, truth.position.z],
                       atol=0.05), (pose, truth.position)  # the vehicle sits on the ground: the same place
    odom = by_topic["/am1/odom"][-1]
    assert odom["header"]["frame_id"] == "world" and odom["child_frame_id"] == "base_link"


@pytest.mark.timeout(600)
def test_a_ros2_peer_starts_a_task_and_a_second_one_is_refused_with_the_reason(live):
    stack, gw, msgdir = live
    auth = {"Authorization": f"Bearer {TOKEN}"}
    command = "Pick up the red cup and place it on the table."
    reply = _peer("call", _port(stack), str(msgdir), "/am1/start_task", "aermani_msgs/srv/StartTask", command,
                  timeout=120)[-1]["reply"]
    assert reply is not None and reply["accepted"] is True and reply["task_id"], reply
    tid = reply["task_id"]
    with httpx.Client(base_url=gw.url, headers=auth, timeout=30) as c:
        task = c.get(f"/tasks/{tid}").json()
        assert task["command"] == command and task["vehicle_id"] == "am1"  # the gateway's task, stored

        assert c.get(f"/tasks/{tid}").json()["state"] not in TERMINAL  # a pick-and-place takes minutes
        second = _peer("call", _port(stack), str(msgdir), "/am1/start_task", "aermani_msgs/srv/StartTask",
                       command, timeout=120)[-1]["reply"]
        if second["accepted"]:  # the first task ended after all: leave nothing flying behind the test
            c.post(f"/tasks/{second['task_id']}/abort", json={"reason": "ROS 2 test: unexpected second task"})
        assert second["accepted"] is False and second["task_id"] == "" and "409" in second["reason"], second

        assert c.post(f"/tasks/{tid}/abort", json={"reason": "ROS 2 test done"}).status_code == 202
        deadline = time.monotonic() + 120
        while c.get(f"/tasks/{tid}").json()["state"] not in TERMINAL:
            assert time.monotonic() < deadline, "the task did not end after its abort"
            time.sleep(0.5)
        assert c.get(f"/tasks/{tid}").json()["state"] == "aborted"


@pytest.mark.timeout(300)
def test_a_malformed_start_task_request_gets_an_error_and_starts_nothing(live):
    stack, gw, _ = live
    key = data_key(0, "/am1/start_task", "aermani_msgs/srv/StartTask", rihs01("aermani_msgs/srv/StartTask"))
    auth = {"Authorization": f"Bearer {TOKEN}"}
    with httpx.Client(base_url=gw.url, headers=auth, timeout=30) as c:
        before = c.get("/tasks").json()["total"]

        async def ask() -> list[tuple[bool, bytes]]:
            async with bus_for(stack) as bus:  # an aermani query: its attachment is the bus's caller, not rmw_zenoh's
                return await bus.query_all(key, b"\x00\x01\x00\x00garbage", timeout=10)

        replies = arun(ask(), 30)
        assert replies and not replies[0][0] and b"attachment" in replies[0][1], replies
        assert c.get("/tasks").json()["total"] == before
