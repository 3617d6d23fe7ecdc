"""The RGB-D camera, rendered by MuJoCo (OpenGL, headless through EGL or OSMesa: `MUJOCO_GL`).

Colour, metric z-depth and per-geom segmentation from the vehicle's camera at its true pose. With
`realism="realistic"` the frames carry what a stereo RGB-D camera delivers: depth error growing with the square
of the distance (spatially correlated, as block matching gives), no depth beyond range or too close, holes at
depth discontinuities (occlusion edges), and colour with exposure that drifts frame to frame, sensor noise,
and the per-layout lighting of the scene. `ideal` gives the clean buffers.
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
DEPTH_K = 0.004  # sigma of the depth error = DEPTH_K * z^2 (m; ~1.6 cm at 2 m, like a 5 cm-baseline camera)
EDGE_JUMP = 0.06  # relative depth jump between neighbours that makes an occlusion edge
REALISM = ("realistic", "ideal", "harsh")  # harsh: the realistic camera (its extra is in the flight)
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
    """One MuJoCo offscreen context; the model is rebuilt from the snapshot's MJCF when its version changes."""

    def __init__(self, intr: Intrinsics = DEFAULT_INTRINSICS, realism: str = "realistic", seed: int = 0,
                 segmentation: bool = True) -> None:
        if realism not in REALISM:
            raise ValueError(f"unknown realism {realism!r}: {' or '.join(REALISM)}")
        self.intr, self.realism, self.segmentation = intr, realism, segmentation
        self.rng = np.random.default_rng(seed)
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
        self._drop = rng.random((h + pad, w + pad)) < 0.8
        self._bank_shape = (h, w)

    def _crop(self, bank: np.ndarray, h: int, w: int) -> np.ndarray:
        oy, ox = (int(v) for v in self.rng.integers(0, 64, 2))
        return bank[oy:oy + h, ox:ox + w]

    def _camera_model(self, rgb: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h, w = depth.shape
        rng = self.rng
        self._noise_banks(h, w)
        # Exposure: auto-exposure hunting around the right value, slowly (a random walk pulled back to 1).
        self.exposure = float(np.clip(self.exposure + 0.1 * (1.0 - self.exposure) + rng.normal(0, 0.03),
                                      0.75, 1.25))
        img = cv2.convertScaleAbs(rgb, alpha=self.exposure)
        img = cv2.subtract(cv2.add(img, self._crop(self._read_pos, h, w)), self._crop(self._read_neg, h, w))
        # Depth: correlated error ~ z^2 (disparity noise of block matching, coarse blocks), plus fine noise.
        z = depth.astype(np.float32)
        coarse = rng.normal(0.0, 1.0, (h // 8 + 1, w // 8 + 1)).astype(np.float32)
        field = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_LINEAR)
        noisy = z + DEPTH_K * z * z * (field + self._crop(self._fine, h, w))
        # Holes at occlusion edges: a relative jump to a neighbour (dilated max - eroded min over 3x3), mostly
        # lost.
        k = np.ones((3, 3), np.uint8)
        jump = cv2.dilate(z, k) - cv2.erode(z, k)
        edge = jump > EDGE_JUMP * np.maximum(z, 1e-3)
        noisy[edge & self._crop(self._drop, h, w)] = 0.0
        return img, noisy


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
