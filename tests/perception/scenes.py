"""Sim-rendered RGB-D frames for perception tests: layouts from services.sim, cameras aimed at each thing."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from services.perception.frames import Frame
from services.sim.layout import ROOM_HALF, Entity
from services.sim.physics import World
from services.sim.render import Renderer, snapshot_at
from services.sim.scenarios import generate
from shared.frames import CAMERA_PITCH_DOWN, DEFAULT_INTRINSICS
from shared.messages import Scenario, SimLabel, SimLabels, Vec3
from shared.sensors import encode_jpeg

_renderer: Renderer | None = None


def renderer() -> Renderer:
    """MuJoCo's camera with the realistic stereo-depth and exposure model (seeded: reproducible frames)."""
    global _renderer
    if _renderer is None:
        _renderer = Renderer(realism="realistic", seed=7)
    return _renderer


def labels_of(world: World) -> SimLabels:
    return SimLabels(labels=tuple(SimLabel(id=e.id, name=e.name, category=e.category, color=e.color,
                                           size=Vec3(x=e.size[0], y=e.size[1], z=e.size[2]))
                                  for e in world.entities))


@dataclass
class View:
    frame: Frame
    world: World
    instance: np.ndarray
    body: tuple[float, float, float, float]  # x, y, z, yaw


def render_view(world: World, x: float, y: float, z: float, yaw: float, stamp_ns: int | None = None,
                jpeg_quality: int = 85, camera: Renderer | None = None) -> View:
    """Render the world from a body pose into a perception Frame (colour goes through JPEG like on the bus);
    `camera` defaults to the seeded realistic one."""
    r = camera or renderer()
    f = r.render(snapshot_at(world, np.array([x, y, z]), yaw))
    stamp = stamp_ns or time.time_ns()
    frame = Frame(stamp, f.depth_mm, DEFAULT_INTRINSICS, f.camera_to_world, time.time_ns(),
                  None, f.instance, labels_of(world))
    from shared.sensors import color_message

    frame.color_payload = color_message(f.rgb, stamp, jpeg=encode_jpeg(f.rgb, jpeg_quality))
    return View(frame, world, f.instance, (x, y, z, yaw))


def aim_at(world: World, target: np.ndarray, distance: float, rng: np.random.Generator) -> tuple[float, ...]:
    """A body pose `distance` away horizontally whose camera centre ray passes near `target`, inside the room."""
    for _ in range(50):
        ang = rng.uniform(-math.pi, math.pi)
        x = target[0] + distance * math.cos(ang)
        y = target[1] + distance * math.sin(ang)
        if abs(x) > ROOM_HALF - 0.4 or abs(y) > ROOM_HALF - 0.4:
            continue
        yaw = math.atan2(target[1] - y, target[0] - x)
        z = target[2] + (distance - 0.12) * math.tan(CAMERA_PITCH_DOWN) + 0.05
        return x, y, z, yaw
    raise RuntimeError("no viewpoint inside the room")


_versions = iter(range(1_000_000, 2_000_000))


def layout(seed: int, look: str = "primitive") -> World:
    world, _, _ = generate(Scenario(seed=seed), look=look)
    # The renderer caches its scene by world version; distinct layouts must not share one.
    world.version = next(_versions)
    return world


def projected_corners_in_view(e: Entity, frame: Frame, margin: int = 2) -> bool:
    """Whether the whole bounding box of `e` projects inside the image (occlusion not considered)."""
    hx, hy, hz = (s / 2 for s in e.size)
    c, s = math.cos(e.yaw), math.sin(e.yaw)
    pts = []
    for ex in (-1, 1):
        for ey in (-1, 1):
            for ez in (-1, 1):
                lx, ly = ex * hx, ey * hy
                pts.append(e.center + np.array([c * lx - s * ly, s * lx + c * ly, ez * hz]))
    pw = np.column_stack([np.array(pts), np.ones(8)])
    pc = (np.linalg.inv(frame.world_from_camera) @ pw.T).T[:, :3]
    if (pc[:, 2] < 0.05).any():
        return False
    intr = frame.intr
    u = intr.fx * pc[:, 0] / pc[:, 2] + intr.cx
    v = intr.fy * pc[:, 1] / pc[:, 2] + intr.cy
    return bool((u >= margin).all() and (u <= intr.width - margin).all() and (v >= margin).all()
                and (v <= intr.height - margin).all())


def unoccluded_pixels(view: View, entity: Entity) -> int:
    """Pixels `entity` would cover from the view's pose with nothing in front of it (to judge occlusion)."""
    alone = World(entities=[entity], version=next(_versions), settle_s=0.0, look=view.world.look)
    x, y, z, yaw = view.body
    f = Renderer(realism="ideal").render(snapshot_at(alone, np.array([x, y, z]), yaw))
    return int((f.instance == entity.id).sum())


def classify(view: View, e: Entity) -> str:
    """How `e` appears in `view`: "in_view" (at least 100 px, the whole bounding box projects inside the image,
    within 3 m of the camera, at least half of its pixels unoccluded), "absent" (no pixel) or "partial"."""
    px = int((view.instance == e.id).sum())
    if px == 0:
        return "absent"
    if (px >= 100 and projected_corners_in_view(e, view.frame)
            and np.linalg.norm(e.center - view.frame.world_from_camera[:3, 3]) <= 3.0
            and px >= 0.5 * unoccluded_pixels(view, e)):
        return "in_view"
    return "partial"


def furniture(name: str, x: float, y: float) -> Entity:
    from services.sim.layout import FURNITURE
    from services.sim.scenarios import FURNITURE_IDS

    spec = FURNITURE[name]
    cat = "surface" if spec.support else "furniture"
    return Entity(FURNITURE_IDS[name], name, cat, spec.shape, np.array([x, y, spec.height / 2]),
                  (*spec.footprint, spec.height), spec.rgb, spec.color)


def thing(name: str, x: float, y: float, on: Entity, yaw: float = 0.0) -> Entity:
    from services.sim.layout import OBJECTS
    from services.sim.scenarios import OBJECT_IDS

    spec = OBJECTS[name]
    return Entity(OBJECT_IDS[name], name, "object", spec.shape, np.array([x, y, on.top_z + spec.size[2] / 2]),
                  spec.size, spec.rgb, spec.color, yaw if spec.shape == "box" else 0.0, support=on.name)


def manual_world(*entities: Entity, look: str = "primitive") -> World:
    from services.sim.scenarios import _structure

    return World(entities=_structure() + list(entities), version=next(_versions), look=look)
