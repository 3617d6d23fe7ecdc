"""What perception does about a stereo camera's edges: flying pixels (a depth mixed between foreground and
background) are dropped, a surface's own pixels next to an edge are kept, and a mask's rim pixels whose depth is
the background's (the depth image a pixel off the colour) are dropped while a rim that continues the object
stays."""

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


def test_rim_pixels_with_the_background_depth_go_the_surface_s_own_rim_stays():
    """A mask drawn on colour, its depth a pixel off (misregistration): the rim column of the box's mask carries
    the wall's depth (2 m) and goes; the top rim rows of a tilted surface continue the interior's depth and stay;
    a thin mask (no interior) keeps everything."""
    depth = np.full((H, W), 2000, np.uint16)
    # A surface seen at a grazing angle: depth grows 1 cm per row (rows 200-279), the box's columns 200-279.
    depth[200:280, 200:280] = (1000 + 10 * (np.arange(80)[:, None] * np.ones((1, 80)))).astype(np.uint16)
    depth[200:280, 198:200] = 2000  # the mask's two left columns show the wall behind (depth shifted)
    mask = np.zeros((H, W), bool)
    mask[200:280, 198:280] = True
    idx = np.flatnonzero(mask.ravel())
    out = geo.rim_outliers(frame(depth), idx, 2)
    v, u = np.divmod(idx[out], W)
    assert set(u.tolist()) == {198, 199} and out.sum() == 160
    assert not geo.rim_outliers(frame(depth), idx, 0).any()
    thin = np.flatnonzero((np.arange(H * W) // W == 240) & (np.arange(H * W) % W < 50))  # a 1-px line
    depth[240, :50] = np.arange(50) * 100 + 500
    assert not geo.rim_outliers(frame(depth), thin, 2).any()
