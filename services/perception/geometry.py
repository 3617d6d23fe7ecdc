"""RGB-D geometry with Open3D: mask -> world points, filtered object boxes, support planes, free placement spots."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d

from services.perception.frames import Frame
from shared.messages import BBox2D

MAX_DEPTH_M = 8.0


@dataclass
class Cloud:
    """World points of a mask (subsampled) with their pixel indices."""

    points: np.ndarray  # Nx3 world ENU
    pixels: np.ndarray  # N flat pixel indices
    n_pixels: int  # mask size before depth filtering and subsampling
    n_valid: int  # pixels with valid depth


def bbox_of(idx: np.ndarray, width: int) -> BBox2D | None:
    if idx.size == 0:
        return None
    v, u = np.divmod(idx, width)
    return BBox2D(x0=int(u.min()), y0=int(v.min()), x1=int(u.max()) + 1, y1=int(v.max()) + 1)


def touches_border(bbox: BBox2D | None, shape: tuple[int, int], margin: int = 1) -> bool:
    if bbox is None:
        return False
    h, w = shape
    return bbox.x0 < margin or bbox.y0 < margin or bbox.x1 > w - margin or bbox.y1 > h - margin


def rim_outliers(frame: Frame, idx: np.ndarray, px: int, rel: float = 0.02, abs_mm: float = 20.0) -> np.ndarray:
    """Which of the mask's pixels lie on its rim (within `px` of its edge) with a depth outside the range of the
    mask's interior depths around them (a (4 px + 1)-square window) by more than `rel` * depth + `abs_mm`. The
    depth image of an RGB-D camera sits a pixel or two off the colour the mask is drawn on (the colour imager's
    calibration), so the rim carries depths of what lies behind or in front of the object; a rim pixel that
    continues the object's surface stays (unlike eroding the mask, which also takes the far edge of a small or
    distant object's visible top and pulls its footprint towards the camera). A rim pixel with no interior near
    it (a thin part) stays too."""
    out = np.zeros(idx.shape, bool)
    if px <= 0 or idx.size == 0:
        return out
    h, w = frame.shape
    v, u = np.divmod(idx, w)
    y0, y1 = max(int(v.min()) - 2 * px, 0), min(int(v.max()) + 2 * px + 1, h)
    x0, x1 = max(int(u.min()) - 2 * px, 0), min(int(u.max()) + 2 * px + 1, w)
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    mask[v - y0, u - x0] = 1
    depth = frame.depth_mm[y0:y1, x0:x1].astype(np.float32)
    inner = (cv2.erode(mask, np.ones((2 * px + 1, 2 * px + 1), np.uint8), borderValue=0) > 0) & (depth > 0)
    k = np.ones((4 * px + 1, 4 * px + 1), np.uint8)
    hi = cv2.dilate(np.where(inner, depth, np.float32(0.0)), k)[v - y0, u - x0]
    lo = cv2.erode(np.where(inner, depth, np.float32(1e9)), k)[v - y0, u - x0]
    d = depth[v - y0, u - x0]
    t = rel * d + abs_mm
    rim = ~inner[v - y0, u - x0] & (d > 0) & (hi > 0)
    out = rim & ((d > hi + t) | (d < lo - t))
    return out


def lift(frame: Frame, idx: np.ndarray, max_points: int | None = None) -> Cloud:
    """Flat pixel indices -> world points; invalid depth (0 or beyond MAX_DEPTH_M) is dropped; evenly
    subsampled to at most `max_points` (deterministic, so answers are repeatable)."""
    h, w = frame.shape
    d = frame.depth_mm.ravel()[idx]
    keep = (d > 0) & (d < MAX_DEPTH_M * 1000)
    n_valid = int(np.count_nonzero(keep))  # what the camera returned; mixed depths at edges are then dropped
    if idx.size:
        solid = keep & ~flying_pixels(frame, idx)
        if np.count_nonzero(solid) >= 4:  # a mask that is all edge keeps what it has
            keep = solid
    good = idx[keep]
    if max_points is not None and good.size > max_points:
        good = good[np.linspace(0, good.size - 1, max_points).astype(np.int64)]
    z = frame.depth_mm.ravel()[good].astype(np.float64) * 0.001
    v, u = np.divmod(good, w)
    intr = frame.intr
    pc = np.empty((good.size, 3))
    pc[:, 0] = (u - intr.cx) * z / intr.fx
    pc[:, 1] = (v - intr.cy) * z / intr.fy
    pc[:, 2] = z
    T = frame.world_from_camera  # noqa: N806
    pts = pc @ T[:3, :3].T + T[:3, 3]
    return Cloud(pts, good, int(idx.size), n_valid)


def flying_pixels(frame: Frame, idx: np.ndarray, rel: float = 0.015, abs_mm: float = 8.0) -> np.ndarray:
    """Which of the pixels `idx` have a depth well between the nearest and the farthest valid depth of their
    5x5 neighbourhood. A stereo matcher's window straddling a depth edge gives such mixed depths (flying pixels,
    on both sides of the edge, so the clean depths on either side are two pixels away): points in mid-air along
    the ray, beside or behind an object, that stretch its footprint box. A pixel on a surface matches (to noise)
    its neighbours on one side of an edge, so it stays; only in-between values go."""
    h, w = frame.shape
    v, u = np.divmod(idx, w)
    y0, y1 = max(int(v.min()) - 2, 0), min(int(v.max()) + 3, h)
    x0, x1 = max(int(u.min()) - 2, 0), min(int(u.max()) + 3, w)
    crop = frame.depth_mm[y0:y1, x0:x1].astype(np.float32)
    k = np.ones((5, 5), np.uint8)
    near = cv2.erode(np.where(crop > 0, crop, np.float32(1e9)), k)[v - y0, u - x0]
    far = cv2.dilate(crop, k)[v - y0, u - x0]
    d = crop[v - y0, u - x0]
    t = rel * d + abs_mm
    out: np.ndarray = (d - near > t) & (far - d > t)
    return out


def remove_outliers(points: np.ndarray, nb_neighbors: int = 16, std_ratio: float = 2.0) -> np.ndarray:
    """Open3D statistical outlier removal; returns the kept indices."""
    if len(points) < nb_neighbors + 2:
        return np.arange(len(points))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    _, kept = pcd.remove_statistical_outlier(nb_neighbors=nb_neighbors, std_ratio=std_ratio)
    return np.asarray(kept, dtype=np.int64)


@dataclass
class ObjectGeometry:
    """An object's oriented box fitted to its points: centre, yaw, size, top and support heights."""

    center: np.ndarray  # x/y: centre of the footprint box; z: halfway between support and top
    yaw: float  # along the footprint's longer side, in (-pi/2, pi/2]
    size: np.ndarray  # along yaw, across, height
    top_z: float
    support_z: float
    n_points: int


def upright_box(points: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Gravity-aligned oriented box of an object resting on a horizontal surface: the minimum-area rectangle
    of the x/y footprint (exact on squares, unlike a PCA box) -> (centre xy, yaw, (long, short))."""
    (cx, cy), (w, h), angle = cv2.minAreaRect(points[:, :2].astype(np.float32))
    yaw = math.radians(angle)
    if h > w:
        w, h = h, w
        yaw += math.pi / 2
    yaw = (yaw + math.pi / 2) % math.pi - math.pi / 2  # a box is symmetric under a half turn
    return np.array([cx, cy]), yaw, np.array([w, h])


MAX_ROUND_RADIUS = 0.15  # m: larger round footprints are not taken for an object's side seen alone


def round_from_side(points: np.ndarray, camera_xy: np.ndarray, rect_center: np.ndarray, rect_yaw: float,
                    rect_lw: np.ndarray, bin_m: float = 0.004) -> tuple[np.ndarray, float] | None:
    """An upright round object whose top the mask misses (a can's bare lid, a bottle's cap and shoulder, a cup
    seen from below its rim) shows only its near side: its points' footprint is the arc facing the camera, the
    rectangle around that arc is about a radius deep and its centre about half a radius nearer than the axis.
    The arc is the footprint's front as the camera sees it (per `bin_m` strip across the view, the nearest
    point: the widest section, not a narrower neck above it). When it lies on a circle much better than on the
    rectangle's edges, the circle spans about the rectangle's length (a half circle spans its diameter) and its
    centre lies beyond the arc from the camera, the circle is the footprint: returns (its centre xy, its
    radius), else None."""
    xy = points[:, :2]
    length, width = float(rect_lw[0]), float(rect_lw[1])
    if len(xy) < 20 or width >= 0.8 * length:
        return None  # about square already: the top is in view (or it is no arc)
    mean = xy.mean(axis=0)
    ahead = mean - camera_xy
    norm = float(np.hypot(*ahead))
    if norm < 1e-6:
        return None  # looking straight down on it: no side
    ahead = ahead / norm
    rel = xy - mean
    depth, lateral = rel @ ahead, rel @ np.array([-ahead[1], ahead[0]])
    strip = np.floor(lateral / bin_m).astype(np.int64)
    order = np.lexsort((depth, strip))
    first = order[np.r_[True, strip[order][1:] != strip[order][:-1]]]
    if first.size < 8:
        return None
    front = xy[first]
    # Algebraic (Kasa) circle fit: x^2 + y^2 = 2 a x + 2 b y + c.
    a = np.column_stack([2 * front, np.ones(len(front))])
    sol, *_ = np.linalg.lstsq(a, (front ** 2).sum(axis=1), rcond=None)
    centre = sol[:2]
    r2 = float(sol[2] + centre @ centre)
    if r2 <= 0:
        return None
    r = math.sqrt(r2)
    if r > MAX_ROUND_RADIUS or not 0.7 * length / 2 <= r <= 1.4 * length / 2:
        return None
    circle_rms = float(np.sqrt(np.mean((np.linalg.norm(front - centre, axis=1) - r) ** 2)))
    c, s = math.cos(rect_yaw), math.sin(rect_yaw)
    off = front - rect_center
    u, v = off @ np.array([c, s]), off @ np.array([-s, c])
    edge = np.minimum(np.abs(length / 2 - np.abs(u)), np.abs(width / 2 - np.abs(v)))
    rect_rms = float(np.sqrt(np.mean(edge ** 2)))
    if circle_rms > max(0.004, 0.1 * r) or circle_rms > 0.5 * rect_rms:
        return None
    if float((centre - front.mean(axis=0)) @ ahead) <= 0:
        return None  # the circle's centre is on the camera's side of the arc: not a near side seen
    return centre, r


def support_height(frame: Frame, idx: np.ndarray, bottom_z: float, ring_px: int = 6) -> float | None:
    """Median height of the surface just around the object's mask (a ring of pixels), when it is there."""
    h, w = frame.shape
    v, u = np.divmod(idx, w)
    y0, y1 = max(int(v.min()) - ring_px, 0), min(int(v.max()) + ring_px + 1, h)
    x0, x1 = max(int(u.min()) - ring_px, 0), min(int(u.max()) + ring_px + 1, w)
    crop = np.zeros((y1 - y0, x1 - x0), np.uint8)
    crop[v - y0, u - x0] = 1
    dilated = np.asarray(cv2.dilate(crop, np.ones((2 * ring_px + 1, 2 * ring_px + 1), np.uint8)), np.uint8)
    ring = dilated & (crop ^ 1)
    rv, ru = np.nonzero(ring)
    ring_idx = (rv + y0) * w + (ru + x0)
    cloud = lift(frame, ring_idx, max_points=800)
    if len(cloud.points) == 0:
        return None
    z = cloud.points[:, 2]
    near = z[(z > bottom_z - 0.04) & (z < bottom_z + 0.03)]
    if near.size < 8:
        return None
    return float(np.median(near))


def object_geometry(frame: Frame, cloud: Cloud, idx: np.ndarray) -> ObjectGeometry:
    """Box, top and support of an object from its (already depth-valid) cloud.

    The camera sees only the near side. Objects here stand upright on horizontal surfaces and the camera
    looks down on them, so the visible top plus the near sides project onto the full footprint: the centre
    of the footprint rectangle is the object's axis, not the (near-biased) mean of the visible points. A round
    object whose top is not in its mask projects only its near arc: `round_from_side` finds the circle."""
    pts = cloud.points
    kept = remove_outliers(pts)
    pts = pts[kept] if kept.size >= 4 else pts
    z = pts[:, 2]
    top_z = float(np.percentile(z, 99.0))
    bottom_z = float(np.percentile(z, 1.0))
    support = support_height(frame, idx, bottom_z)
    support_z = support if support is not None and support < top_z - 0.005 else bottom_z
    # Only points at the object's own height span the footprint (a stray support pixel must not widen it).
    body = pts[z > support_z + 0.005] if np.count_nonzero(z > support_z + 0.005) >= 4 else pts
    cxy, yaw, lw = upright_box(body)
    side = round_from_side(body, frame.world_from_camera[:2, 3], cxy, yaw, lw)
    if side is not None:
        cxy, r = side
        yaw, lw = 0.0, np.array([2 * r, 2 * r])
    height = max(top_z - support_z, 0.0)
    center = np.array([cxy[0], cxy[1], support_z + height / 2])
    return ObjectGeometry(center, yaw, np.array([lw[0], lw[1], height]), top_z, support_z, int(len(pts)))


@dataclass
class Placement:
    """A placement spot found on a support plane, with the plane, the clearance there and the inlier count."""

    spot: np.ndarray  # x, y on the plane
    surface_z: float
    plane: tuple[float, float, float, float]
    clearance: float
    n_inliers: int
    max_clearance: float


def horizontal_plane(points: np.ndarray, distance: float = 0.012, max_tilt_deg: float = 10.0,
                     tries: int = 3, min_inliers: int = 50, seed: int = 0) -> tuple[np.ndarray, np.ndarray] | None:
    """RANSAC (Open3D segment_plane) for the dominant near-horizontal plane: vertical faces (table sides,
    legs) are peeled off and the search repeats. Returns (plane a,b,c,d with normal up, inlier indices)."""
    rest = np.arange(len(points))
    cos_max = math.cos(math.radians(max_tilt_deg))
    o3d.utility.random.seed(seed)
    for _ in range(tries):
        if rest.size < min_inliers:
            return None
        # RANSAC on an even subsample (a plane needs few points), inliers then from every point.
        sample = rest[np.linspace(0, rest.size - 1, min(rest.size, 2500)).astype(np.int64)]
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[sample]))
        plane, _ = pcd.segment_plane(distance_threshold=distance, ransac_n=3, num_iterations=120)
        plane = np.asarray(plane, dtype=np.float64)
        norm = np.linalg.norm(plane[:3])
        if norm <= 0:
            return None
        plane = plane / norm
        inl = np.flatnonzero(np.abs(points[rest] @ plane[:3] + plane[3]) <= distance)
        if inl.size < min_inliers:
            return None
        if plane[2] < 0:
            plane = -plane
        if plane[2] >= cos_max:
            return plane, rest[inl]
        rest = np.delete(rest, inl)
    return None


def free_spot(surface_pts: np.ndarray, surface_z: float, clutter_pts: np.ndarray, required: float,
              cell: float = 0.02, preferred: np.ndarray | None = None) -> Placement | None:
    """A point on the surface at least `required` from every edge and every clutter point standing on it.

    The visible surface is rasterised on a `cell` grid; cells with clutter (anything 1.5 cm to 80 cm above
    the plane) are blocked; a distance transform gives each free cell its clearance to the nearest edge or
    clutter (unseen parts count as edges: conservative). Among cells with the best clearance up to
    `required` + 10 cm, the one nearest `preferred` (default: the visible surface's middle) wins."""
    xy = surface_pts[:, :2]
    lo = xy.min(axis=0) - 2 * cell
    hi = xy.max(axis=0) + 2 * cell
    shape = (int(math.ceil((hi[1] - lo[1]) / cell)) + 1, int(math.ceil((hi[0] - lo[0]) / cell)) + 1)
    if shape[0] * shape[1] > 400 * 400:
        return None
    grid = np.zeros(shape, np.uint8)
    ij = ((xy - lo) / cell).astype(np.int64)
    grid[ij[:, 1], ij[:, 0]] = 1
    # Close sampling gaps between depth pixels, not occlusion holes (those are a few cells wide).
    grid = np.asarray(cv2.morphologyEx(grid, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)), np.uint8)
    if len(clutter_pts):
        c = clutter_pts[(clutter_pts[:, 2] > surface_z + 0.015) & (clutter_pts[:, 2] < surface_z + 0.8)]
        cij = ((c[:, :2] - lo) / cell).astype(np.int64)
        ok = (cij[:, 0] >= 0) & (cij[:, 1] >= 0) & (cij[:, 0] < shape[1]) & (cij[:, 1] < shape[0])
        block = np.zeros(shape, np.uint8)
        block[cij[ok, 1], cij[ok, 0]] = 1
        grid[block.astype(bool)] = 0
    grid[0, :] = grid[-1, :] = 0
    grid[:, 0] = grid[:, -1] = 0
    dist = cv2.distanceTransform(grid, cv2.DIST_L2, 5) * cell
    best = float(dist.max())
    if best <= 0:
        return None
    target = min(best, required + 0.10)
    cand = np.argwhere(dist >= target - 1e-6)
    pos = lo + (cand[:, ::-1] + 0.5) * cell
    ref = preferred if preferred is not None else xy.mean(axis=0)
    k = int(np.argmin(np.linalg.norm(pos - ref, axis=1)))
    # The clearance counts from the cell centre to the nearest blocked cell's centre; half a cell is lost.
    clearance = float(dist[tuple(cand[k])]) - cell / 2
    plane = (0.0, 0.0, 1.0, -surface_z)
    return Placement(pos[k], surface_z, plane, clearance, len(surface_pts), best - cell / 2)
