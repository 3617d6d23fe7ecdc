"""`color` segmenter: classical OpenCV colour classes + blob shape/size filters + depth, for CPU-only cameras."""

from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from services.perception import geometry as geo
from services.perception import query as q
from services.perception.frames import Frame
from services.perception.segmenters.base import Found, Segment, Segmenter, register

# A colour class: an object whose albedo has this OpenCV HSV (H 0-180, S/V 0-255) and whose extent is about
# `dims` (long, short, height in metres). Shading multiplies the albedo, so H and S stay put and V drops:
# pixels are classified on (H, S) and a blob's brightest pixels must come close to the albedo's V.
# The defaults are the simulator's objects; a real deployment loads its own table (`color_catalog`).


@dataclass(frozen=True)
class ColorClass:
    """One object class of the color segmenter: its albedo in HSV, extent, category and tolerances."""

    name: str
    color: str
    hsv: tuple[int, int, int]
    dims: tuple[float, float, float]
    category: str = "object"
    tol_h: float = 7.0
    tol_s: float = 55.0


@dataclass(frozen=True)
class SurfaceClass:
    """A furniture top: albedo `rgb`. A flat pixel matches by chromaticity (r, g, b over their sum, within
    `chroma_tol`) and by brightness relative to the albedo (within `brightness`): room light and exposure
    scale the brightness of a top far more than they shift its hue."""

    name: str
    color: str
    rgb: tuple[int, int, int]
    chroma_tol: float = 0.03
    brightness: tuple[float, float] = (0.45, 1.15)
    category: str = "surface"
    min_extent: float = 0.35  # metres: a top narrower than this is an object of the same colour
    more_rgb: tuple[tuple[int, int, int], ...] = ()  # other colours of the same top (a sink's basin)


DEFAULT_OBJECTS = (
    ColorClass("red cup", "red", (0, 225, 215), (0.08, 0.08, 0.11)),
    ColorClass("purple cup", "purple", (136, 198, 200), (0.08, 0.08, 0.11)),
    # Printed cans (the textured look): white lettering and aluminium rims anti-alias into the label's pixels and
    # pull their saturation down; a wider saturation range keeps the label's blob whole.
    ColorClass("coke can", "crimson", (173, 239, 160), (0.066, 0.066, 0.12), tol_s=80.0),
    ColorClass("soda can", "blue", (108, 221, 225), (0.066, 0.066, 0.12), tol_s=80.0),
    ColorClass("tissue box", "cyan", (95, 136, 235), (0.24, 0.12, 0.10)),
    ColorClass("green bottle", "green", (66, 221, 150), (0.07, 0.07, 0.25)),
    ColorClass("apple", "lime", (40, 219, 210), (0.08, 0.08, 0.08)),
    ColorClass("orange", "orange", (16, 245, 250), (0.08, 0.08, 0.08)),
    ColorClass("banana", "yellow", (26, 213, 245), (0.19, 0.045, 0.04)),
    ColorClass("cracker box", "pink", (164, 147, 235), (0.16, 0.07, 0.21)),
    ColorClass("cardboard box", "brown", (15, 155, 165), (0.22, 0.16, 0.15)),
    ColorClass("hammer", "olive", (30, 255, 120), (0.30, 0.10, 0.035)),
)
DEFAULT_SURFACES = (
    SurfaceClass("table", "white", (225, 225, 220)),
    SurfaceClass("round table", "sage", (120, 165, 140)),
    SurfaceClass("wooden table", "wood", (150, 100, 55), chroma_tol=0.045),
    SurfaceClass("shelf", "beige", (205, 190, 160)),
    SurfaceClass("sink", "blue steel", (140, 165, 200)),
    SurfaceClass("counter", "dark grey", (70, 70, 75)),
)
SURFACE_HEIGHT = (0.3, 1.6)  # metres above the floor where furniture tops are


def load_catalog(path: str) -> tuple[tuple[ColorClass, ...], tuple[SurfaceClass, ...]]:
    """JSON {"objects": [{name, color, hsv, dims, ...}], "surfaces": [{name, color, rgb, ...}]}."""
    data = json.loads(Path(path).read_text())
    objs = tuple(ColorClass(**{**o, "hsv": tuple(o["hsv"]), "dims": tuple(o["dims"])}) for o in data.get("objects", []))
    surfs = tuple(SurfaceClass(**{**s, "rgb": tuple(s["rgb"]),
                                  "more_rgb": tuple(tuple(c) for c in s.get("more_rgb", ()))})
                  for s in data.get("surfaces", []))
    return objs, surfs


def robust_footprint(xy: np.ndarray) -> tuple[float, float]:
    """Long and short side of the footprint, measured between the 2nd and 98th percentiles along the axes
    of the minimum-area rectangle (a few stray rim pixels must not make an object look too big)."""
    (_, _), (_, _), angle = cv2.minAreaRect(xy.astype(np.float32))
    a = math.radians(angle)
    axes = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])
    proj = xy @ axes.T
    ext = np.percentile(proj, 98, axis=0) - np.percentile(proj, 2, axis=0)
    return float(ext.max()), float(ext.min())


# A blob whose 95th-percentile brightness (V) is below this share of its class's albedo is a shadow or a dark
# patch with a tint, not the object. Brightness cannot tell classes of one hue apart here: the realistic room
# light (key light 0.45-0.65) and the camera's auto-exposure (0.75-1.25) put a lit object anywhere from about
# 0.35 to 1.3 of its albedo, so an olive hammer (V 120) and a yellow banana (V 245) overlap; their sizes tell
# them apart. At 0.45 this check rejected the red cup on the shelf's shaded side for seconds on end while the
# vehicle hovered 2 m away (V 90-94 against a limit of 97), and a whole search then missed it.
DARK_SHARE = 0.25


def _hs_lut(classes: tuple[ColorClass, ...]) -> np.ndarray:
    """(H, S) -> 1 + index of the nearest class within its tolerance ellipse, 0 for none."""
    h = np.arange(180, dtype=np.float32)[:, None]
    s = np.arange(256, dtype=np.float32)[None, :]
    best = np.full((180, 256), np.inf, np.float32)
    lut = np.zeros((180, 256), np.uint8)
    for i, c in enumerate(classes):
        dh = np.abs(h - c.hsv[0])
        dh = np.minimum(dh, 180 - dh)
        d = (dh / c.tol_h) ** 2 + ((s - c.hsv[1]) / c.tol_s) ** 2
        take = (d <= 1.0) & (d < best)
        best[take] = np.broadcast_to(d, best.shape)[take]
        lut[take] = i + 1
    return lut


@register
class ColorSegmenter(Segmenter):
    """Objects: pixel -> colour class by a (hue, saturation) lookup table; connected blobs; each blob kept
    only when its brightness fits the albedo and its 3D extent (from depth) fits the class's size.
    Surfaces: pixels whose local normal (from depth) is near vertical, at furniture height, coloured like a
    known top."""

    type = "color"

    def start(self) -> None:
        path = getattr(self.settings, "color_catalog", "")
        self.objects, self.surfaces = load_catalog(path) if path else (DEFAULT_OBJECTS, DEFAULT_SURFACES)
        self.lut = _hs_lut(self.objects)
        self.kernel = np.ones((3, 3), np.uint8)
        self._cache: dict[tuple[int, int, str], list[Segment]] = {}
        self._lock = threading.Lock()

    def known_names(self, frame: Frame | None) -> list[str]:
        return [c.name for c in self.objects] + [s.name for s in self.surfaces]

    def detect(self, frame: Frame) -> list[Segment]:
        return self._cached(frame, "objects", self.detect_objects) + self._cached(frame, "surfaces",
                                                                                    self.detect_surfaces)

    def _cached(self, frame: Frame, part: str, fn) -> list[Segment]:
        """Several queries (and the detections) on one frame segment it once. Segments are read-only."""
        key = (id(frame), frame.stamp_ns, part)
        with self._lock:
            hit = self._cache.get(key)
        if hit is None:
            hit = fn(frame)
            with self._lock:
                self._cache = {k: v for k, v in self._cache.items() if k[1] == frame.stamp_ns and k[0] == id(frame)}
                self._cache[key] = hit
        return list(hit)

    def find(self, frame: Frame, query: q.Query, categories: tuple[str, ...]) -> Found:
        # Only run the half that can answer: object blobs or surface tops (each costs tens of ms).
        segments = []
        if "object" in categories:
            segments += self._cached(frame, "objects", self.detect_objects)
        if {"surface", "furniture"} & set(categories):
            segments += self._cached(frame, "surfaces", self.detect_surfaces)
        result = q.match(query, [s.candidate() for s in segments], self.known_names(frame), categories)
        if result.chosen is None:
            return Found(None, result.reason, result.message)
        return Found(next(s for s in segments if s.key == result.chosen.key), "ok", result.message)

    # ---- objects

    def detect_objects(self, frame: Frame) -> list[Segment]:
        hsv = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2HSV)
        cls = self.lut[hsv[..., 0], hsv[..., 1]]
        cls[hsv[..., 2] < 30] = 0
        h, w = cls.shape
        out: list[Segment] = []
        counts = np.bincount(cls.ravel(), minlength=len(self.objects) + 1)
        for ci in np.flatnonzero(counts[1:] >= self.settings.color_min_area_px) + 1:
            c = self.objects[int(ci) - 1]
            full = cls == ci
            # Work in the class's bounding box: most classes cover a small part of the image.
            rows, cols = np.flatnonzero(full.any(axis=1)), np.flatnonzero(full.any(axis=0))
            oy, ox = int(rows[0]), int(cols[0])
            roi = full[oy:int(rows[-1]) + 1, ox:int(cols[-1]) + 1]
            mask = cv2.morphologyEx(roi.astype(np.uint8), cv2.MORPH_OPEN, self.kernel)
            n, lab, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
            found: list[tuple[Segment, np.ndarray]] = []
            for k in range(1, n):
                area = int(stats[k, cv2.CC_STAT_AREA])
                if area < self.settings.color_min_area_px:
                    continue
                x, y, bw, bh = (int(stats[k, j]) for j in range(4))
                sv, su = np.nonzero(lab[y:y + bh, x:x + bw] == k)
                idx = (sv + y + oy) * w + (su + x + ox)
                checked = self._check_blob(frame, hsv, c, idx, len(out) + len(found))
                if checked is not None:
                    found.append(checked)
            out.extend(self._merge(found, c))
        return out

    @staticmethod
    def _merge(found: list[tuple[Segment, np.ndarray]], c: ColorClass) -> list[Segment]:
        """Blobs of one class closer than the object's size are one object split by an occluder."""
        groups: list[list[tuple[Segment, np.ndarray]]] = []
        for item in sorted(found, key=lambda f: -f[0].n_pixels):
            for g in groups:
                if np.linalg.norm(g[0][1][:2] - item[1][:2]) < max(c.dims):
                    g.append(item)
                    break
            else:
                groups.append([item])
        out = []
        for g in groups:
            seg = g[0][0]
            if len(g) > 1:
                idx = np.concatenate([s.indices for s, _ in g])
                seg = Segment(seg.key, seg.label, seg.category, seg.color, seg.score, seg.volume, int(idx.size),
                              _indices=idx)
            out.append(seg)
        return out

    def _check_blob(self, frame: Frame, hsv: np.ndarray, c: ColorClass, idx: np.ndarray,
                    key: int) -> tuple[Segment, np.ndarray] | None:
        v = hsv[..., 2].ravel()[idx]
        if idx.size == 0 or np.percentile(v, 95) < DARK_SHARE * c.hsv[2]:
            return None  # too dark for any light this object could be in
        cloud = geo.lift(frame, idx, max_points=600)
        if len(cloud.points) < 10:
            return None
        # Keep the blob's own depth layer: JPEG bleeds colour across edges onto whatever lies behind.
        d = frame.depth_mm.ravel()[cloud.pixels].astype(np.float32) * 0.001
        med = float(np.median(d))
        sel = np.flatnonzero(np.abs(d - med) < max(0.15, 1.2 * max(c.dims)))
        if sel.size < 10:
            return None
        pts = cloud.points[sel]
        z = pts[:, 2]
        height = float(np.percentile(z, 98) - np.percentile(z, 2))
        long_, short = robust_footprint(pts[:, :2])
        exp_long, exp_short, exp_h = max(c.dims[:2]), min(c.dims[:2]), c.dims[2]
        if long_ > 1.5 * exp_long + 0.04 or height > 1.5 * exp_h + 0.04 or short > 1.5 * max(exp_short, exp_h) + 0.04:
            return None  # too big: a surface or another object of that colour
        truncated = geo.touches_border(geo.bbox_of(idx, frame.shape[1]), frame.shape)
        if not truncated and long_ < 0.35 * exp_long and height < 0.35 * exp_h:
            return None  # a fleck, not the object
        fit = min(1.0, long_ / exp_long) * min(1.0, max(height, 0.01) / exp_h)
        score = float(np.clip(0.5 + 0.5 * fit, 0.0, 1.0))
        dropped = np.setdiff1d(cloud.pixels, cloud.pixels[sel]) if sel.size < len(cloud.pixels) else sel[:0]
        keep = np.setdiff1d(idx, dropped) if dropped.size else idx
        seg = Segment(key, c.name, c.category, c.color, score, long_ * short * max(height, 0.01), int(keep.size),
                      _indices=keep)
        return seg, pts.mean(axis=0)

    # ---- surfaces

    def detect_surfaces(self, frame: Frame, stride: int = 2) -> list[Segment]:
        h, w = frame.shape
        vv, uu = np.mgrid[0:h:stride, 0:w:stride]
        idx = (vv * w + uu).ravel()
        gh, gw = vv.shape
        d = frame.depth_mm.ravel()[idx].astype(np.float32) * 0.001
        intr = frame.intr
        pc = np.stack([(uu.ravel() - intr.cx) * d / intr.fx, (vv.ravel() - intr.cy) * d / intr.fy, d], axis=1)
        T = frame.world_from_camera  # noqa: N806
        pw = (pc @ T[:3, :3].T + T[:3, 3]).reshape(gh, gw, 3).astype(np.float32)
        valid = (d > 0).reshape(gh, gw)
        # Normal from the cross product of neighbour differences (both must have depth).
        dx = np.zeros_like(pw)
        dy = np.zeros_like(pw)
        dx[:, :-1] = pw[:, 1:] - pw[:, :-1]
        dy[:-1] = pw[1:] - pw[:-1]
        n = np.cross(dx, dy)
        nn = np.linalg.norm(n, axis=2) + 1e-9
        flat = (np.abs(n[..., 2]) / nn > math.cos(math.radians(12))) & valid
        flat[:, -1] = flat[-1] = False
        zf = pw[..., 2]
        flat &= (zf > SURFACE_HEIGHT[0]) & (zf < SURFACE_HEIGHT[1])
        if not flat.any():
            return []
        fy, fx = np.nonzero(flat)
        rgb = frame.rgb[fy * stride, fx * stride].astype(np.float32)  # only the flat pixels
        owner = np.array([i for i, s in enumerate(self.surfaces) for _ in (s.rgb, *s.more_rgb)])
        tols = np.array([s.chroma_tol for s in self.surfaces for _ in (s.rgb, *s.more_rgb)], np.float32)
        lo = np.array([s.brightness[0] for s in self.surfaces for _ in (s.rgb, *s.more_rgb)], np.float32)
        hi = np.array([s.brightness[1] for s in self.surfaces for _ in (s.rgb, *s.more_rgb)], np.float32)
        albedo = np.array([c for s in self.surfaces for c in (s.rgb, *s.more_rgb)], np.float32)
        # Chromaticity and relative brightness: the light's strength and the exposure scale a top's colour.
        total = rgb.sum(axis=1, keepdims=True) + 1e-3
        a_total = albedo.sum(axis=1)
        # Each pixel's chromaticity once (N x 3), then its distance to every albedo's (N x K): the same numbers as
        # dividing inside the broadcast, without K divisions per pixel (the profile's largest own-time cost).
        chroma = rgb / total
        chroma_d = np.sqrt(((chroma[:, None, :] - (albedo / a_total[:, None])[None]) ** 2).sum(axis=2))
        ratio = total / a_total[None]
        ok = (chroma_d < tols[None]) & (ratio >= lo[None]) & (ratio <= hi[None])
        # Nearest chromaticity among the classes whose brightness range fits.
        score = np.where(ok, chroma_d / tols[None], np.inf)
        nearest = score.argmin(axis=1)
        close = np.isfinite(score[np.arange(len(nearest)), nearest])
        cls = np.where(close, owner[nearest], -1)
        out: list[Segment] = []
        for i, s in enumerate(self.surfaces):
            pick = cls == i
            if np.count_nonzero(pick) * stride * stride < 4 * self.settings.color_min_area_px:
                continue
            mask = np.zeros((gh, gw), np.uint8)
            mask[fy[pick], fx[pick]] = 1
            mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, self.kernel)
            n_cc, lab, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
            if n_cc <= 1:
                continue
            best: tuple[float, np.ndarray] | None = None
            for k in range(1, n_cc):
                if stats[k, cv2.CC_STAT_AREA] * stride * stride < 4 * self.settings.color_min_area_px:
                    continue
                sel = (lab == k).ravel()
                xy = pw.reshape(-1, 3)[sel, :2]
                (_, _), (a, b), _ = cv2.minAreaRect(xy.astype(np.float32))
                # A brown box top is not a wooden table: furniture tops are wide.
                if min(a, b) < s.min_extent:
                    continue
                if best is None or a * b > best[0]:
                    best = (a * b, sel)
            if best is None:
                continue
            sel = best[1]
            out.append(Segment(1000 + i, s.name, s.category, s.color, 0.8, 0.0, int(sel.sum()) * stride * stride,
                               _indices=idx[sel]))
        return out
