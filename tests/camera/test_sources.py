"""Camera sources without a bus: configuration errors name the fix, calibration files, folder and log reading."""

from __future__ import annotations

import numpy as np
import pytest

from services.camera.settings import CameraSettings
from services.camera.sources import make_source
from services.camera.sources.base import load_calibration
from shared.errors import CameraError
from tests.camera.frames import CAL, frame_pixels, write_folder, write_log


def settings(**kw) -> CameraSettings:
    return CameraSettings(_env_file=None, **kw)


def test_unknown_source_names_the_choices():
    with pytest.raises(CameraError, match="unknown camera source 'kinect'.*file.*mcap.*realsense.*uvc.*zed"):
        make_source(settings(source="kinect"))


def test_missing_sdks_say_what_to_install():
    pytest.importorskip("numpy")
    try:
        import pyrealsense2  # noqa: F401
    except ImportError:
        with pytest.raises(CameraError, match="pip install pyrealsense2"):
            make_source(settings(source="realsense"))
    try:
        import pyzed.sl  # noqa: F401
    except ImportError:
        with pytest.raises(CameraError, match="ZED SDK.*pyzed"):
            make_source(settings(source="zed"))


def test_realsense_without_a_device_says_so_at_once():
    """With the real SDK and no device: the open asks the SDK's device list first and fails in milliseconds,
    saying "no RealSense connected" (the SDK's own pipeline.start waits 15 s with the GIL held)."""
    import time

    pytest.importorskip("pyrealsense2", reason="pyrealsense2 (pip install -e .[realsense]) is not installed")
    import pyrealsense2 as rs

    if len(rs.context().query_devices()):
        pytest.skip("a RealSense is connected to this machine")
    for kw, says in (({}, "no RealSense connected"), ({"device": "123456789"}, "no RealSense connected")):
        source = make_source(settings(source="realsense", **kw))
        t0 = time.monotonic()
        with pytest.raises(CameraError, match=says):
            source.open()
        assert time.monotonic() - t0 < 1.0


def test_file_source_refuses_bad_input(tmp_path):
    with pytest.raises(CameraError, match="needs AERMANI_CAMERA_PATH"):
        make_source(settings(source="file"))
    with pytest.raises(CameraError, match="does not exist"):
        make_source(settings(source="file", path=str(tmp_path / "nope")))
    (tmp_path / "empty").mkdir()
    with pytest.raises(CameraError, match="no images"):
        make_source(settings(source="file", path=str(tmp_path / "empty")))
    folder = write_folder(tmp_path / "partial", n=3)
    (folder / "0001_depth.png").unlink()
    with pytest.raises(CameraError, match="2 of 3 frames have depth.*0001.png"):
        make_source(settings(source="file", path=str(folder)))


def test_calibration_yaml_plain_and_ros(tmp_path):
    write_folder(tmp_path / "f", n=1)
    assert load_calibration(tmp_path / "f" / "calibration.yaml") == CAL
    ros = tmp_path / "ros.yaml"
    ros.write_text("image_width: 640\nimage_height: 480\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
                   "  data: [600.0, 0, 320.5, 0, 601.0, 240.5, 0, 0, 1]\n")
    c = load_calibration(ros)
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (640, 480, 600.0, 601.0, 320.5, 240.5)
    bad = tmp_path / "bad.yaml"
    bad.write_text("width: 640\nheight: 480\nfx: x\n")
    with pytest.raises(CameraError, match="lacks a field or has a non-number"):
        load_calibration(bad)


@pytest.mark.parametrize("layout", ["flat", "split"])
def test_folder_frames_resize_and_loop(tmp_path, layout):
    folder = write_folder(tmp_path / "f", n=2, layout=layout)
    src = make_source(settings(source="file", path=str(folder), width=160, height=120))
    src.open()
    assert src.has_depth and src.intrinsics is not None
    assert (src.intrinsics.width, src.intrinsics.fx, src.intrinsics.cx) == (160, 87.5, 79.5)
    got = [src.read() for _ in range(3)]
    assert got[0].rgb.shape == (120, 160, 3) and got[0].depth_mm.shape == (120, 160)
    import cv2

    for i, cap in zip((0, 1, 0), got, strict=True):
        expected = cv2.resize(frame_pixels(i)[1], (160, 120), interpolation=cv2.INTER_NEAREST)
        assert np.array_equal(cap.depth_mm, expected)


def test_folder_without_loop_ends_with_a_reason(tmp_path):
    src = make_source(settings(source="file", path=str(write_folder(tmp_path / "f", n=2)), loop=False,
                               width=320, height=240))
    src.open()
    assert src.read() is not None and src.read() is not None
    assert src.read() is None
    assert "reached its end after 2 frames (loop off)" in src.ended


def test_mcap_source_pairs_by_stamp_in_any_order(tmp_path):
    log = tmp_path / "run.mcap"
    write_log(log, n=4, vehicle="am7")
    src = make_source(settings(source="mcap", path=str(log), loop=False))
    src.open()
    assert src.vehicle == "am7" and src.has_depth and src.intrinsics == CAL
    caps = [src.read() for _ in range(4)]
    for i, cap in enumerate(caps):
        assert cap.jpeg and np.array_equal(cap.depth_mm, frame_pixels(i)[1])
    assert src.read() is None and "end after 4 frames" in src.ended


def test_mcap_source_refuses_a_log_without_frames(tmp_path):
    log = tmp_path / "run.mcap"
    write_log(log, n=2, vehicle="am7")
    with pytest.raises(CameraError, match="no camera/color samples of vehicle 'am9'"):
        make_source(settings(source="mcap", path=str(log), mcap_vehicle="am9")).open()


def test_video_file_loops_with_its_sidecar_calibration(tmp_path):
    import cv2

    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (320, 240))
    assert writer.isOpened()
    for i in range(3):
        writer.write(cv2.cvtColor(frame_pixels(i)[0], cv2.COLOR_RGB2BGR))
    writer.release()
    (tmp_path / "clip.yaml").write_text("width: 320\nheight: 240\nfx: 200\nfy: 201\ncx: 160\ncy: 120\n")
    src = make_source(settings(source="file", path=str(video), width=320, height=240))
    src.open()
    assert not src.has_depth and (src.intrinsics.fx, src.intrinsics.fy) == (200.0, 201.0)
    caps = [src.read() for _ in range(4)]
    assert all(c.depth_mm is None and c.rgb.shape == (240, 320, 3) for c in caps)
    red_x = [int(np.argmax(c.rgb[120, :, 0].astype(int) - c.rgb[120, :, 1])) for c in caps]
    assert red_x[3] == red_x[0] and red_x[1] > red_x[0], f"loops back to the first frame: {red_x}"
