"""The simulated depth camera: the floor in view from the ground (the absolute near plane), and each flaw of the
stereo camera model present with its size in `realistic` (worse in `harsh`) and absent in `ideal`."""

from __future__ import annotations

import asyncio
import math

import cv2
import numpy as np
import pytest

from services.sim import render
from services.sim.layout import FLOOR_Z
from services.sim.render import FLAWS, MIN_DEPTH_M, Renderer, shift_image, snapshot_at
from services.sim.scenarios import STRUCTURE_IDS
from shared.frames import CAMERA_OFFSET_BODY, CAMERA_PITCH_DOWN, DEFAULT_INTRINSICS
from tests.perception.scenes import furniture, layout, manual_world


def floor_depth(rows: np.ndarray, height: float) -> np.ndarray:
    """z-depth of the floor along image rows `rows` for the camera `height` above it (pitched down, level body),
    inf where the row looks above the horizon."""
    s, c = math.sin(CAMERA_PITCH_DOWN), math.cos(CAMERA_PITCH_DOWN)
    down = s + c * (rows - DEFAULT_INTRINSICS.cy) / DEFAULT_INTRINSICS.fy  # downward part of the ray (z = 1)
    return np.where(down > 1e-6, height / np.maximum(down, 1e-6), np.inf)


@pytest.mark.parametrize("realism", ["ideal", "realistic"])
def test_a_landed_camera_sees_the_floor(realism, monkeypatch):
    """Landed (gear on the floor), the camera is CAMERA_OFFSET_BODY[2] - FLOOR_Z above it (0.2 m with the gear
    that reaches below the gripper's pads; 5 cm when this test was written), pitched 35 deg down: the lower half of
    the image is floor a few tens of centimetres from the lens. MuJoCo's near plane, a fraction of the model's
    extent (0.17 m here), clipped the nearest of it: black colour, no depth. With the absolute near plane it
    renders: floor in colour and segmentation, and in the clean z-buffer at the floor's distance (checked with the
    stereo minimum range lifted: a real stereo camera, like the simulated one, returns no depth nearer than
    0.2 m)."""
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
    # The clip plane itself, in metres: what the lens sees from 3 cm on (a cup just under it while grasping).
    assert r.model.vis.map.znear * r.model.stat.extent <= 0.03 + 1e-9
    lower = slice(DEFAULT_INTRINSICS.height // 2, DEFAULT_INTRINSICS.height)
    assert (f.instance[lower] == STRUCTURE_IDS["floor"]).mean() > 0.95
    black = (f.rgb[lower].max(axis=2) < 15).mean()
    assert black < 0.01, f"{100 * black:.0f} % of the lower half is black: clipped by the near plane"
    if realism == "ideal":
        # The z-buffer holds the floor where it is (lower half: 4-9 cm). Only the clean buffers: the realistic
        # stereo model has no depth there anyway (a disparity of 200-400 px: the right imager does not see it).
        rows = np.arange(DEFAULT_INTRINSICS.height, dtype=np.float64)[lower]
        expect = floor_depth(rows, height)[:, None] * np.ones((1, DEFAULT_INTRINSICS.width))
        z = raw.depth_mm[lower].astype(np.float64) / 1000.0
        floor = raw.instance[lower] == STRUCTURE_IDS["floor"]
        assert (z[floor] > 0).mean() > 0.95, "no depth on the floor of the lower half"
        assert (np.abs(z[floor] - expect[floor]) <= 0.005).mean() > 0.95
    # With the stereo minimum range, the floor nearer than 0.2 m has no depth, the floor beyond it has.
    all_rows = np.arange(DEFAULT_INTRINSICS.height, dtype=np.float64)
    near_rows = np.flatnonzero(floor_depth(all_rows, height) < MIN_DEPTH_M - 0.01)
    if near_rows.size:
        assert (f.depth_mm[near_rows] == 0).mean() > 0.99
    far_rows = np.flatnonzero(floor_depth(np.arange(DEFAULT_INTRINSICS.height, dtype=np.float64),
                                          height) > MIN_DEPTH_M + 0.03)
    band = f.depth_mm[far_rows]
    on_floor = f.instance[far_rows] == STRUCTURE_IDS["floor"]
    assert on_floor.sum() > 2000
    assert (band[on_floor] > 0).mean() > 0.8


# ---- the stereo camera's flaws: statistics on seeded MuJoCo frames against the clean `ideal` render of the same
# snapshot (primitive look: the same for every level), present in `realistic` and absent in `ideal`.

BF = FLAWS["realistic"].baseline_m * DEFAULT_INTRINSICS.fx  # disparity (px) x depth (m)


@pytest.fixture(scope="module")
def ideal():
    r = Renderer(realism="ideal")
    yield r
    r.close()


@pytest.fixture(scope="module")
def realistic():
    r = Renderer(realism="realistic", seed=5, unit=5)
    yield r
    r.close()


@pytest.fixture(scope="module")
def machine_scene():
    """A black coffee machine 1.3 m ahead of the camera, in front of the floor and the far wall; a white table
    to the right of it, farther away."""
    world = manual_world(furniture("coffee machine", 1.3, 0.0), furniture("table", 1.8, -1.1))
    return world, snapshot_at(world, np.array([0.0, 0.0, 0.9]), 0.0)


def metres(depth_mm: np.ndarray) -> np.ndarray:
    return depth_mm.astype(np.float64) / 1000.0


def aligned(r: Renderer, depth_mm: np.ndarray) -> np.ndarray:
    """The depth moved back onto the colour image by the unit's known misregistration."""
    dx, dy = r.misregistration
    return shift_image(depth_mm, -dx, -dy)


def test_ideal_is_clean_and_realistic_is_reproducible(machine_scene, ideal):
    _, snap = machine_scene
    a, b = ideal.render(snap), ideal.render(snap)
    assert np.array_equal(a.depth_mm, b.depth_mm) and np.array_equal(a.rgb, b.rgb)
    assert ideal.bias_px == 0.0 and ideal.misregistration == (0, 0)
    first = [Renderer(realism="realistic", seed=9, unit=2) for _ in range(2)]
    try:
        x, y = (r.render(snap) for r in first)
        assert np.array_equal(x.depth_mm, y.depth_mm) and np.array_equal(x.rgb, y.rgb)
        assert not np.array_equal(x.depth_mm, a.depth_mm)
    finally:
        for r in first:
            r.close()


@pytest.mark.parametrize("level", ["realistic", "harsh"])
def test_scale_bias_per_unit(machine_scene, ideal, level):
    """A disparity offset drawn per unit: depth off by a factor that grows with z, 0.9-1.7 % at 2 m in
    `realistic` (D435 product page: depth accuracy < 2 % at 2 m), 1.7-3.4 % in `harsh`, of either sign across
    units, the same for every frame of a unit."""
    _, snap = machine_scene
    clean = metres(ideal.render(snap).depth_mm)
    lo, hi = {"realistic": (0.008, 0.018), "harsh": (0.016, 0.036)}[level]
    biases = []
    for unit in range(6):
        r = Renderer(realism=level, seed=unit, unit=unit)
        try:
            rel = []
            for _ in range(3):
                z = metres(aligned(r, r.render(snap).depth_mm))
                ok = (z > 0) & (clean > 1.8) & (clean < 2.2)
                rel.append(float(np.median(z[ok] / clean[ok] - 1.0)))
        finally:
            r.close()
        expect = -r.bias_px * 2.0 / BF  # first order of bf / (bf / z + offset) at z = 2 m
        assert abs(np.mean(rel) - expect) < 0.003, (unit, rel, expect)
        assert lo < abs(np.mean(rel)) < hi, (unit, rel)
        assert np.ptp(rel) < 0.004  # one unit, one bias: its frames agree
        biases.append(np.mean(rel))
    assert min(biases) < 0 < max(biases)


def left_edges(clean: np.ndarray) -> list[tuple[int, int, int]]:
    """(row, column of the first foreground pixel, expected band width px) where a row steps from a far
    background onto a nearer surface (left to right) and the band is wide enough to measure."""
    out = []
    for v in range(0, clean.shape[0], 4):
        row = clean[v]
        for u in range(30, clean.shape[1] - 1):
            zb, zf = row[u], row[u + 1]
            if zb > 0 and zf > 0 and zf < 0.8 * zb:
                width = BF * (1.0 / zf - 1.0 / zb)
                if 5 <= width < 25:
                    out.append((v, u + 1, int(width)))
    return out


def test_occlusion_band_left_of_near_objects(machine_scene, ideal, realistic):
    """Left-referenced stereo with the right imager to the right: the background just left of a foreground edge is
    hidden from the right imager; the band is baseline * fx * (1/z_fg - 1/z_bg) px wide. Right of the object the
    background keeps its depth."""
    _, snap = machine_scene
    clean = metres(ideal.render(snap).depth_mm)
    edges = left_edges(clean)
    assert len(edges) > 20, "the scene has no measurable foreground edge"
    z = aligned(realistic, realistic.render(snap).depth_mm)
    inside, beyond, ideal_inside, right_side = [], [], [], []
    for v, u, width in edges:
        inside.append((z[v, u - width + 1:u - 1] == 0).mean())  # the pixel at the edge itself may fly or drop
        beyond.append((z[v, u - 2 * width - 4:u - width - 2] == 0).mean())
        ideal_inside.append((clean[v, u - width + 1:u - 1] == 0).mean())
    # The same rows' right edges (foreground onto a farther background, left to right): no band.
    for v, u, width in edges:
        row = clean[v]
        right = next((k for k in range(u, len(row) - 1) if row[k + 1] > 1.25 * row[k] > 0), None)
        if right is not None and right + width + 3 < len(row):
            right_side.append((z[v, right + 3:right + width + 3] == 0).mean())
    assert np.mean(inside) > 0.9
    assert np.mean(beyond) < 0.4  # a band, not a hole: the background farther left has depth again
    assert len(right_side) > 10 and np.mean(right_side) < 0.3
    assert np.mean(ideal_inside) == 0.0


def test_flying_pixels_at_depth_edges(machine_scene, ideal, realistic):
    """At a depth edge some pixels get a depth between foreground and background (a matching window straddling
    the edge), not one of the two."""
    _, snap = machine_scene
    clean = metres(ideal.render(snap).depth_mm)
    k = np.ones((3, 3), np.uint8)
    near, far = cv2.erode(clean, k), cv2.dilate(clean, k)
    edge = (clean > 0) & (near > 0) & (far - near > 0.3)
    assert edge.sum() > 200

    def between(z: np.ndarray) -> float:
        off = np.abs(z - clean) > 0.2 * (far - near)  # neither its own surface (nor noise on it)
        mixed = (z > near + 0.1 * (far - near)) & (z < far - 0.1 * (far - near)) & off
        return float(mixed[edge].mean())

    assert between(clean) < 0.01
    flying = between(metres(aligned(realistic, realistic.render(snap).depth_mm)))
    # 35 % of edge pixels fly (some of them then fall in the occlusion band and lose their depth instead).
    assert 0.15 < flying < FLAWS["realistic"].edge_flying + 0.05


def test_dropouts_on_dark_surfaces(machine_scene, ideal, realistic):
    """Low albedo (the black coffee machine) loses much of its depth; a white table at a similar distance keeps
    nearly all of it; the ideal camera loses none."""
    world, snap = machine_scene
    clean_frame = ideal.render(snap)

    def surface(name: str) -> np.ndarray:
        ent = next(e for e in world.entities if e.name == name)
        # Away from edges and bands.
        mask = cv2.erode((clean_frame.instance == ent.id).astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        assert mask.sum() > 500, f"{name} hardly in view"
        return mask & (metres(clean_frame.depth_mm) < 2.5)

    dark, white = surface("coffee machine"), surface("table")
    lost_dark, lost_white = [], []
    for _ in range(4):
        z = aligned(realistic, realistic.render(snap).depth_mm)
        lost_dark.append((z[dark] == 0).mean())
        lost_white.append((z[white] == 0).mean())
    assert np.mean(lost_dark) > 0.25
    assert np.mean(lost_white) < 0.05
    assert (clean_frame.depth_mm[dark] == 0).mean() == 0.0


def test_colour_depth_misregistration(machine_scene, ideal, realistic):
    """The depth image sits a pixel or two off the colour image (a unit's extrinsic calibration error): the shift
    that best matches the clean depth is the unit's, and not zero."""
    _, snap = machine_scene
    clean = ideal.render(snap).depth_mm.astype(np.float64)
    z = realistic.render(snap).depth_mm.astype(np.float64)

    def mismatch(depth: np.ndarray, dx: int, dy: int) -> float:
        ref = shift_image(clean, dx, dy)
        ok = (depth > 0) & (ref > 0)
        # Pixels on another surface than the reference's (edges): the bias and the noise stay far below 10 %.
        return float(np.mean(np.abs(depth[ok] - ref[ok]) > 0.1 * ref[ok]))

    shifts = [(dx, dy) for dx in range(-3, 4) for dy in range(-3, 4)]
    best = min(shifts, key=lambda s: mismatch(z, *s))
    assert best == realistic.misregistration != (0, 0)
    assert min(shifts, key=lambda s: mismatch(clean, *s)) == (0, 0)
    assert max(abs(c) for c in realistic.misregistration) <= FLAWS["realistic"].misregistration_px
    units = {Renderer(realism="harsh", unit=u).misregistration for u in range(12)}
    assert max(max(abs(c) for c in s) for s in units) == FLAWS["harsh"].misregistration_px == 2


def test_levels_order():
    """harsh is worse than realistic in every flaw; ideal has none."""
    ideal_f, real, harsh = FLAWS["ideal"], FLAWS["realistic"], FLAWS["harsh"]
    for name in ("subpixel_px", "bias_px", "edge_drop", "edge_flying", "dark_drop", "flat_drop", "random_drop",
                 "misregistration_px", "latency_s"):
        assert getattr(ideal_f, name) == 0
        assert getattr(harsh, name) > getattr(real, name) > 0, name
    assert not ideal_f.occlusion and real.occlusion and harsh.occlusion
    assert 0.03 <= real.latency_s <= 0.15


class _Bus:
    """Records what the camera loop publishes, in order; stops the loop after two colour frames."""

    def __init__(self, stop: asyncio.Event, keys) -> None:
        self.log: list[tuple[str, object]] = []
        self.stop, self.keys = stop, keys

    def publish(self, key: str, payload, reliable: bool = True) -> None:
        self.log.append((key, payload))
        if key == self.keys.camera_color and sum(k == key for k, _ in self.log) >= 2:
            self.stop.set()


def test_frames_are_published_the_latency_after_their_capture():
    """The level's latency (or AERMANI_SIM_CAMERA_LATENCY_S) delays the frames, not tf: each frame is scheduled
    the latency after its capture (less what the render took: here a frozen clock, so the render took nothing),
    with its capture stamp, the same as its tf's, which went out at once. Without latency nothing is scheduled."""
    from services.sim.app import CameraPublisher
    from services.sim.core import SimCore
    from services.sim.settings import SimSettings
    from shared.messages import Scenario
    from shared.sensors import parse_color, parse_transforms

    core = SimCore(Scenario(seed=1))
    for level in ("ideal", "realistic", "harsh"):
        cam = CameraPublisher(None, core, SimSettings(camera=False, realism=level))
        assert cam.latency_s == FLAWS[level].latency_s
    assert CameraPublisher(None, core, SimSettings(camera=False, camera_latency_s=0.2)).latency_s == 0.2

    def run(latency: float) -> tuple[list[str], list[float]]:
        settings = SimSettings(realism="ideal", render_always=True, fps=4.0, camera_latency_s=latency)
        cam = CameraPublisher(None, core, settings)
        cam.clock = lambda: 100.0
        delays: list[float] = []

        async def go() -> list[tuple[str, object]]:
            loop = asyncio.get_running_loop()
            call_later = loop.call_later

            def spy(delay, callback, *args):
                if getattr(callback, "__name__", "") == "_publish_late":
                    delays.append(delay)
                return call_later(delay, callback, *args)

            loop.call_later = spy  # type: ignore[method-assign]
            stop = asyncio.Event()
            cam.bus = bus = _Bus(stop, settings.keys)  # type: ignore[assignment]
            await asyncio.wait_for(cam.run(stop), 120.0)  # a hang guard, not a timing check
            return bus.log

        try:
            log = asyncio.run(go())
        finally:
            cam.close()
        keys = settings.keys
        color = next(p for k, p in log if k == keys.camera_color)
        tf = next(p for k, p in log if k == keys.tf)
        assert isinstance(color, bytes) and isinstance(tf, bytes)
        assert parse_color(color)[0] == next(iter(parse_transforms(tf).values()))[0]
        seq = ["tf" if k == keys.tf else "color" for k, _ in log if k in (keys.tf, keys.camera_color)]
        return seq, delays

    seq, delays = run(0.0)
    assert seq[:4] == ["tf", "color", "tf", "color"] and delays == []
    seq, delays = run(0.5)
    # Each frame was scheduled 0.5 s after its capture; its tf went out at once (whether the next frame's tf
    # also precedes it depends on how long that render takes: not checked).
    assert seq[0] == "tf" and "color" in seq and len(delays) >= 2 and all(d == 0.5 for d in delays)
