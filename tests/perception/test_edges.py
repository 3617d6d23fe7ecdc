"""What perception does about a stereo camera's edges: flying pixels (a depth mixed between foreground and
background) are dropped, a surface's own pixels next to an edge are kept, and an object's points come from its
mask's interior (the misregistered rim carries the background's depth)."""

from __future__ import annotations

import numpy as np

from services.perception import geometry as geo
from services.perception.frames import Frame
from shared.frames import DEFAULT_INTRINSICS

H, W = DEFAULT_INTRINSICS.height, DEFAULT_INTRINSICS.width


def frame(depth_mm: np.ndarray) -> Frame:
    return Frame(0, depth_mm.astype(np.uint16), DEFAULT_INTRINSICS, np.eye(4))


def box_scene() -> tuple[np.ndarray, np.ndarray]:
    """A box 1.0 m away (rows/columns 200-279) in front of a wall 2.0 m away; its left and right edges each get
    one column of mixed depth (flying pixels, 1.3 and 1.7 m)."""
    depth = np.full((H, W), 2000, np.uint16)
    depth[200:280, 200:280] = 1000
    depth[200:280, 199] = 1300
    depth[200:280, 280] = 1700
    mask = np.zeros((H, W), bool)
    mask[200:280, 199:281] = True  # the mask reaches onto the edge columns
    return depth, mask


def test_flying_pixels_are_the_mixed_depths_only():
    depth, mask = box_scene()
    idx = np.flatnonzero(mask.ravel())
    flying = geo.flying_pixels(frame(depth), idx)
    v, u = np.divmod(idx[flying], W)
    assert set(u.tolist()) == {199, 280}  # both mixed columns, nothing else
    assert flying.sum() == 160
    # The box's own surface right beside the edge, and noise on it (1 % of 1 m), stays.
    noisy = depth.copy()
    noisy[200:280, 200:280] += np.random.default_rng(0).integers(-10, 11, (80, 80)).astype(np.uint16)
    inner = np.zeros((H, W), bool)
    inner[200:280, 200:280] = True
    assert not geo.flying_pixels(frame(noisy), np.flatnonzero(inner.ravel())).any()


def test_lift_drops_flying_pixels_and_keeps_their_count_as_returned():
    depth, mask = box_scene()
    cloud = geo.lift(frame(depth), np.flatnonzero(mask.ravel()))
    z = cloud.points[:, 2]  # identity pose: optical z
    assert np.allclose(z, 1.0) and len(z) == 80 * 80
    assert cloud.n_valid == 80 * 82  # what the camera returned, before the filter


def test_interior_drops_the_rim_unless_too_little_is_left():
    _, mask = box_scene()
    idx = np.flatnonzero(mask.ravel())
    inner = geo.interior(idx, (H, W), 2, keep=30)
    v, u = np.divmod(inner, W)
    assert (u.min(), u.max(), v.min(), v.max()) == (201, 278, 202, 277)
    thin = np.flatnonzero((np.arange(H * W) // W == 240) & (np.arange(H * W) % W < 50))  # a 1-px line
    assert np.array_equal(geo.interior(thin, (H, W), 2, keep=30), thin)
    assert np.array_equal(geo.interior(idx, (H, W), 0, keep=30), idx)
