"""The drone side without the simulator's camera: the camera service (file source) + perception (colour
segmenter) + the autopilot bridge on the simulator's MAVLink only (AERMANI_SIM_CAMERA=0, the bridge publishes
world->base_link from MAVLink as on a real PX4). Frames reach perception through the camera service and a
localization is answered from them.

The frames are what a camera on that vehicle would see: the test flies the vehicle up over MAVLink, reads
its pose from the bridge, renders the simulator's layout from that pose to PNG + 16-bit depth PNG +
calibration YAML, and only then starts the camera service on that folder. The estimate is checked against
the simulator's ground truth, which only agrees if pixels, depth, calibration, mount and the bridge's pose
were all used correctly."""

from __future__ import annotations

import asyncio
import math
import time

import cv2
import numpy as np
import pytest

from aermani.launcher import Stack
from services.sim.scenarios import generate
from shared.bus import Latest
from shared.frames import DEFAULT_INTRINSICS
from shared.keys import Keys
from shared.messages import (
    ArmCommand,
    JudgeRequest,
    LocalizeRequest,
    Scenario,
    TakeoffCommand,
)
from shared.sensors import CompressedImage, decode_proto, stamp_to_ns
from tests.helpers import bus_for, run_stack, wait_until

pytestmark = [pytest.mark.integration, pytest.mark.slow]

K = Keys("am1")
SEED, TARGET = 3, "red cup"


def write_view(folder, world, x: float, y: float, z: float, yaw: float) -> None:
    """The view as a clean depth camera sees it (`ideal` buffers): the check is of the plumbing (pixels, depth,
    calibration, mount, the bridge's pose), and the target is ~3 m away, where a real stereo camera's unit bias
    alone is 5-7 cm (services/sim/README.md, Realism), more than the 5 cm a plumbing error must show within."""
    from services.sim.render import Renderer, snapshot_at

    r = Renderer(realism="ideal")
    try:
        f = r.render(snapshot_at(world, np.array([x, y, z]), yaw))
    finally:
        r.close()
    folder.mkdir(parents=True)
    cv2.imwrite(str(folder / "0000.png"), cv2.cvtColor(f.rgb, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(folder / "0000_depth.png"), f.depth_mm)
    i = DEFAULT_INTRINSICS
    (folder / "calibration.yaml").write_text(
        f"width: {i.width}\nheight: {i.height}\nfx: {i.fx}\nfy: {i.fy}\ncx: {i.cx}\ncy: {i.cy}\n")


async def test_camera_service_feeds_perception_with_the_bridge_on_sim_mavlink(tmp_path):
    # The file source replays one frame rendered from the pose read at one moment, and perception places it with
    # the pose of the moment it is published: the vehicle must hold that pose to the millimetre for the frame to
    # stay true, which the multirotor's centimetres of hover wander do not (the check is of the plumbing): the
    # kinematic body.
    env = {"AERMANI_SIM_DYNAMICS": "kinematic", "AERMANI_SIM_CAMERA": "false",
           "AERMANI_AUTOPILOT_BRIDGE_PUBLISH_TF": "true",
           "AERMANI_PERCEPTION_SEGMENTER": "color", "AERMANI_SIM_SEED": str(SEED),
           "AERMANI_SIM_TARGET_OBJECT": TARGET, "AERMANI_SIM_SPEED_FACTOR": "3"}
    with run_stack(["sim", "autopilot_bridge", "perception"], tmp_path, env=env, timeout=180) as stack:
        await _fly_render_localize(stack, tmp_path)


async def _fly_render_localize(stack, tmp_path) -> None:
    async with bus_for(stack) as bus:
        latest = Latest(bus.subscribe(K.autopilot_state))
        seg = bus.subscribe(K.camera_segmentation)
        colors = bus.subscribe(K.camera_color, maxsize=500)
        task = asyncio.create_task(latest.run())
        try:
            await wait_until(lambda: latest.value is not None and latest.value.link_ok, 60, what="bridge link")
            # The simulator's camera is off: perception has nothing yet, and says so.
            est = await bus.query(K.localize_object, LocalizeRequest(query=TARGET), timeout=20)
            assert not est.found and est.reason == "no_frame", est
            assert (await bus.query(K.autopilot_command, ArmCommand(), timeout=60)).ok
            res = await bus.query(K.autopilot_command, TakeoffCommand(altitude=1.5), timeout=120)
            assert res.ok, res.message

            def settled() -> bool:
                s = latest.value
                return abs(s.position.z - 1.5) < 0.05 and math.hypot(s.velocity.x, s.velocity.y, s.velocity.z) < 0.03

            await wait_until(settled, 90, what=f"hover: {latest.value}")
            await asyncio.sleep(0.5)
            s = latest.value
            world, _, _ = generate(Scenario(seed=SEED, target_object=TARGET))  # the layout the sim flies in
            write_view(tmp_path / "frames", world, s.position.x, s.position.y, s.position.z, s.yaw)

            camera = Stack(["camera"], port=stack.port, router=False, log_dir=tmp_path / "logs-camera",
                           env={"AERMANI_CAMERA_SOURCE": "file", "AERMANI_CAMERA_PATH": str(tmp_path / "frames"),
                                "AERMANI_CAMERA_FPS": "5"})
            camera.start(wait=False)
            try:
                await wait_until(lambda: ("am1", "camera") in stack.alive(), 60, what="camera alive")
                est = None
                deadline = time.monotonic() + 60
                while time.monotonic() < deadline:
                    est = await bus.query(K.localize_object, LocalizeRequest(query=TARGET, max_frame_age_s=2.0),
                                          timeout=20)
                    if est.reason not in ("no_frame", "stale_frame"):
                        break
                    await asyncio.sleep(0.3)
                stamps = set()
                while (c := colors.recv_nowait()) is not None:
                    stamps.add(stamp_to_ns(decode_proto(CompressedImage, c).timestamp))
                health = await bus.subscribe(K.health("camera")).recv(timeout=10)
            finally:
                await asyncio.to_thread(camera.stop)
            assert est is not None and est.found, (est, camera.find("camera").tail(20))
            assert est.frame_stamp_ns in stamps, "the estimate comes from a frame the camera service published"
            judge = await bus.query(K.sim_judge, JudgeRequest(op="world"), timeout=20)
            truth = next(o for o in judge.objects if o.name == TARGET)
            p = est.pose.position
            assert math.hypot(p.x - truth.position.x, p.y - truth.position.y) <= 0.05, (truth, est)
            assert abs(est.top_z - truth.top_z) <= 0.05, (truth, est)
            assert health.ok and health.details["depth"] is True and health.details["frames"] > 0, health
            assert seg.recv_nowait() is None, "the simulator published camera frames although its camera is off"
        finally:
            task.cancel()
