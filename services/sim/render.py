"""CPU RGB-D camera: Open3D raycasting gives z-depth, instance ids and normals; colour is Lambert-shaded albedo."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from services.sim.core import Snapshot
from services.sim.world import Entity, World
from shared.frames import DEFAULT_INTRINSICS, Mount
from shared.sensors import Intrinsics, pose_matrix

MAX_DEPTH_M = 10.0
INVALID_ID = o3d.t.geometry.RaycastingScene.INVALID_ID
_SUN = np.array([0.35, 0.25, 1.0]) / np.linalg.norm([0.35, 0.25, 1.0])
_FILL = np.array([-0.6, -0.75, 0.3]) / np.linalg.norm([-0.6, -0.75, 0.3])
TILE = 0.5  # floor/wall tile size, metres: texture for the eye and for feature-based consumers
SINK_CELL = 0.05
SINK_RIM = 0.1  # the basin is drawn inside this rim (visual only: objects still rest on the top plane)
BASIN_RGB = (105, 115, 125)


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


def _tiled_box(size: tuple[float, float, float], cell: float = TILE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A box centred on the origin whose faces are split into about TILE-sized quads (outward triangles),
    with a checkerboard parity per triangle."""
    half = np.array(size) / 2
    verts: list[np.ndarray] = []
    tris: list[np.ndarray] = []
    parity: list[np.ndarray] = []
    n = 0
    for axis in range(3):
        a1, a2 = [i for i in range(3) if i != axis]
        k1 = max(1, int(math.ceil(size[a1] / cell)))
        k2 = max(1, int(math.ceil(size[a2] / cell)))
        g1 = np.linspace(-half[a1], half[a1], k1 + 1)
        g2 = np.linspace(-half[a2], half[a2], k2 + 1)
        for sign in (-1.0, 1.0):
            m1, m2 = np.meshgrid(g1, g2, indexing="ij")
            v = np.zeros((k1 + 1, k2 + 1, 3))
            v[..., a1], v[..., a2], v[..., axis] = m1, m2, sign * half[axis]
            idx = np.arange((k1 + 1) * (k2 + 1)).reshape(k1 + 1, k2 + 1) + n
            a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
            t = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
            i1, i2 = np.meshgrid(np.arange(k1), np.arange(k2), indexing="ij")
            parity.append(np.tile(((i1 + i2) % 2).reshape(-1), 2))
            # Orient every face outward: (e_a1 x e_a2) points along +axis for a cyclic (a1, a2, axis).
            if (sign > 0) != ((a1, a2, axis) in ((0, 1, 2), (1, 2, 0), (2, 0, 1))):
                t = t[:, ::-1]
            verts.append(v.reshape(-1, 3))
            tris.append(t)
            n += (k1 + 1) * (k2 + 1)
    return np.concatenate(verts), np.concatenate(tris).astype(np.uint32), np.concatenate(parity)


def entity_mesh(e: Entity) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """World-frame vertices, triangles and (structure only) tile parity of one entity."""
    parity = None
    if e.category == "structure" and e.shape == "box":
        v, t, parity = _tiled_box(e.size)
    elif e.name == "sink":
        v, t, _ = _tiled_box(e.size, SINK_CELL)  # fine top grid so the basin can be drawn in it
    else:
        v, t = _UNIT[e.shape]
        v = v * np.array(e.size)
    c, s = math.cos(e.yaw), math.sin(e.yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (v @ rot.T + e.center).astype(np.float32), t, parity


def _triangle_colors(e: Entity, verts: np.ndarray, tris: np.ndarray, parity: np.ndarray | None) -> np.ndarray:
    """Flat-shaded colour of every triangle: albedo x (ambient + sun + fill), tiles on structure."""
    p = verts[tris.astype(np.int64)]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    shade = 0.38 + 0.55 * np.clip(n @ _SUN, 0, None) + 0.22 * np.clip(n @ _FILL, 0, None)
    if parity is not None:
        shade = shade * (1.0 - 0.09 * parity)
    albedo = np.tile(np.array(e.rgb, dtype=np.float64), (len(tris), 1))
    if e.name == "sink":
        cen = p.mean(axis=1) - e.center
        basin = (n[:, 2] > 0.9) & (np.abs(cen[:, 0]) < e.size[0] / 2 - SINK_RIM) & (
            np.abs(cen[:, 1]) < e.size[1] / 2 - SINK_RIM)
        albedo[basin] = BASIN_RGB
    return np.clip(albedo * shade[:, None], 0, 255).astype(np.uint8)


class Renderer:
    """Casts one ray per pixel (directions cached in the camera frame with z = 1, so t_hit is z-depth).

    Colour is a lookup of a per-triangle flat-shaded colour table, so a frame costs one raycast plus a few
    gathers; the scene is rebuilt only when the world's geometry changes (or while an object is carried).
    """

    def __init__(self, intr: Intrinsics = DEFAULT_INTRINSICS, mount: Mount | None = None) -> None:
        self.intr = intr
        # The render worker is a child process with the parent's environment, so Mount() here is the
        # simulator's settings.mount (AERMANI_MOUNT_*).
        self.base_from_camera = (mount or Mount()).base_to_camera()
        u, v = np.meshgrid(np.arange(intr.width, dtype=np.float64), np.arange(intr.height, dtype=np.float64))
        self._xc = ((u - intr.cx) / intr.fx).astype(np.float32)
        self._yc = ((v - intr.cy) / intr.fy).astype(np.float32)
        self._tmp = np.empty_like(self._xc)
        self._rays = np.empty((intr.height, intr.width, 6), dtype=np.float32)
        self._scene: o3d.t.geometry.RaycastingScene | None = None
        self._key: tuple | None = None
        self._lut = np.zeros(1, dtype=np.uint16)
        self._offsets = np.zeros(1, dtype=np.int64)
        self._colors = np.zeros((1, 3), dtype=np.uint8)
        self.rebuilds = 0
        self._mesh_cache: dict[tuple, tuple] = {}

    def _ensure_scene(self, world: World) -> None:
        held = world.attached()
        key = (world.version, None if held is None else (tuple(np.round(held.center, 4)), round(held.yaw, 4)))
        if key == self._key and self._scene is not None:
            return
        scene = o3d.t.geometry.RaycastingScene()
        lut, offsets, colors = [], [], []
        total = 0
        cache: dict[tuple, tuple] = {}
        for e in world.entities:
            # Meshes are cached by pose, so carrying an object re-meshes only that object.
            ekey = (e.id, e.shape, tuple(np.round(e.center, 5)), tuple(e.size), round(e.yaw, 5), e.rgb)
            entry = self._mesh_cache.get(ekey)
            if entry is None:
                verts, tris, parity = entity_mesh(e)
                entry = (o3d.core.Tensor(verts), o3d.core.Tensor(tris), _triangle_colors(e, verts, tris, parity))
            cache[ekey] = entry
            vt, tt, col = entry
            scene.add_triangles(vt, tt)
            lut.append(e.id)
            offsets.append(total)
            colors.append(col)
            total += len(col)
        self._mesh_cache = cache
        colors.append(np.zeros((1, 3), dtype=np.uint8))  # misses: black
        self._scene = scene
        self._lut = np.array(lut + [0], dtype=np.uint16)  # last entry: misses
        self._offsets = np.array(offsets + [total], dtype=np.int64)
        self._colors = np.concatenate(colors)
        self._key = key
        self.rebuilds += 1

    def camera_pose(self, position: np.ndarray, yaw: float) -> np.ndarray:
        return pose_matrix(float(position[0]), float(position[1]), float(position[2]), yaw) @ self.base_from_camera

    def render(self, snap: Snapshot) -> Frame:
        self._ensure_scene(snap.world)
        assert self._scene is not None
        cam = self.camera_pose(snap.position, snap.yaw)
        rot = cam[:3, :3].astype(np.float32)
        self._rays[..., :3] = cam[:3, 3].astype(np.float32)
        # d_world = R @ (x, y, 1), written axis by axis: cheaper than a BLAS call on 300k tiny vectors.
        for i in range(3):
            np.multiply(self._xc, rot[i, 0], out=self._tmp)
            self._tmp += self._yc * rot[i, 1]
            self._tmp += rot[i, 2]
            self._rays[..., 3 + i] = self._tmp
        ans = self._scene.cast_rays(o3d.core.Tensor.from_numpy(self._rays))
        t = ans["t_hit"].numpy()
        gid = ans["geometry_ids"].numpy()
        prim = ans["primitive_ids"].numpy()
        valid = (t <= MAX_DEPTH_M) & (gid != INVALID_ID)  # inf fails the first test
        depth = np.where(valid, t * 1000.0 + 0.5, 0).astype(np.uint16)
        g = np.where(valid, gid, len(self._lut) - 1).astype(np.int64)
        inst = self._lut[g]
        tri = self._offsets[g] + np.where(valid, prim, 0)
        rgb = self._colors[tri]
        return Frame(rgb, depth, inst, cam)
