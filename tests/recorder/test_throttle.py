"""The recorder's frame rate limit: pairs kept or skipped together, every step's frame kept."""

from __future__ import annotations

import numpy as np

from services.recorder.throttle import FrameThrottle
from shared.messages import ReasoningStep
from shared.sensors import color_message, depth_message
from tests.recorder.samples import K

ENC = "application/protobuf;foxglove.CompressedImage"
RGB = np.zeros((8, 8, 3), np.uint8)
DEPTH = np.full((8, 8), 1500, np.uint16)
FPS = 15
PERIOD = 1_000_000_000 // FPS


def pair(stamp: int, depth_first: bool = False) -> list[tuple[str, bytes, str, int]]:
    c = (K.camera_color.key, color_message(RGB, stamp), ENC, stamp)
    d = (K.camera_depth.key, depth_message(DEPTH, stamp), ENC, stamp)
    return [d, c] if depth_first else [c, d]


def written(throttle: FrameThrottle, samples) -> list[tuple[str, int]]:
    out = []
    for s in samples:
        out += [(k, t) for k, _, _, t in throttle.admit(*s)]
    return out


def test_one_pair_a_second_kept_whole_whichever_half_comes_first() -> None:
    th = FrameThrottle(1.0)
    samples = [s for i in range(3 * FPS) for s in pair(10**12 + i * PERIOD, depth_first=bool(i % 2))]
    out = written(th, samples)
    stamps = sorted({t for _, t in out})
    assert stamps == [10**12 + i * PERIOD for i in (0, FPS, 2 * FPS)]
    assert all((K.camera_color.key, t) in out and (K.camera_depth.key, t) in out for t in stamps)
    assert th.skipped == 2 * (3 * FPS - 3)


def test_the_frame_a_step_was_decided_on_is_written_with_the_step() -> None:
    th = FrameThrottle(1.0)
    base = 10**12
    written(th, [s for i in range(FPS) for s in pair(base + i * PERIOD)])
    seen = base + 7 * PERIOD  # skipped by the rate limit
    step = ReasoningStep(task_id="t", step=1, image_stamp_ns=seen).model_dump_json().encode()
    out = written(th, [(K.reasoning_step.key, step, "application/json;aermani.ReasoningStep", base + 10**10)])
    assert sorted(out) == sorted([(K.camera_color.key, seen), (K.camera_depth.key, seen),
                                  (K.reasoning_step.key, base + 10**10)])
    assert written(th, [(K.reasoning_step.key, step, "application/json", 1)]) == [(K.reasoning_step.key, 1)]


def test_a_frame_that_comes_after_the_step_that_names_it_is_written() -> None:
    """Zenoh orders nothing across keys: a `done` step, published milliseconds after its decision, reached the
    recorder before its frame under load (ci30's test_demo_rules found that frame missing from the log)."""
    th = FrameThrottle(1.0)
    base = 10**12
    written(th, pair(base))  # the pair of this second is written
    late = base + 7 * PERIOD  # within the second: the rate limit would skip it
    step = ReasoningStep(task_id="t", step=1, image_stamp_ns=late).model_dump_json().encode()
    assert written(th, [(K.reasoning_step.key, step, "application/json", base + 8 * PERIOD)]) == \
        [(K.reasoning_step.key, base + 8 * PERIOD)]
    out = written(th, [s for i in range(1, FPS) for s in pair(base + i * PERIOD)])
    assert sorted(out) == [(K.camera_color.key, late), (K.camera_depth.key, late)]


def test_zero_keeps_every_frame_and_other_keys_always_pass() -> None:
    every = FrameThrottle(0.0)
    samples = [s for i in range(10) for s in pair(i * PERIOD)]
    assert len(written(every, samples)) == 20
    th = FrameThrottle(1.0)
    state = (K.autopilot_state.key, b"{}", "application/json", 5)
    garbage = (K.camera_color.key, b"\xff\x00not protobuf", ENC, 6)
    assert written(th, [state, state, garbage]) == [(K.autopilot_state.key, 5)] * 2 + [(K.camera_color.key, 6)]


def test_depth_thinned_by_the_link_still_gets_its_colour_frame() -> None:
    """The drone router sends depth at 1 Hz: each depth frame that arrives is written with its colour."""
    th = FrameThrottle(1.0)
    base, out = 10**12, []
    for i in range(3 * FPS):
        t = base + i * PERIOD
        c, d = pair(t)
        out += [(k, s) for k, _, _, s in th.admit(*c)]
        if i % FPS == 5:  # a depth frame at its own phase, once a second
            out += [(k, s) for k, _, _, s in th.admit(*d)]
    depth_stamps = [s for k, s in out if k == K.camera_depth.key]
    colour_stamps = {s for k, s in out if k == K.camera_color.key}
    assert depth_stamps == [base + i * PERIOD for i in (5, FPS + 5, 2 * FPS + 5)]
    assert set(depth_stamps) <= colour_stamps
    assert len(colour_stamps) <= 2 * 3  # the rate limit's own frames and depth's partners
