"""obj_localization and placement_localization on one frame: segmenter + geometry -> estimates and detections."""

from __future__ import annotations

import logging
import math
from typing import Any, NamedTuple, TypeVar

import numpy as np

from services.perception import geometry as geo
from services.perception import query as q
from services.perception.frames import Frame
from services.perception.segmenters.base import Found, Segment, Segmenter
from services.perception.settings import PerceptionSettings
from shared.messages import (
    BBox2D,
    Detection,
    Detections,
    LocalizeRequest,
    ObjectEstimate,
    PlacementEstimate,
    Pose,
    Vec3,
)

log = logging.getLogger("aermani.perception")

OBJECT_CATEGORIES = ("object",)
PLACEMENT_CATEGORIES = ("surface", "furniture", "structure")


def _vec(a: np.ndarray | tuple[float, float, float]) -> Vec3:
    return Vec3(x=float(a[0]), y=float(a[1]), z=float(a[2]))


def _catalog(seg: Segment) -> Vec3 | None:
    """The segment's class's catalogued extent standing (x long, y short, z height), when the segmenter knows it."""
    return _vec(seg.nominal) if seg.nominal is not None else None


def camera_yaw(frame: Frame) -> float:
    """Heading of the camera's optical axis projected on the ground plane."""
    fwd = frame.world_from_camera[:3, 2]
    return math.atan2(fwd[1], fwd[0])


E = TypeVar("E", ObjectEstimate, PlacementEstimate)


class _Target(NamedTuple):
    """A found segment with its pixels, their bounding box and depth points, and the estimate's common fields."""

    found: Found
    seg: Segment
    idx: np.ndarray
    bbox: BBox2D | None
    cloud: geo.Cloud
    base: dict[str, Any]


class Perception:
    """Stateless per request: everything comes from the frame it is given."""

    def __init__(self, segmenter: Segmenter, settings: PerceptionSettings) -> None:
        self.segmenter = segmenter
        self.settings = settings

    # ---- objects

    def localize_object(self, frame: Frame, req: LocalizeRequest, parsed: q.Query) -> ObjectEstimate:
        target = self._target(frame, parsed, OBJECT_CATEGORIES, ObjectEstimate, self.settings.max_object_points,
                              self.settings.min_pixels, self.settings.rim_px)
        if not isinstance(target, _Target):
            return target
        found, seg, idx, bbox, cloud, base = target
        if cloud.n_valid < self.settings.min_points:
            return ObjectEstimate(found=False, reason="too_few_points", n_points=cloud.n_valid,
                                  message=f"{seg.label}: {cloud.n_valid} valid depth points (< "
                                  f"{self.settings.min_points}); move closer", **base)
        g = geo.object_geometry(frame, cloud, idx)
        truncated = geo.touches_border(bbox, frame.shape)
        valid_frac = cloud.n_valid / max(idx.size, 1)
        conf = seg.score * min(1.0, cloud.n_valid / 300) * (0.5 + 0.5 * valid_frac) * (0.6 if truncated else 1.0)
        msg = found.message + ("; partly out of the image, estimate biased" if truncated else "")
        return ObjectEstimate(
            found=True, reason="ok", message=msg, pose=Pose(position=_vec(g.center), yaw=g.yaw),
            size=_vec(g.size), top_z=g.top_z, support_z=g.support_z, confidence=round(float(conf), 3),
            n_points=g.n_points, catalog_size=_catalog(seg), **base)

    # ---- placement

    def localize_placement(self, frame: Frame, req: LocalizeRequest, parsed: q.Query) -> PlacementEstimate:
        s = self.settings
        target = self._target(frame, parsed, PLACEMENT_CATEGORIES, PlacementEstimate, s.max_surface_points)
        if not isinstance(target, _Target):
            return target
        found, seg, _, bbox, cloud, base = target
        if cloud.n_valid < s.min_points:
            return PlacementEstimate(found=False, reason="too_few_points", n_points=cloud.n_valid,
                                     message=f"{seg.label}: {cloud.n_valid} valid depth points", **base)
        plane = geo.horizontal_plane(cloud.points, s.plane_distance, s.max_plane_tilt_deg,
                                     min_inliers=max(s.min_points, 30))
        if plane is None:
            return PlacementEstimate(found=False, reason="too_few_points", n_points=cloud.n_valid,
                                     message=f"no horizontal plane found on the {seg.label}", **base)
        coeffs, inliers = plane
        surf = cloud.points[inliers]
        surface_z = float(np.median(surf[:, 2]))
        radius = self._held_radius(req)
        required = radius + s.placement_margin
        clutter = self._clutter(frame, surf, surface_z, bbox)
        spot = geo.free_spot(surf, surface_z, clutter, required, s.cell_size)
        if spot is None or spot.clearance < required:
            best = 0.0 if spot is None else spot.max_clearance
            return PlacementEstimate(
                found=False, reason="no_free_spot", surface_z=surface_z, n_points=int(inliers.size),
                plane=tuple(float(c) for c in coeffs),  # type: ignore[arg-type]
                message=f"no spot on the visible {seg.label} with {required:.2f} m clearance (best {best:.2f} m);"
                " look from another side or clear the surface", **base)
        pos = (spot.spot[0], spot.spot[1], surface_z + s.vertical_offset)
        visible_frac = min(1.0, inliers.size / 400)
        conf = seg.score * visible_frac * min(1.0, spot.clearance / (required + 0.05))
        plane_t = (float(coeffs[0]), float(coeffs[1]), float(coeffs[2]), float(coeffs[3]))
        return PlacementEstimate(
            found=True, reason="ok", message=found.message, pose=Pose(position=_vec(pos), yaw=camera_yaw(frame)),
            surface_z=surface_z, plane=plane_t, vertical_offset=s.vertical_offset, clearance=spot.clearance,
            confidence=round(float(conf), 3), n_points=int(inliers.size), **base)

    def _target(self, frame: Frame, parsed: q.Query, categories: tuple[str, ...], estimate: type[E], max_points: int,
                min_pixels: int = 0, rim_px: int = 0) -> _Target | E:
        """What the query names, its pixels and their depth points (without the rim pixels, `rim_px` wide, whose
        depth does not continue the mask's interior); or the `estimate` saying why not (a bad query, not found,
        too few pixels, no valid depth)."""
        base: dict[str, Any] = {"query": parsed.text, "frame_stamp_ns": frame.stamp_ns}
        try:
            found = self.segmenter.find(frame, parsed, categories)
        except q.BadQuery as exc:
            return estimate(found=False, reason="bad_query", message=str(exc), **base)
        if found.segment is None:
            return estimate(found=False, reason=found.reason, message=found.message, **base)
        seg = found.segment
        idx = seg.indices
        bbox = geo.bbox_of(idx, frame.shape[1])
        base.update(label=seg.label, bbox=bbox)
        if idx.size < min_pixels:
            return estimate(found=False, reason="not_visible", message=f"{seg.label}: only {idx.size} pixels", **base)
        cloud = geo.lift(frame, idx[~geo.rim_outliers(frame, idx, rim_px)] if rim_px else idx, max_points)
        if cloud.n_valid == 0:
            return estimate(found=False, reason="depth_invalid", n_points=0,
                            message=f"{seg.label} is in view ({idx.size} px) but has no valid depth", **base)
        return _Target(found, seg, idx, bbox, cloud, base)

    def _held_radius(self, req: LocalizeRequest) -> float:
        size = req.object_size
        if size is None or not all(math.isfinite(v) and v > 0 for v in size.as_tuple()[:2]):
            return self.settings.default_object_radius
        return min(math.hypot(size.x, size.y) / 2, 1.0)

    def _clutter(self, frame: Frame, surf: np.ndarray, surface_z: float, bbox) -> np.ndarray:
        """Points standing on the surface's footprint: what a placed object could hit. Only the image region
        of the surface and above it (things standing on it rise above it in the image) is lifted."""
        h, w = frame.shape
        st = self.settings.clutter_stride
        y0 = max(0, bbox.y0 - h // 3) if bbox is not None else 0
        y1, x0, x1 = (bbox.y1, bbox.x0, bbox.x1) if bbox is not None else (h, 0, w)
        vv, uu = np.mgrid[y0:y1:st, x0:x1:st]
        idx = (vv * w + uu).ravel()
        pts = geo.lift(frame, idx).points
        lo = surf[:, :2].min(axis=0) - 0.05
        hi = surf[:, :2].max(axis=0) + 0.05
        inside = np.all((pts[:, :2] >= lo) & (pts[:, :2] <= hi), axis=1)
        return pts[inside]

    # ---- detections

    def detections(self, frame: Frame) -> Detections:
        items = []
        for seg in self.segmenter.detect(frame):
            if seg.category == "structure":
                continue
            items.append(self._detection(frame, seg))
        return Detections(frame_stamp_ns=frame.stamp_ns, segmenter=self.segmenter.type,
                          items=tuple(d for d in items if d is not None))

    def _detection(self, frame: Frame, seg: Segment) -> Detection | None:
        idx = seg.indices
        bbox = geo.bbox_of(idx, frame.shape[1])
        cloud = geo.lift(frame, idx, max_points=1500)
        cat = seg.category if seg.category in ("object", "surface", "furniture") else "other"
        catalog = _catalog(seg)
        if len(cloud.points) < 3:
            return Detection(label=seg.label, category=cat, bbox=bbox, confidence=0.0,  # type: ignore[arg-type]
                             catalog_size=catalog)
        lo = np.percentile(cloud.points, 2, axis=0)
        hi = np.percentile(cloud.points, 98, axis=0)
        if seg.category == "object":
            # Robust top and footprint, as for localize_object but without the outlier pass (cheap).
            hi[2] = np.percentile(cloud.points[:, 2], 99)
        conf = seg.score * min(1.0, cloud.n_valid / 200)
        return Detection(label=seg.label, category=cat, bbox=bbox, centroid=_vec((lo + hi) / 2),  # type: ignore[arg-type]
                         size=_vec(hi - lo), confidence=round(float(conf), 3), n_points=cloud.n_valid,
                         catalog_size=catalog)
