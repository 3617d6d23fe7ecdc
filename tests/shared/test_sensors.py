"""Depth on the bus: a 16-bit PNG in a foxglove.CompressedImage, lossless; an older log's RawImage still reads."""

from __future__ import annotations

import numpy as np
import pytest

from shared.errors import DecodeError
from shared.sensors import CompressedImage, decode_depth, depth_message, parse_depth, raw16_message


def noisy_depth(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rows = np.arange(480, dtype=np.float64)[:, None]
    img = 1500 + 2 * rows + rng.normal(0, 5, (480, 640))
    img[100:200, 200:300] = 900
    img[300:320, :] = 0  # dropouts: no depth
    return np.clip(img, 0, 65535).astype(np.uint16)


def test_depth_round_trips_exactly_and_is_smaller_than_raw() -> None:
    img = noisy_depth()
    img[0, 0] = 65535  # the whole 16-bit range survives
    payload = depth_message(img, 123_456_789, frame_id="cam")
    stamp, back = parse_depth(payload)
    assert stamp == 123_456_789 and back.dtype == np.uint16 and np.array_equal(back, img)
    msg = CompressedImage()
    msg.ParseFromString(payload)
    assert (msg.format, msg.frame_id) == ("png", "cam")
    assert len(payload) < 0.6 * img.nbytes  # 5 mm noise on every pixel still compresses


def test_a_raw16_depth_from_an_older_log_still_reads() -> None:
    img = noisy_depth(1)
    stamp, back = parse_depth(raw16_message(img, 42))
    assert stamp == 42 and np.array_equal(back, img)
    assert decode_depth(raw16_message(img, 42, frame_id="cam"))[1] == "cam"
    assert decode_depth(depth_message(img, 42, frame_id="cam"))[1] == "cam"


@pytest.mark.parametrize("fmt, data, why", [
    ("jpeg", b"\xff\xd8\xff", "expected a png depth image"),
    ("png", b"not a png", "not a 16-bit greyscale image"),
])
def test_a_depth_payload_that_is_not_16_bit_png_is_a_decode_error(fmt: str, data: bytes, why: str) -> None:
    payload = CompressedImage(format=fmt, data=data).SerializeToString()
    with pytest.raises(DecodeError, match=why):
        parse_depth(payload)


def test_an_8_bit_png_is_refused_as_depth() -> None:
    import cv2

    ok, png8 = cv2.imencode(".png", np.zeros((4, 4), np.uint8))
    assert ok
    with pytest.raises(DecodeError, match="uint8"):
        parse_depth(CompressedImage(format="png", data=png8.tobytes()).SerializeToString())


def test_depth_message_refuses_what_is_not_hxw_uint16() -> None:
    with pytest.raises(ValueError, match="HxW uint16"):
        depth_message(np.zeros((4, 4), np.float32), 0)
