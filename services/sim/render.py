"""CPU RGB-D camera: Open3D raycasting gives z-depth, instance ids and normals; colour is Lambert-shaded albedo."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from services.sim.core import Snapshot
from services.sim.world import Entity, World
from shared.frames import DEFAULT_INTRINSICS, base_to_camera
from shared.sensors import Intrinsics, pose_matrix

MAX_DEPTH_M = 10.0
INVALID_ID = o3d.t.geometry.RaycastingScene.INVALID_ID
_LIGHT = np.array([0.35, 0.25, 1.0]) / np.linalg.norm([0.35, 0.25, 1.0])


@dataclass
class Frame:
    rgb: np.ndarray  # HxWx3 uint8
    depth_mm: np.ndarray  # HxW uint16, 0 = no return
    instance: np.ndarray  # HxW uint16, 0 = nothing
    camera_to_world: np.ndarray  # 4x4 pose of the optical frame


def _unit_mesh(shape: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (centred on the origin, unit extent) and triangles of a primitive."""
    if shape == "box":
        m = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)
        m.translate((-0.5, -0.5, -0.5))
    elif shape == "cylinder":
        m = o3d.geometry.TriangleMesh.create_cylinder(radius=0.5, height=1.0, resolution=24)
    else:
        m = o3d.geometry.TriangleMesh.create_sphere(radius=0.5, resolution=10)
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.triangles, dtype=np.uint32)


_UNIT = {s: _unit_mesh(s) for s in ("box", "cylinder", "sphere")}


def entity_mesh(e: Entity) -> tuple[np.ndarray, np.ndarray]:
    """World-frame vertices and triangles of one entity."""
    v, t = _UNIT[e.shape]
    v = v * np.array(e.size)
    c, s = math.cos(e.yaw), math.sin(e.yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (v @ rot.T + e.center).astype(np.float32), t


class Renderer:
    """Casts one ray per pixel (directions cached in the camera frame with z = 1, so t_hit is z-depth)."""

    def __init__(self, intr: Intrinsics = DEFAULT_INTRINSICS, seed: int = 7) -> None:
        self.intr = intr
        u, v = np.meshgrid(np.arange(intr.width, dtype=np.float64), np.arange(intr.height, dtype=np.float64))
        self._dirs_cam = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)],
                                  axis=-1).astype(np.float32)
        self._inv_norm = (1.0 / np.linalg.norm(self._dirs_cam, axis=-1)).astype(np.float32)
        self._rays = np.empty((intr.height, intr.width, 6), dtype=np.float32)
        self._light = _LIGHT.astype(np.float32)
        # Multiplicative grain on floor and walls (a few percent), fixed so the image is stable.
        self._noise = np.random.default_rng(seed).normal(0.0, 0.015, (intr.height, intr.width)).astype(np.float32)
        self._scene: o3d.t.geometry.RaycastingScene | None = None
        self._key: tuple | None = None
        self._lut = np.zeros(1, dtype=np.uint16)
        self._palette = np.zeros((1, 3), dtype=np.float32)
        self._floor_ids: set[int] = set()
        self.rebuilds = 0

    def _ensure_scene(self, world: World) -> None:
        held = world.attached()
        key = (world.version, None if held is None else (tuple(np.round(held.center, 4)), round(held.yaw, 4)))
        if key == self._key and self._scene is not None:
            return
        scene = o3d.t.geometry.RaycastingScene()
        lut = []
        max_id = max(e.id for e in world.entities)
        palette = np.zeros((max_id + 1, 3), dtype=np.float32)
        for e in world.entities:
            verts, tris = entity_mesh(e)
            scene.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(tris))
            lut.append(e.id)
            palette[e.id] = e.rgb
        self._scene = scene
        self._lut = np.array(lut + [0], dtype=np.uint16)  # last entry: misses
        self._palette = palette
        self._textured = np.zeros(max_id + 1, dtype=bool)
        for e in world.entities:
            if e.category == "structure":
                self._textured[e.id] = True
        self._key = key
        self.rebuilds += 1

    def camera_pose(self, position: np.ndarray, yaw: float) -> np.ndarray:
        return pose_matrix(float(position[0]), float(position[1]), float(position[2]), yaw) @ base_to_camera()

    def render(self, snap: Snapshot) -> Frame:
        self._ensure_scene(snap.world)
        assert self._scene is not None
        cam = self.camera_pose(snap.position, snap.yaw)
        rot, origin = cam[:3, :3].astype(np.float32), cam[:3, 3].astype(np.float32)
        dirs = self._rays[..., 3:]
        np.matmul(self._dirs_cam, rot.T, out=dirs)
        self._rays[..., :3] = origin
        ans = self._scene.cast_rays(o3d.core.Tensor.from_numpy(self._rays))
        t = ans["t_hit"].numpy()
        gid = ans["geometry_ids"].numpy()
        normals = ans["primitive_normals"].numpy()
        valid = (t <= MAX_DEPTH_M) & (gid != INVALID_ID)  # inf fails the first test
        depth = np.where(valid, t * 1000.0 + 0.5, 0).astype(np.uint16)
        inst = self._lut[np.where(valid, gid, len(self._lut) - 1)]

        # Lambert from a fixed overhead light plus a dim headlight, with normals turned towards the camera.
        facing = np.einsum("hwc,hwc->hw", normals, dirs)
        lam = normals @ self._light
        lam *= -np.sign(facing)
        np.clip(lam, 0.0, None, out=lam)
        shade = 0.30 + 0.50 * lam + 0.25 * np.abs(facing) * self._inv_norm
        textured = self._textured[inst]
        if textured.any():
            # A floor/wall tile pattern gives the scene texture without disturbing object colours.
            tt = t[textured][:, None]
            hit = origin + dirs[textured] * tt
            tile = np.floor(hit * 2.0).sum(axis=1) % 2
            shade[textured] *= 1.0 - 0.08 * tile
            shade[textured] += self._noise[textured]
        shade[~valid] = 0.0
        rgb = self._palette[inst] * shade[..., None]
        np.clip(rgb, 0, 255, out=rgb)
        return Frame(rgb.astype(np.uint8), depth, inst, cam)
