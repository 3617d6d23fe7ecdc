"""The camera service as a real process over real Zenoh: file and mcap sources publish aligned, stamped
frames, calibration and the mounts; it conforms to its declarations; a stalled or absent camera shows in
health and in `aermani health`; a colour-only camera makes perception say that 3D localization needs depth."""

from __future__ import annotations

import asyncio
import contextlib
import os
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

from shared.conformance import check_service
from shared.frames import Mount
from shared.keys import Keys
from shared.messages import LocalizeRequest
from shared.sensors import (
    CompressedImage,
    decode_proto,
    parse_calibration,
    parse_color,
    parse_depth,
    parse_transforms,
    stamp_to_ns,
)
from tests.camera.frames import CAL, frame_pixels, write_folder, write_log
from tests.helpers import bus_for, run_stack

pytestmark = pytest.mark.integration

K = Keys("am1")


def camera_env(**kw: object) -> dict[str, str]:
    return {f"AERMANI_CAMERA_{k.upper()}": str(v) for k, v in kw.items()}


async def pairs(bus, n: int, timeout: float = 30.0) -> tuple[list[tuple[int, bytes, np.ndarray]], list[bytes], list]:
    """n colour/depth pairs with the same stamp (and what else came: calibrations, tf payloads)."""
    color, depth = bus.subscribe(K.camera_color), bus.subscribe(K.camera_depth)
    cal, tf = bus.subscribe(K.camera_calibration), bus.subscribe(K.tf)
    colors: dict[int, bytes] = {}
    depths: dict[int, np.ndarray] = {}
    out: list[tuple[int, bytes, np.ndarray]] = []
    cals: list[bytes] = []
    deadline = time.monotonic() + timeout
    while len(out) < n or not cals:  # calibration comes at 1 Hz
        assert time.monotonic() < deadline, f"only {len(out)} pairs (colours {len(colors)}, depths {len(depths)})"
        with contextlib.suppress(TimeoutError):
            c = await color.recv(timeout=0.2)
            colors[stamp_to_ns(decode_proto(CompressedImage, c).timestamp)] = c
        while (d := depth.recv_nowait()) is not None:
            stamp, img = parse_depth(d)
            depths[stamp] = img
        for stamp in sorted(set(colors) & set(depths)):
            out.append((stamp, colors.pop(stamp), depths.pop(stamp)))
        while (x := cal.recv_nowait()) is not None:
            cals.append(x)
    tfs = []
    while (x := tf.recv_nowait()) is not None:
        tfs.append(x)
    for s in (color, depth, cal, tf):
        s.close()
    return out, cals, tfs


def frame_index(depth: np.ndarray) -> int:
    return (int(depth[0, 0]) - 1000) // 100


async def test_file_source_publishes_aligned_frames_calibration_and_mounts(tmp_path):
    folder = write_folder(tmp_path / "frames", n=4)
    env = camera_env(source="file", path=folder, width=160, height=120, fps=10)
    with run_stack(["camera"], tmp_path, env=env) as stack:
        async with bus_for(stack) as bus:
            got, cals, tfs = await pairs(bus, 8)
    stamps = [s for s, _, _ in got]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    assert all(abs(s - time.time_ns()) < 600e9 for s in stamps), "stamps are ns since the epoch"
    seen = [frame_index(d) for _, _, d in got]
    assert set(seen) == {0, 1, 2, 3} and seen.index(0) < len(seen) - 1 - seen[::-1].index(0), f"loops: {seen}"
    for _, c, d in got:
        i = frame_index(d)
        assert np.array_equal(d, cv2.resize(frame_pixels(i)[1], (160, 120), interpolation=cv2.INTER_NEAREST))
        rgb = parse_color(c)[1]
        assert rgb.shape == (120, 160, 3)
        x = (40 + 20 * i) // 2
        assert rgb[55:65, x + 5:x + 15, 0].mean() > 180 and rgb[55:65, x + 5:x + 15, 1].mean() < 80, "red square"
    cal = parse_calibration(cals[-1]) if cals else None
    assert cal is not None and (cal.width, cal.height, cal.fx, cal.cx) == (160, 120, CAL.fx / 2, 79.5)
    mounts = parse_transforms(tfs[-1])
    m = Mount(_env_file=None)
    assert np.allclose(mounts[("base_link", "camera")][1], m.base_to_camera(), atol=1e-6)
    assert np.allclose(mounts[("base_link", "gripper")][1], m.base_to_gripper(), atol=1e-6)
    tf_stamps = {parse_transforms(t)[("base_link", "camera")][0] for t in tfs}
    assert tf_stamps & set(stamps), "tf is published with the stamp of its frame"


async def test_mount_comes_from_the_one_setting(tmp_path):
    folder = write_folder(tmp_path / "frames", n=1)
    env = {**camera_env(source="file", path=folder, width=320, height=240, fps=5),
           "AERMANI_MOUNT_CAMERA_OFFSET": "0.2,0.01,-0.08", "AERMANI_MOUNT_CAMERA_PITCH_DEG": "50",
           "AERMANI_MOUNT_GRIPPER_OFFSET": "0.05,0,-0.3"}
    with run_stack(["camera"], tmp_path, env=env) as stack:
        async with bus_for(stack) as bus:
            sub = bus.subscribe(K.tf)
            tf = parse_transforms(await sub.recv(timeout=20))
    cam = tf[("base_link", "camera")][1]
    assert np.allclose(cam[:3, 3], (0.2, 0.01, -0.08)) and np.allclose(tf[("base_link", "gripper")][1][:3, 3],
                                                                       (0.05, 0.0, -0.3))
    # The optical axis (z) points 50 degrees below the horizon.
    assert np.isclose(np.degrees(np.arcsin(-cam[2, 2])), 50.0, atol=1e-4)


async def test_mcap_source_republishes_recorded_frames_with_fresh_stamps(tmp_path):
    log = tmp_path / "flight.mcap"
    recorded = write_log(log, n=5, vehicle="am7")
    env = camera_env(source="mcap", path=log, fps=10)
    with run_stack(["camera"], tmp_path, env=env) as stack:
        async with bus_for(stack) as bus:
            got, cals, _ = await pairs(bus, 6)
    from shared.mcaplog import iter_samples

    jpegs = {bytes(decode_proto(CompressedImage, s.payload).data)
             for s in iter_samples(log, "aermani/v1/am7/camera/color")}
    for stamp, c, d in got:
        assert stamp not in recorded, "a replayed frame gets a new stamp (bus convention: now)"
        assert bytes(decode_proto(CompressedImage, c).data) in jpegs, "JPEG bytes pass through verbatim"
        assert np.array_equal(d, frame_pixels(frame_index(d))[1])
    assert parse_calibration(cals[-1]) == CAL


async def test_camera_service_conforms_to_its_declarations(tmp_path):
    folder = write_folder(tmp_path / "frames", n=3)
    colour_only = write_folder(tmp_path / "video", n=3, depth=False)
    env = camera_env(source="file", path=folder, width=320, height=240, fps=10)
    with run_stack(["camera"], tmp_path, env=env) as stack:
        async with bus_for(stack) as bus:
            report = await check_service(bus, "camera", "am1", expect_health=True, timeout=5.0)
    report.raise_for_failures()
    checked = {f.key for f in report.findings}
    assert checked >= {K.camera_color.key, K.camera_depth.key, K.camera_calibration.key, K.tf.key,
                       K.health("camera").key, K.alive("camera").key}, checked

    # A colour-only camera fails the same check on camera/depth unless the deployment says it has no depth.
    env = camera_env(source="file", path=colour_only, width=320, height=240, fps=10)
    with run_stack(["camera"], tmp_path / "b", env=env) as stack:
        async with bus_for(stack) as bus:
            strict = await check_service(bus, "camera", "am1", timeout=3.0)
            lenient = await check_service(bus, "camera", "am1", timeout=3.0, skip=("camera/depth",))
    assert not strict.ok and any(not f.ok and f.key.endswith("camera/depth") for f in strict.findings), strict.summary()
    lenient.raise_for_failures()


def _cli_health(endpoint: str) -> str:
    env = {**os.environ, "COLUMNS": "250", "PYTHONPATH": os.getcwd()}
    out = subprocess.run([sys.executable, "-m", "aermani.cli", "health", "--connect", endpoint, "--timeout", "2.5"],
                         capture_output=True, text=True, env=env, timeout=60)
    return out.stdout + out.stderr


async def test_a_stalled_camera_shows_in_health_and_in_aermani_health(tmp_path):
    folder = write_folder(tmp_path / "frames", n=3)
    env = camera_env(source="file", path=folder, width=320, height=240, fps=5, loop="false", stall_s=0.5)
    with run_stack(["camera"], tmp_path, env=env) as stack:
        async with bus_for(stack) as bus:
            sub = bus.subscribe(K.health("camera"))
            seen = []
            while not seen or seen[-1].ok or seen[-1].details.get("frames", 0) < 3:
                seen.append(await sub.recv(timeout=10))
        text = await asyncio.to_thread(_cli_health, stack.endpoint)
    last = seen[-1]
    assert not last.ok and last.details["frames"] == 3 and last.details["frame_age_s"] > 0.5
    assert "camera stalled" in last.message and "reached its end after 3 frames (loop off)" in last.message
    assert "camera" in text and "camera stalled" in text, text


async def test_an_absent_camera_shows_in_health(tmp_path):
    env = camera_env(source="uvc", device="/dev/video-aermani-absent", reopen_s=0.5)
    with run_stack(["camera"], tmp_path, env=env) as stack:
        async with bus_for(stack) as bus:
            sub = bus.subscribe(K.health("camera"))
            h = await sub.recv(timeout=10)
            for _ in range(5):  # the very first report may precede the first open attempt
                if h.message.startswith("camera absent"):
                    break
                h = await sub.recv(timeout=10)
    assert not h.ok and h.message.startswith("camera absent: no camera at /dev/video-aermani-absent"), h
    assert h.details["opened"] is False and h.details["frames"] == 0


async def test_an_absent_realsense_is_absent_not_hung(tmp_path):
    """Under the supervisor, with the real SDK and no device: health says "camera absent: no RealSense
    connected" within seconds, the log says it at every try, and the service is never killed as hung (an open
    that went straight to the SDK's pipeline blocked the process for 15 s per try)."""
    pytest.importorskip("pyrealsense2", reason="pyrealsense2 (pip install -e .[realsense]) is not installed")
    import pyrealsense2 as rs

    if len(rs.context().query_devices()):
        pytest.skip("a RealSense is connected to this machine")
    with run_stack(["camera"], tmp_path, env=camera_env(source="realsense", reopen_s=0.5), supervise=True) as stack:
        async with bus_for(stack) as bus:
            sub = bus.subscribe(K.health("camera"))
            h = await sub.recv(timeout=10)
            for _ in range(5):
                if h.message.startswith("camera absent"):
                    break
                h = await sub.recv(timeout=10)
            await asyncio.sleep(6.0)  # past the supervisor's 4 s hung limit and several retries
            last = await sub.recv(timeout=5)
        log = stack.find("camera").log_path.read_text()
        events = list(stack.events)
    assert not h.ok and h.message.startswith("camera absent: no RealSense connected"), h
    assert last.message.startswith("camera absent: no RealSense connected"), last
    assert log.count("camera absent: no RealSense connected") >= 3, log[-2000:]
    assert not [e for e in events if "hung" in e or "exited" in e or "restart" in e], events


async def test_colour_only_camera_makes_perception_say_3d_needs_depth(tmp_path):
    folder = write_folder(tmp_path / "video", n=3, depth=False)
    env = {**camera_env(source="file", path=folder, width=320, height=240, fps=10),
           "AERMANI_PERCEPTION_SEGMENTER": "color"}
    with run_stack(["camera", "perception"], tmp_path, env=env) as stack:
        async with bus_for(stack) as bus:
            health = bus.subscribe(K.health("perception"))
            h = await health.recv(timeout=10)
            while h.details.get("color", 0) == 0:  # a colour frame is in: the answer is about depth, not frames
                h = await health.recv(timeout=10)
            est = await bus.query(K.localize_object, LocalizeRequest(query="red cup"), timeout=20)
    assert not est.found and est.reason == "no_frame"
    assert "3D localization needs a depth image" in est.message and "uvc" in est.message, est.message
    assert not h.ok and "needs a depth camera" in h.message, h


async def test_idle_camera_says_it_publishes_nothing(tmp_path):
    with run_stack(["camera"], tmp_path, env=camera_env(source="none")) as stack:
        async with bus_for(stack) as bus:
            h = await bus.subscribe(K.health("camera")).recv(timeout=10)
            color = bus.subscribe(K.camera_color)
            await asyncio.sleep(1.0)
            frame = color.recv_nowait()
    assert h.ok and "AERMANI_CAMERA_SOURCE=none" in h.message and frame is None


@pytest.mark.parametrize("case", ["unknown source", "calibration for another size", "empty log"])
def test_a_misconfigured_camera_exits_with_the_reason(case, router, tmp_path):
    """Configuration errors end the process (non-zero, the reason in its log) instead of idling as 'absent'."""
    folder = write_folder(tmp_path / "frames", n=1)
    if case == "unknown source":
        cfg, says = camera_env(source="kinect"), "unknown camera source 'kinect'"
    elif case == "calibration for another size":
        (folder / "calibration.yaml").write_text("width: 640\nheight: 480\nfx: 350\nfy: 350\ncx: 319.5\ncy: 239.5\n")
        cfg, says = camera_env(source="file", path=folder), "is for 640x480 but the frames are 320x240"
    else:
        write_log(tmp_path / "x.mcap", n=2, vehicle="am7")
        cfg, says = camera_env(source="mcap", path=tmp_path / "x.mcap", mcap_vehicle="am9"), "no camera/color samples"
    env = {**os.environ, **cfg, "AERMANI_ZENOH_CONNECT": router, "PYTHONPATH": os.getcwd()}
    out = subprocess.run([sys.executable, "-m", "services.camera"], env=env, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode != 0 and says in out.stderr + out.stdout, out.stderr[-2000:]
