"""`color` segmenter: classical OpenCV colour classes + blob shape/size filters + depth, for CPU-only cameras."""

from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass, replace
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


@dataclass(frozen=True)
class ToneClass:
    """An object with no hue of its own (bare steel, black plastic), which a hue lookup cannot find: it is a patch
    on a known furniture top that is unlike the top, and is told apart by its albedo's brightness, estimated
    through the top's known albedo (the light and the exposure that scale the top scale what lies on it)."""

    name: str
    color: str
    brightness: tuple[float, float]  # albedo brightness range (mean of R, G, B; 0-255)
    dims: tuple[float, float, float]  # long, short, height (m)
    category: str = "object"
    max_saturation: float = 90.0  # the patch's median HSV saturation: bare steel and black carry little


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
DEFAULT_TONES = (
    ToneClass("wrench", "silver", (60.0, 235.0), (0.20, 0.045, 0.02)),
    # Black handle, a red band, a thin steel shaft: the patch is mostly the handle. A black object's hue and
    # saturation are noise (and the top's colour bleeds into them through JPEG), so no saturation bound.
    ToneClass("screwdriver", "black", (0.0, 60.0), (0.18, 0.025, 0.025), max_saturation=256.0),
)
SURFACE_HEIGHT = (0.3, 1.6)  # metres above the floor where furniture tops are


def load_catalog(path: str) -> tuple[tuple[ColorClass, ...], tuple[SurfaceClass, ...], tuple[ToneClass, ...]]:
    """JSON {"objects": [{name, color, hsv, dims, ...}], "surfaces": [{name, color, rgb, ...}],
    "tones": [{name, color, brightness, dims, ...}]} ("tones" optional: objects without a hue of their own)."""
    data = json.loads(Path(path).read_text())
    objs = tuple(ColorClass(**{**o, "hsv": tuple(o["hsv"]), "dims": tuple(o["dims"])}) for o in data.get("objects", []))
    surfs = tuple(SurfaceClass(**{**s, "rgb": tuple(s["rgb"]),
                                  "more_rgb": tuple(tuple(c) for c in s.get("more_rgb", ()))})
                  for s in data.get("surfaces", []))
    tones = tuple(ToneClass(**{**t, "brightness": tuple(t["brightness"]), "dims": tuple(t["dims"])})
                  for t in data.get("tones", []))
    return objs, surfs, tones


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

# Tone classes (objects without a hue), developed on dev layouts 100-149, 200-239 and 300-339:
# - a pixel inside a top's outline (less TONE_RIM_PX of its rim) is unlike the top when its chromaticity is more
#   than TONE_CHROMA x the top's chroma tolerance off the top's albedo, or its brightness more than TONE_BRIGHTNESS
#   off the top's own within TONE_WINDOW_PX around it; an opening with TONE_KERNEL clears JPEG speckle and parts
#   under TONE_MIN_PART_PX; a part within TONE_CLEAR_PX of a coloured object's pixels is its shadow or its rim;
# - parts of one tone within TONE_GAP_PX of each other are one patch (a thin handle 3-4 px wide at 2 m breaks);
#   a patch needs TONE_MIN_AREA_PX, and one with more than TONE_HUED_SHARE of strongly saturated hue-class pixels
#   (S >= TONE_HUED_SAT) is a coloured object the hue classes refused;
# - a patch must rise TONE_MIN_RISE (or TONE_RISE_PER_M2 x distance^2: stereo depth noise grows with the square
#   of the range) above the top around it: tools rose 1.3-2.3 cm at 0.8-1.6 m; stains, seams and shadows
#   0-0.9 cm (one 1.7 cm at 2.9 m).
TONE_CHROMA = 1.5
TONE_BRIGHTNESS = 0.18
TONE_WINDOW_PX = 31
TONE_RIM_PX = 3
TONE_KERNEL = np.ones((2, 2), np.uint8)
TONE_MIN_PART_PX = 15
TONE_CLEAR_PX = 3
TONE_GAP_PX = 6
TONE_MIN_AREA_PX = 40
TONE_HUED_SAT = 120
TONE_HUED_SHARE = 0.3
TONE_MAX_TINT = 0.045
TONE_MIN_RISE = 0.01
TONE_RISE_PER_M2 = 0.0025


@dataclass
class _Part:
    """A connected part of a patch on a top: its pixels, its image box (x0, y0, x1, y1) and its top's height."""

    idx: np.ndarray
    box: tuple[int, int, int, int]
    top_z: float
    top_chroma: np.ndarray  # the top's albedo over its sum


def _near_groups(parts: list[_Part], gap: int) -> list[list[_Part]]:
    """Parts whose image boxes come within `gap` pixels of each other, transitively, are one group (the opening
    that clears JPEG speckle breaks a thin handle seen from 2 m into pieces a few pixels apart)."""
    group = list(range(len(parts)))

    def root(i: int) -> int:
        while group[i] != i:
            group[i] = group[group[i]]
            i = group[i]
        return i

    for i, a in enumerate(parts):
        for j in range(i + 1, len(parts)):
            b = parts[j]
            if (a.box[0] - gap <= b.box[2] and b.box[0] - gap <= a.box[2]
                    and a.box[1] - gap <= b.box[3] and b.box[1] - gap <= a.box[3]):
                group[root(j)] = root(i)
    out: dict[int, list[_Part]] = {}
    for i, p in enumerate(parts):
        out.setdefault(root(i), []).append(p)
    return list(out.values())


def _tint(rgb: np.ndarray, top_chroma: np.ndarray) -> float:
    """How far the mean chromaticity of `rgb` (N x 3) lies from every mix of grey and the top's chromaticity:
    a grey or black object shows grey plus what JPEG bleeds in from the top around it; any other colour is its own."""
    c = rgb.astype(np.float64).sum(axis=0)
    c = c / max(float(c.sum()), 1e-6)
    grey = np.full(3, 1 / 3)
    d = top_chroma - grey
    s = float(np.clip(np.dot(c - grey, d) / max(float(np.dot(d, d)), 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(c - (grey + s * d)))


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
        self.objects, self.surfaces, self.tones = (load_catalog(path) if path
                                                   else (DEFAULT_OBJECTS, DEFAULT_SURFACES, DEFAULT_TONES))
        self.lut = _hs_lut(self.objects)
        self.kernel = np.ones((3, 3), np.uint8)
        self._cache: dict[tuple[int, int, str], list[Segment]] = {}
        self._lock = threading.Lock()
        self._grids: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._tone_names = frozenset(t.name for t in self.tones)
        self._tone_words = frozenset(w for n in self._tone_names for w in q.words(n))

    def known_names(self, frame: Frame | None) -> list[str]:
        return [c.name for c in self.objects] + [t.name for t in self.tones] + [s.name for s in self.surfaces]

    def detect(self, frame: Frame) -> list[Segment]:
        return (self._cached(frame, "objects", self.detect_objects) + self._cached(frame, "tones", self.detect_tones)
                + self._cached(frame, "surfaces", self.detect_surfaces))

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
            if self._may_name_tone(query):  # needs the surface pass: only when the query could mean one
                segments += self._cached(frame, "tones", self.detect_tones)
        if {"surface", "furniture"} & set(categories):
            segments += self._cached(frame, "surfaces", self.detect_surfaces)
        result = q.match(query, [s.candidate() for s in segments], self.known_names(frame), categories)
        if result.chosen is None:
            return Found(None, result.reason, result.message)
        return Found(next(s for s in segments if s.key == result.chosen.key), "ok", result.message)

    def _may_name_tone(self, query: q.Query) -> bool:
        """Whether the query could be answered by a tone class: one of its words is in a tone class's name,
        names a family holding one, or its colour words cover a tone's colour."""
        return bool(self._tone_words.intersection(query.words)
                    or any(q.FAMILIES.get(w, frozenset()) & self._tone_names for w in query.words)
                    or any(t.color in covered for t in self.tones for c in query.colors
                           for covered in [q.COLOR_WORDS.get(c, frozenset({c}))]))

    # ---- objects

    def detect_objects(self, frame: Frame) -> list[Segment]:
        hsv = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2HSV)
        cls = self.lut[hsv[..., 0], hsv[..., 1]]
        cls[hsv[..., 2] < 30] = 0
        h, w = cls.shape
        out: list[Segment] = []
        serial = 0  # every blob's key, unique in the frame (a merge keeps its largest blob's key)
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
                checked = self._check_blob(frame, hsv, c, idx, serial)
                serial += 1
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
                seg = replace(seg, n_pixels=int(idx.size), _indices=idx, _compute=None)
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
                      (exp_long, exp_short, exp_h), _indices=keep)
        return seg, pts.mean(axis=0)

    # ---- objects without a hue: patches on a known top

    def detect_tones(self, frame: Frame) -> list[Segment]:
        """Objects of the tone classes (bare steel, black): on each furniture top the surface pass found, the
        pixels inside the top's outline that are unlike the top around them, in connected parts (`_top_parts`);
        neighbouring parts of one tone are one patch, which is the object when it is not a coloured object's (no
        strong hue in or beside it, no tint of its own) and its 3D shape fits (`_check_tone`)."""
        if not self.tones:
            return []
        h, w = frame.shape
        hsv = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2HSV)
        sat = hsv[..., 1]
        # Pixels a hue class takes with a strong saturation: an olive hammer grip the size checks refused is still
        # not steel. (Weakly saturated ones are not counted: the top's colour bleeds into a thin grey object's
        # pixels through JPEG's chroma subsampling.)
        hue_strong = (self.lut[hsv[..., 0], sat] > 0) & (sat >= TONE_HUED_SAT) & (hsv[..., 2] >= 30)
        # The coloured objects' own pixels are theirs, and a part touching them is their shadow or rim.
        hued8 = np.zeros((h, w), np.uint8)
        for o in self._cached(frame, "objects", self.detect_objects):
            hued8.ravel()[o.indices] = 1
        hued = cv2.dilate(hued8, np.ones((2 * TONE_CLEAR_PX + 1,) * 2, np.uint8)) > 0
        by_name = {s.name: s for s in self.surfaces}
        parts: dict[int, list[_Part]] = {}  # tone class -> its parts on every top
        unlike_all = np.zeros((h, w), bool)  # on any top, unlike it
        for top_seg in self._cached(frame, "surfaces", self.detect_surfaces):
            for i, part in self._top_parts(frame, top_seg, by_name[top_seg.label], sat, hued, unlike_all):
                parts.setdefault(i, []).append(part)
        hue_beside = unlike_all & hue_strong
        out: list[Segment] = []
        for i, found in parts.items():
            for group in _near_groups(found, TONE_GAP_PX):
                idx = np.concatenate([p.idx for p in group])
                if idx.size < TONE_MIN_AREA_PX:
                    continue
                if np.count_nonzero(hue_strong.ravel()[idx]) > TONE_HUED_SHARE * idx.size:
                    continue  # mostly a hue class's pixels: a coloured object the hue classes refused
                if _tint(frame.rgb.reshape(-1, 3)[idx], group[0].top_chroma) > TONE_MAX_TINT:
                    continue  # its own colour: a coloured object's shaded side or a shadow tinted by it
                if self._beside_hue(idx, w, h, hue_beside):
                    continue  # the bare part of a coloured object: a hammer's steel head by its olive grip
                seg = self._check_tone(frame, self.tones[i], idx, group[0].top_z, 2000 + len(out))
                if seg is not None:
                    out.append(seg)
        return out

    def _top_parts(self, frame: Frame, top_seg: Segment, sc: SurfaceClass, sat: np.ndarray, hued: np.ndarray,
                   unlike_all: np.ndarray) -> list[tuple[int, _Part]]:
        """The parts on one top with the tone class each fits: pixels inside the top's outline whose chromaticity is
        off the top's albedo or whose brightness is off the top's around them, not a coloured object's or beside
        one, in connected parts; a part's albedo brightness (its brightness over the top's, times the top's known
        albedo) and its saturation give its tone. Marks the top's unlike pixels in `unlike_all`."""
        h, w = frame.shape
        top_pts = geo.lift(frame, top_seg.indices, max_points=400).points
        if len(top_pts) < 10:
            return []
        top_z = float(np.median(top_pts[:, 2]))
        v, u = np.divmod(top_seg.indices, w)
        pad = TONE_RIM_PX + 2  # room for the rim's erosion inside the crop
        y0, y1 = max(int(v.min()) - pad, 0), min(int(v.max()) + pad, h)
        x0, x1 = max(int(u.min()) - pad, 0), min(int(u.max()) + pad, w)
        grid = np.zeros((y1 - y0, x1 - x0), np.uint8)
        grid[v - y0, u - x0] = 1
        top = cv2.dilate(grid, np.ones((2, 2), np.uint8))  # the surface pass's grid (stride 2), filled down-right
        # What lies on the top is inside its outline: the convex hull (tops are convex; a long object lying across
        # the top can split the top's pixels in two, and the surface pass keeps the larger part), less its rim,
        # where the depth mixes the top with its side and the floor.
        contours, _ = cv2.findContours(top, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        hull = np.zeros_like(top)
        cv2.fillConvexPoly(hull, cv2.convexHull(np.concatenate(contours)), 1)
        region = cv2.erode(hull, np.ones((2 * TONE_RIM_PX + 1,) * 2, np.uint8), borderValue=0) > 0
        rgb = frame.rgb[y0:y1, x0:x1].astype(np.float32)
        b = rgb.sum(axis=2)
        ch = rgb / (b[..., None] + 1e-3)
        albedos = np.array([sc.rgb, *sc.more_rgb], np.float32)
        chroma_off = np.ones(b.shape, bool)  # off every albedo's chromaticity (squared distances: no root)
        for a in albedos:
            chroma_off &= ((ch - a / a.sum()) ** 2).sum(axis=2) > (TONE_CHROMA * sc.chroma_tol) ** 2
        # The top's brightness around each pixel, from the top's own pixels only (normalised box filter).
        k = (TONE_WINDOW_PX, TONE_WINDOW_PX)
        topf = top.astype(np.float32)
        den = cv2.boxFilter(topf, -1, k, normalize=False)
        ratio = b / np.maximum(cv2.boxFilter(b * topf, -1, k, normalize=False) / np.maximum(den, 1e-6), 1e-3)
        patch = region & (chroma_off | (np.abs(ratio - 1.0) > TONE_BRIGHTNESS)) & (den > 0)
        unlike_all[y0:y1, x0:x1] |= patch
        patch &= ~hued[y0:y1, x0:x1]
        opened = cv2.morphologyEx(patch.astype(np.uint8), cv2.MORPH_OPEN, TONE_KERNEL)
        n, lab, stats, _ = cv2.connectedComponentsWithStats(opened, connectivity=8)
        a_bright = float(albedos[0].sum()) / 3.0
        top_chroma = albedos[0] / albedos[0].sum()
        out: list[tuple[int, _Part]] = []
        for k_ in range(1, n):
            if stats[k_, cv2.CC_STAT_AREA] < TONE_MIN_PART_PX:
                continue
            bx, by, bw, bh = (int(stats[k_, j]) for j in range(4))
            py, px_ = np.nonzero(lab[by:by + bh, bx:bx + bw] == k_)
            py, px_ = py + by, px_ + bx
            idx = (py + y0) * w + (px_ + x0)
            albedo = float(np.median(ratio[py, px_])) * a_bright
            s_med = float(np.median(sat.ravel()[idx]))
            for i, t in enumerate(self.tones):
                if t.brightness[0] <= albedo <= t.brightness[1] and s_med <= t.max_saturation:
                    out.append((i, _Part(idx, (bx + x0, by + y0, bx + x0 + bw, by + y0 + bh), top_z, top_chroma)))
                    break
        return out

    @staticmethod
    def _beside_hue(idx: np.ndarray, w: int, h: int, hue_unlike: np.ndarray) -> bool:
        """Whether at least TONE_MIN_PART_PX strongly hued pixels that are not the top lie within TONE_GAP_PX of
        the patch. (A screwdriver's red ferrule band does not reach it: found 24/24 from 0.5-0.8 m.)"""
        v, u = np.divmod(idx, w)
        y0, y1 = max(int(v.min()) - TONE_GAP_PX, 0), min(int(v.max()) + TONE_GAP_PX + 1, h)
        x0, x1 = max(int(u.min()) - TONE_GAP_PX, 0), min(int(u.max()) + TONE_GAP_PX + 1, w)
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        mask[v - y0, u - x0] = 1
        near = cv2.dilate(mask, np.ones((2 * TONE_GAP_PX + 1,) * 2, np.uint8)) > 0
        return int(np.count_nonzero(near & hue_unlike[y0:y1, x0:x1])) >= TONE_MIN_PART_PX

    def _check_tone(self, frame: Frame, t: ToneClass, idx: np.ndarray, top_z: float, key: int) -> Segment | None:
        """A patch that stands off the top around it (a stain, a seam or a shadow lies in it: the 90th percentile
        of its heights at least TONE_MIN_RISE above the top's, more where the depth is noisier) and whose 3D extent
        fits the tone class: long side, short side and height at most 1.5 times the class's + 4 cm (the depth's
        noise); long side at least 0.4 times the class's unless the image border cuts it (a screwdriver's black
        handle is half its length)."""
        cloud = geo.lift(frame, idx, max_points=600)
        if len(cloud.points) < 10:
            return None
        pts = cloud.points
        support = geo.support_height(frame, idx, top_z)
        if support is None:
            return None
        dist = float(np.linalg.norm(pts.mean(axis=0) - frame.world_from_camera[:3, 3]))
        if np.percentile(pts[:, 2], 90) - support < max(TONE_MIN_RISE, TONE_RISE_PER_M2 * dist * dist):
            return None
        height = float(np.percentile(pts[:, 2], 98) - np.percentile(pts[:, 2], 2))
        long_, short = robust_footprint(pts[:, :2])
        exp_long, exp_short, exp_h = max(t.dims[:2]), min(t.dims[:2]), t.dims[2]
        if long_ > 1.5 * exp_long + 0.04 or short > 1.5 * exp_short + 0.04 or height > 1.5 * exp_h + 0.04:
            return None
        if not geo.touches_border(geo.bbox_of(idx, frame.shape[1]), frame.shape) and long_ < 0.4 * exp_long:
            return None
        fit = min(1.0, long_ / exp_long)
        return Segment(key, t.name, t.category, t.color, float(0.5 + 0.5 * fit), long_ * short * max(height, 0.01),
                       int(idx.size), (exp_long, exp_short, exp_h), _indices=idx)

    # ---- surfaces

    def _grid(self, frame: Frame, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The surface pass's pixel grid for this frame size and camera: flat indices and each pixel's ray
        ((u - cx) / fx, (v - cy) / fy), computed once per camera."""
        intr = frame.intr
        key = (frame.shape, stride, intr.fx, intr.fy, intr.cx, intr.cy)
        hit = self._grids.get(key)
        if hit is None:
            h, w = frame.shape
            vv, uu = np.mgrid[0:h:stride, 0:w:stride]
            hit = ((vv * w + uu).ravel(), ((uu - intr.cx) / intr.fx).astype(np.float32),
                   ((vv - intr.cy) / intr.fy).astype(np.float32))
            self._grids = {key: hit}
        return hit

    def detect_surfaces(self, frame: Frame, stride: int = 2) -> list[Segment]:
        h, w = frame.shape
        idx, rx, ry = self._grid(frame, stride)
        gh, gw = rx.shape
        d = frame.depth_mm[::stride, ::stride].astype(np.float32) * np.float32(0.001)
        # World points per component, in float32 (nine multiply-adds per point, not a float64 N x 3 matmul: the
        # matmul was 40 % of this pass).
        T = frame.world_from_camera  # noqa: N806
        R, t = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)  # noqa: N806
        xc, yc = rx * d, ry * d
        pw = np.empty((gh, gw, 3), np.float32)
        for k in range(3):
            pw[..., k] = R[k, 0] * xc + R[k, 1] * yc + R[k, 2] * d + t[k]
        valid = d > 0
        # Normal from the cross product of neighbour differences (both must have depth): flat where its vertical
        # component is within 12 degrees, compared squared (no root).
        dx = np.zeros_like(pw)
        dy = np.zeros_like(pw)
        dx[:, :-1] = pw[:, 1:] - pw[:, :-1]
        dy[:-1] = pw[1:] - pw[:-1]
        nx = dx[..., 1] * dy[..., 2] - dx[..., 2] * dy[..., 1]
        ny = dx[..., 2] * dy[..., 0] - dx[..., 0] * dy[..., 2]
        nz = dx[..., 0] * dy[..., 1] - dx[..., 1] * dy[..., 0]
        nz2 = nz * nz
        flat = (nz2 > np.float32(math.cos(math.radians(12)) ** 2) * (nx * nx + ny * ny + nz2)) & (nz2 > 0) & valid
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
            closed = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, self.kernel)
            n_cc, lab, stats, _ = cv2.connectedComponentsWithStats(closed, connectivity=8)
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
