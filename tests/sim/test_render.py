"""The simulated depth camera: the floor in view from the ground (the absolute near plane)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.sim import render
from services.sim.layout import FLOOR_Z
from services.sim.render import MIN_DEPTH_M, Renderer, snapshot_at
from services.sim.scenarios import STRUCTURE_IDS
from shared.frames import CAMERA_OFFSET_BODY, CAMERA_PITCH_DOWN, DEFAULT_INTRINSICS
from tests.perception.scenes import layout


def floor_depth(rows: np.ndarray, height: float) -> np.ndarray:
    """z-depth of the floor along image rows `rows` for the camera `height` above it (pitched down, level body),
    inf where the row looks above the horizon."""
    s, c = math.sin(CAMERA_PITCH_DOWN), math.cos(CAMERA_PITCH_DOWN)
    down = s + c * (rows - DEFAULT_INTRINSICS.cy) / DEFAULT_INTRINSICS.fy  # downward part of the ray (z = 1)
    return np.where(down > 1e-6, height / np.maximum(down, 1e-6), np.inf)


@pytest.mark.parametrize("realism", ["ideal", "realistic"])
def test_a_landed_camera_sees_the_floor(realism, monkeypatch):
    """Landed (gear on the floor), the camera is 5 cm above it, pitched 35 deg down: the lower half of the image
    is floor 4-9 cm from the lens. MuJoCo's near plane, a fraction of the model's extent (0.17 m here), clipped
    all of it: black colour, no depth. With the absolute near plane it renders: floor in colour and segmentation,
    and in the z-buffer at the floor's distance (checked with the stereo minimum range lifted: a real stereo
    camera, like the simulated one by default, returns no depth nearer than 0.2 m, i.e. below row ~100)."""
    world = layout(1, look="primitive" if realism == "ideal" else "textured")
    start = np.array([0.0, 0.0, 0.0])
    snap = snapshot_at(world, start, 0.3)
    height = CAMERA_OFFSET_BODY[2] - FLOOR_Z
    r = Renderer(realism=realism, seed=3)
    try:
        f = r.render(snap)
        monkeypatch.setattr(render, "MIN_DEPTH_M", 0.0)
        raw = r.render(snap)
    finally:
        r.close()
    lower = slice(DEFAULT_INTRINSICS.height // 2, DEFAULT_INTRINSICS.height)
    assert (f.instance[lower] == STRUCTURE_IDS["floor"]).mean() > 0.95
    black = (f.rgb[lower].max(axis=2) < 15).mean()
    assert black < 0.01, f"{100 * black:.0f} % of the lower half is black: clipped by the near plane"
    # The z-buffer holds the floor where it is (lower half: 4-9 cm).
    rows = np.arange(DEFAULT_INTRINSICS.height, dtype=np.float64)[lower]
    expect = floor_depth(rows, height)[:, None] * np.ones((1, DEFAULT_INTRINSICS.width))
    z = raw.depth_mm[lower].astype(np.float64) / 1000.0
    floor = raw.instance[lower] == STRUCTURE_IDS["floor"]
    assert (z[floor] > 0).mean() > 0.95, "no depth on the floor of the lower half"
    tol = 0.005 if realism == "ideal" else 0.2 * expect[floor]  # realistic: stereo noise, edges
    assert (np.abs(z[floor] - expect[floor]) <= tol).mean() > 0.9
    # With the stereo minimum range, the lower half has no depth (too near), the floor beyond 0.2 m has.
    assert (f.depth_mm[lower] == 0).mean() > 0.99
    far_rows = np.flatnonzero(floor_depth(np.arange(DEFAULT_INTRINSICS.height, dtype=np.float64),
                                          height) > MIN_DEPTH_M + 0.03)
    band = f.depth_mm[far_rows]
    on_floor = f.instance[far_rows] == STRUCTURE_IDS["floor"]
    assert on_floor.sum() > 2000
    assert (band[on_floor] > 0).mean() > 0.8
