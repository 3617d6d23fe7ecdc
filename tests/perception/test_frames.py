"""Frame pairing by timestamp, tf lookup at the frame's stamp, and what is reported missing."""

from __future__ import annotations

import numpy as np

from services.perception.frames import FrameStore
from shared.frames import DEFAULT_INTRINSICS, base_to_camera
from shared.messages import SimLabels
from shared.sensors import calibration_message, color_message, parse_calibration, pose_matrix, raw16_message
from shared.sensors import transforms_message as tfm

RGB = np.zeros((480, 640, 3), np.uint8)
DEPTH = np.full((480, 640), 1500, np.uint16)


def tf(stamp: int, x: float) -> bytes:
    return tfm([("world", "base_link", pose_matrix(x, 0.0, 1.0, 0.0)), ("base_link", "camera", base_to_camera())],
               stamp)


def test_pairs_only_matching_stamps_and_picks_newest_complete() -> None:
    st = FrameStore()
    st.add_tf(tf(1_000, 0.0))
    assert st.latest() is None and "colour" in st.missing()
    st.add_color(color_message(RGB, 2_000))
    st.add_depth(raw16_message(DEPTH, 1_000))  # a depth image of another frame does not pair
    assert st.latest() is None
    assert "same timestamp" in st.missing()
    st.add_depth(raw16_message(DEPTH, 2_000))
    f = st.latest()
    assert f is not None and f.stamp_ns == 2_000
    # A newer colour image alone does not replace the complete pair.
    st.add_color(color_message(RGB, 3_000))
    assert st.latest().stamp_ns == 2_000
    st.add_depth(raw16_message(DEPTH, 3_000))
    assert st.latest().stamp_ns == 3_000
    assert f.rgb.shape == (480, 640, 3)  # colour decodes lazily


def test_tf_nearest_to_frame_stamp_and_out_of_order_dropped() -> None:
    st = FrameStore()
    for stamp, x in ((1_000, 1.0), (2_000, 2.0), (3_000, 3.0)):
        st.add_tf(tf(stamp, x))
    st.add_tf(tf(1_500, 99.0))  # late and out of order: ignored
    st.add_color(color_message(RGB, 2_100))
    st.add_depth(raw16_message(DEPTH, 2_100))
    f = st.latest()
    expected = pose_matrix(2.0, 0.0, 1.0, 0.0) @ base_to_camera()
    assert np.allclose(f.world_from_camera, expected, atol=1e-6)


def test_segmentation_required_for_sim_and_calibration_used() -> None:
    st = FrameStore(need_segmentation=True)
    st.add_tf(tf(1, 0.0))
    st.add_calibration(parse_calibration(calibration_message(DEFAULT_INTRINSICS, 1)))
    st.add_color(color_message(RGB, 5))
    st.add_depth(raw16_message(DEPTH, 5))
    assert st.latest() is None and "segmentation" in st.missing()
    st.add_segmentation(raw16_message(np.zeros((480, 640), np.uint16), 5))
    assert st.latest() is None and "sim/labels" in st.missing()
    st.add_labels(SimLabels())
    f = st.latest()
    assert f is not None and f.segmentation is not None and f.intr == DEFAULT_INTRINSICS


def test_no_tf_means_no_frame() -> None:
    st = FrameStore()
    st.add_color(color_message(RGB, 5))
    st.add_depth(raw16_message(DEPTH, 5))
    assert st.latest() is None
    assert "tf world->base_link" in st.missing()


def test_frame_waits_for_its_own_pose_instead_of_taking_an_old_one() -> None:
    # Zenoh does not order keys: a frame can arrive before the tf with its stamp. During a 1 m/s climb an
    # older pose 0.5 s back would put every point half a metre too low.
    st = FrameStore()
    t0 = 1_700_000_000_000_000_000
    st.add_tf(tf(t0, 0.0))
    st.add_color(color_message(RGB, t0 + 500_000_000))
    st.add_depth(raw16_message(DEPTH, t0 + 500_000_000))
    assert st.latest() is None
    assert "transform at the frame's timestamp" in st.missing()
    rev = st.revision
    st.add_tf(tf(t0 + 500_000_000, 2.0))
    assert st.revision > rev  # the service wakes waiting queries on a pose too
    f = st.latest()
    assert f is not None and f.stamp_ns == t0 + 500_000_000
    assert np.allclose(f.world_from_camera, pose_matrix(2.0, 0.0, 1.0, 0.0) @ base_to_camera(), atol=1e-6)


def test_pose_interpolated_between_bracketing_samples() -> None:
    st = FrameStore()
    t0 = 1_700_000_000_000_000_000
    st.add_tf(tf(t0, 0.0))
    st.add_tf(tf(t0 + 100_000_000, 1.0))
    st.add_color(color_message(RGB, t0 + 25_000_000))
    st.add_depth(raw16_message(DEPTH, t0 + 25_000_000))
    f = st.latest()
    assert np.allclose(f.world_from_camera, pose_matrix(0.25, 0.0, 1.0, 0.0) @ base_to_camera(), atol=1e-6)
