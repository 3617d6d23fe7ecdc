"""The RGB-D camera, rendered by MuJoCo (OpenGL, headless through EGL or OSMesa: `MUJOCO_GL`).

Colour, metric z-depth and per-geom segmentation from the vehicle's camera at its true pose. `realistic` (and
the worse `harsh`) give what a left-referenced active stereo RGB-D camera (an Intel RealSense D435) delivers:
depth error growing with the square of the distance (disparity noise, spatially correlated as block matching
gives), a per-unit scale bias, an invalid band left of near objects and at the left border (what the right
imager cannot see), flying pixels and holes at depth edges, dropouts on dark and textureless surfaces, no depth
beyond range or too close, depth a pixel or two off the colour, and colour with exposure that drifts frame to
frame and sensor noise; the publisher (app.py) adds the frame latency. `ideal` gives the clean buffers. Each
flaw's model, size and source: services/sim/README.md (Realism).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import mujoco
import numpy as np

from services.sim.core import Snapshot
from shared.frames import DEFAULT_INTRINSICS, base_to_camera
from shared.sensors import Intrinsics, pose_matrix

MAX_DEPTH_M = 6.0  # stereo range: farther pixels carry no depth
MIN_DEPTH_M = 0.2  # closer than this the stereo pair cannot match
NEAR_PLANE_M = 0.03  # OpenGL near plane, absolute: the floor 4-9 cm below a landed camera's lower half stays in view
FAR_PLANE_M = 30.0  # OpenGL far plane, absolute (the room is 8 m across)
EDGE_JUMP = 0.06  # relative depth jump over a 3x3 window that makes a depth edge
REALISM = ("realistic", "ideal", "harsh")


@dataclass(frozen=True)
class CameraFlaws:
    """What one realism level's camera does to the clean buffers. Sources of each figure: services/sim/README.md
    (Realism). All zero (the `ideal` level) leaves depth and colour untouched."""

    baseline_m: float = 0.05  # stereo baseline of the left-referenced pair (D435: 50 mm)
    subpixel_px: float = 0.0  # disparity noise (RMS, px): depth sigma = z^2 * subpixel / (baseline * fx)
    bias_px: float = 0.0  # largest disparity offset of a unit (px): a depth scale error growing with z
    occlusion: bool = False  # invalid band left of foreground edges and at the image's left border
    edge_drop: float = 0.0  # share of depth-edge pixels that lose their depth
    edge_flying: float = 0.0  # share of depth-edge pixels with a depth mixed between foreground and background
    dark_drop: float = 0.0  # dropout probability on a black surface (falls linearly to 0 at DARK_GREY)
    flat_drop: float = 0.0  # dropout probability on a textureless surface at 4 m (grows with z^2)
    random_drop: float = 0.0  # dropout probability anywhere
    misregistration_px: int = 0  # largest colour/depth offset of a unit (px, per axis)
    latency_s: float = 0.0  # delay from capture to publication (frames keep the capture stamp)
    exposure: bool = False  # auto-exposure wandering and read noise in colour


FLAWS = {
    "ideal": CameraFlaws(),
    "realistic": CameraFlaws(subpixel_px=0.07, bias_px=0.15, occlusion=True, edge_drop=0.45, edge_flying=0.35,
                             dark_drop=0.6, flat_drop=0.10, random_drop=0.005, misregistration_px=1,
                             latency_s=0.07, exposure=True),
    "harsh": CameraFlaws(subpixel_px=0.12, bias_px=0.3, occlusion=True, edge_drop=0.5, edge_flying=0.45,
                         dark_drop=0.9, flat_drop=0.35, random_drop=0.02, misregistration_px=2,
                         latency_s=0.15, exposure=True),
}
"""The camera model of each realism level."""

DARK_GREY = 50  # rendered grey level (0-255) under which low albedo starts to cost depth
FLAT_STD = 2.0  # local grey standard deviation (7x7) under which a surface counts as textureless
# MUJOCO_GL -> the module of the GLContext class MuJoCo picks for it (`mujoco.GLContext`).
GL_MODULES = {"egl": "mujoco.egl", "osmesa": "mujoco.osmesa", "glfw": "mujoco.glfw", "": "mujoco.glfw"}


def check_gl_platform() -> None:
    """Refuse, with the cause, to render on an OpenGL platform other than the one MUJOCO_GL names. MuJoCo reads
    MUJOCO_GL once, when it is first imported; `services.sim` sets the default (EGL) on its own import, so code
    that imports `mujoco` before any `services.sim` module gets MuJoCo's own default, GLFW, which needs a display:
    on a headless machine its context never exists, `MjrContext` raises a FatalError and the next renderer
    aborts the whole Python process (SIGABRT: what once killed a test run that imported mujoco first)."""
    import os

    wanted = os.environ.get("MUJOCO_GL", "").lower().strip()
    got = getattr(getattr(mujoco, "GLContext", None), "__module__", None)
    expected = GL_MODULES.get(wanted)
    if expected is not None and got != expected:
        raise RuntimeError(
            f"MuJoCo renders through {got or 'no OpenGL platform'} but MUJOCO_GL={wanted!r} asks for {expected}: "
            "mujoco was imported before services.sim set MUJOCO_GL (import services.sim first, or set MUJOCO_GL "
            "before starting Python)")


@dataclass
class Frame:
    """One rendered camera view: colour, depth in mm, instance ids and the true camera pose."""

    rgb: np.ndarray  # HxWx3 uint8
    depth_mm: np.ndarray  # HxW uint16, 0 = no return
    instance: np.ndarray  # HxW uint16, 0 = nothing (or the vehicle itself)
    camera_to_world: np.ndarray  # 4x4 pose of the optical frame (true)


class Renderer:
    """One MuJoCo offscreen context; the model is rebuilt from the snapshot's MJCF when its version changes.

    `unit` is the camera unit: its depth scale bias and colour/depth misregistration are drawn once from it (a
    unit's calibration error, the same for every frame and every run). `seed` seeds the per-frame noise. Both
    together reproduce a run frame for frame."""

    def __init__(self, intr: Intrinsics = DEFAULT_INTRINSICS, realism: str = "realistic", seed: int = 0,
                 segmentation: bool = True, unit: int = 0) -> None:
        if realism not in REALISM:
            raise ValueError(f"unknown realism {realism!r}: {', '.join(REALISM)}")
        self.intr, self.realism, self.segmentation = intr, realism, segmentation
        self.flaws = fl = FLAWS[realism]
        self.rng = np.random.default_rng(seed)
        # The unit's calibration error: a disparity offset (a depth scale error, 0.9-1.7 % at 2 m for the
        # realistic level) and a colour/depth offset of 1..misregistration_px px, each of either sign.
        urng = np.random.default_rng(np.random.SeedSequence([435, unit]))
        sign = -1.0 if urng.random() < 0.5 else 1.0
        self.bias_px = float(sign * urng.uniform(0.5, 1.0) * fl.bias_px)
        m = fl.misregistration_px
        shift = (0, 0)
        while m and shift == (0, 0):
            shift = (int(urng.integers(-m, m + 1)), int(urng.integers(-m, m + 1)))
        self.misregistration = shift  # (dx, dy): depth pixel (u, v) holds what colour shows at (u - dx, v - dy)
        self._version: tuple[int, int] | None = None
        self._renderer: mujoco.Renderer | None = None
        self.exposure = 1.0

    def _model(self, snap: Snapshot) -> None:
        key = (snap.version, hash(snap.xml))  # distinct layouts may share a version number (offline previews)
        if self._version == key and self._renderer is not None:
            return
        if self._renderer is not None:
            self._renderer.close()
        check_gl_platform()
        self.model = mujoco.MjModel.from_xml_string(snap.xml)
        # MuJoCo's clip planes are fractions of the model's extent (16.7 m for the room, so the MJCF's 0.01 put the
        # near plane at 0.17 m): set them absolute, or a landed camera 5 cm above the floor, pitched down, sees
        # the floor of its lower 75 % clipped away (black colour, no depth).
        self.model.vis.map.znear = NEAR_PLANE_M / self.model.stat.extent
        self.model.vis.map.zfar = FAR_PLANE_M / self.model.stat.extent
        scale = self.intr.height / DEFAULT_INTRINSICS.height
        if scale != 1.0:  # a coarse camera keeps the field of view
            self.model.vis.global_.offwidth, self.model.vis.global_.offheight = self.intr.width, self.intr.height
        self.data = mujoco.MjData(self.model)
        self._renderer = mujoco.Renderer(self.model, self.intr.height, self.intr.width)
        self._opt = mujoco.MjvOption()
        self._opt.geomgroup[3] = 0  # the gripper's fingers are out of the camera's view anyway
        self._version = key

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def render(self, snap: Snapshot) -> Frame:
        self._model(snap)
        r, d, m = self._renderer, self.data, self.model
        assert r is not None  # _model() made it
        d.qpos[:] = snap.qpos
        mujoco.mj_kinematics(m, d)
        mujoco.mj_camlight(m, d)
        r.update_scene(d, camera="camera", scene_option=self._opt)
        rgb = r.render().copy()
        r.enable_depth_rendering()
        depth = r.render().copy()
        r.disable_depth_rendering()
        if self.segmentation:
            r.enable_segmentation_rendering()
            seg = r.render()
            r.disable_segmentation_rendering()
            ids, types = seg[..., 0], seg[..., 1]
            lut = snap.geom_instance
            ok = (types == int(mujoco.mjtObj.mjOBJ_GEOM)) & (ids >= 0) & (ids < len(lut) - 1)
            instance = np.where(ok, lut[np.clip(ids, 0, len(lut) - 1)], 0).astype(np.uint16)
        else:
            instance = np.zeros(depth.shape, np.uint16)
        vehicle = m.body("vehicle").id
        x, y, z = (float(v) for v in d.xpos[vehicle])
        cam = pose_matrix(x, y, z, float(np.arctan2(d.xmat[vehicle][3], d.xmat[vehicle][0]))) @ base_to_camera()
        if self.realism != "ideal":
            rgb, depth = self._camera_model(rgb, depth)
        valid = (depth > MIN_DEPTH_M) & (depth < MAX_DEPTH_M) & np.isfinite(depth)
        depth_mm = np.where(valid, depth * 1000.0 + 0.5, 0).astype(np.uint16)
        return Frame(rgb, depth_mm, instance, cam)

    def _noise_banks(self, h: int, w: int) -> None:
        """Noise drawn once and cropped at a random offset per frame (drawing 1M normals costs 20 ms)."""
        if getattr(self, "_bank_shape", None) == (h, w):
            return
        rng, pad = self.rng, 64
        read = rng.normal(0.0, 2.0, (h + pad, w + pad, 3))
        self._read_pos = np.clip(read, 0, 255).astype(np.uint8)
        self._read_neg = np.clip(-read, 0, 255).astype(np.uint8)
        self._fine = rng.normal(0.0, 0.35, (h + pad, w + pad)).astype(np.float32)
        self._uniform = rng.random((h + pad, w + pad), dtype=np.float32)
        self._bank_shape = (h, w)

    def _crop(self, bank: np.ndarray, h: int, w: int) -> np.ndarray:
        oy, ox = (int(v) for v in self.rng.integers(0, 64, 2))
        return bank[oy:oy + h, ox:ox + w]

    def _camera_model(self, rgb: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h, w = depth.shape
        fl, rng = self.flaws, self.rng
        self._noise_banks(h, w)
        z = depth.astype(np.float32)
        bf = np.float32(fl.baseline_m * self.intr.fx)  # disparity (px) = bf / z
        disparity = bf / np.maximum(z, np.float32(1e-3))
        lost = self._dropouts(rgb, z, h, w)
        if fl.occlusion:
            lost |= self._occluded(disparity, w)
        # Disparity error (block matching): a correlated field over 8-px blocks plus fine noise, and the unit's
        # offset; depth = bf / disparity turns both into an error ~ z^2 (the RMS formula of Intel's tuning paper).
        coarse = rng.normal(0.0, 1.0, (h // 8 + 1, w // 8 + 1)).astype(np.float32)
        field = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_LINEAR)
        noise = np.float32(fl.subpixel_px) * (field + self._crop(self._fine, h, w))
        noisy = bf / np.maximum(disparity + noise + np.float32(self.bias_px), np.float32(1e-3))
        # Depth edges: a matching window straddling a jump matches part foreground, part background: some pixels
        # are lost, some get a depth in between (flying pixels).
        k = np.ones((3, 3), np.uint8)
        near, far = cv2.erode(z, k), cv2.dilate(z, k)
        edge = (far - near) > EDGE_JUMP * np.maximum(z, np.float32(1e-3))
        u = self._crop(self._uniform, h, w)
        flying = edge & (u < fl.edge_flying)
        mix = self._crop(self._uniform, h, w) * np.float32(0.7) + np.float32(0.15)
        noisy = np.where(flying, near + mix * (far - near), noisy)
        lost |= edge & (u >= fl.edge_flying) & (u < fl.edge_flying + fl.edge_drop)
        noisy[lost] = 0.0
        dx, dy = self.misregistration
        if dx or dy:
            noisy = shift_image(noisy, dx, dy)
        img = rgb
        if fl.exposure:
            # Auto-exposure hunting around the right value, slowly (a random walk pulled back to 1); read noise.
            self.exposure = float(np.clip(self.exposure + 0.1 * (1.0 - self.exposure) + rng.normal(0, 0.03),
                                          0.75, 1.25))
            img = cv2.convertScaleAbs(rgb, alpha=self.exposure)
            img = cv2.subtract(cv2.add(img, self._crop(self._read_pos, h, w)), self._crop(self._read_neg, h, w))
        return img, noisy

    def _dropouts(self, rgb: np.ndarray, z: np.ndarray, h: int, w: int) -> np.ndarray:
        """Pixels without depth on dark or textureless surfaces, in blobs (the matcher fails over regions)."""
        fl = self.flaws
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
        p = np.clip((DARK_GREY - grey) * np.float32(fl.dark_drop / DARK_GREY), 0.0, None)
        if fl.flat_drop:
            mean = cv2.blur(grey, (7, 7))
            var = cv2.blur(grey * grey, (7, 7)) - mean * mean
            flat = var < FLAT_STD * FLAT_STD
            p += np.where(flat, np.float32(fl.flat_drop / 16.0) * z * z, np.float32(0.0))
        p += np.float32(fl.random_drop)
        # A smooth field in [0, 1] (blobs of ~16 px) against the probability: the share lost follows p.
        blobs = cv2.resize(self.rng.random((h // 16 + 2, w // 16 + 2), dtype=np.float32), (w, h),
                           interpolation=cv2.INTER_CUBIC)
        out: np.ndarray = blobs < p
        return out

    @staticmethod
    def _occluded(disparity: np.ndarray, w: int) -> np.ndarray:
        """Pixels the right imager cannot see. Left-referenced pair, the right imager `baseline` to the right: a
        left pixel u lands at u - d(u) in the right image; it is hidden when a pixel to its right lands at or left
        of that (something nearer covers it), which leaves a band bf * (1/z_fg - 1/z_bg) px wide left of each
        foreground edge, and the left border up to d px sees nothing the right imager sees."""
        xr = np.arange(w, dtype=np.float32)[None, :] - disparity
        right_min = np.minimum.accumulate(xr[:, ::-1], axis=1)[:, ::-1]  # min over u' >= u
        hidden = np.zeros(xr.shape, bool)
        hidden[:, :-1] = xr[:, :-1] > right_min[:, 1:] + np.float32(0.5)
        out: np.ndarray = hidden | (xr < 0)
        return out


def shift_image(img: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """`img` moved by (dx, dy) pixels; what comes in from outside is 0 (no depth)."""
    out = np.zeros_like(img)
    h, w = img.shape[:2]
    out[max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)] = img[max(-dy, 0):h + min(-dy, 0),
                                                                    max(-dx, 0):w + min(-dx, 0)]
    return out


def snapshot_at(world, position: np.ndarray, yaw: float) -> Snapshot:
    """Put the vehicle of `world` at `position` (ENU body origin) with `yaw` and take a camera snapshot."""
    world.set_vehicle(np.asarray(position, float), yaw)
    return Snapshot(world.version, world.xml, world.state_vector(), world.geom_instance,
                    np.asarray(position, float), yaw)


def preview(world, position: np.ndarray, yaw: float, realism: str = "ideal") -> Frame:
    """Render `world` from a vehicle standing at `position` (ENU body origin) with `yaw`, offline."""
    snap = snapshot_at(world, position, yaw)
    r = Renderer(realism=realism)
    try:
        return r.render(snap)
    finally:
        r.close()
