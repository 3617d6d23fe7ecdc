"""Ground-truth world of the simulator: furniture, objects, gripper physics and collision geometry (ENU)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

Shape = Literal["box", "cylinder", "sphere"]
Category = Literal["object", "surface", "furniture", "structure"]

ROOM_HALF = 4.0  # the room is 8 m x 8 m centred on the world origin; its walls are the geofence
# The autopilot's ground is z = 0 (the body origin of a landed vehicle, as PX4 reports it); the floor plane
# sits one landing-gear height below, so the camera of a landed vehicle is above the floor, not inside it.
FLOOR_Z = -0.10
WALL_HEIGHT = 2.6
VEHICLE_RADIUS = 0.25  # collision cylinder of the airframe around the body origin
VEHICLE_HEIGHT = 0.15  # ... from VEHICLE_BELOW under the body origin up
VEHICLE_BELOW = 0.05
CAPTURE_RADIUS = 0.07  # gripper capture region: horizontal distance from the object's axis
CAPTURE_ABOVE_TOP = 0.05  # ... and vertically from the object's centre to its top + this


@dataclass(frozen=True)
class ObjectSpec:
    name: str
    shape: Shape
    size: tuple[float, float, float]  # extent x, y, z in metres (cylinder/sphere: diameter, diameter, height)
    color: str
    rgb: tuple[int, int, int]


@dataclass(frozen=True)
class FurnitureSpec:
    name: str
    shape: Shape  # box or cylinder (round table)
    footprint: tuple[float, float]  # x, y extent (cylinder: diameter, diameter)
    height: float  # top height above the floor
    color: str
    rgb: tuple[int, int, int]
    support: bool  # objects may rest on its top


# Hues are spread so a classical HSV segmenter separates them: red cup (hue ~0) vs purple cup (~275 deg)
# vs coke can (deep crimson, smaller and taller) vs orange (~30 deg) and so on.
OBJECTS: dict[str, ObjectSpec] = {s.name: s for s in (
    ObjectSpec("red cup", "cylinder", (0.08, 0.08, 0.11), "red", (215, 25, 25)),
    ObjectSpec("purple cup", "cylinder", (0.08, 0.08, 0.11), "purple", (125, 45, 200)),
    ObjectSpec("coke can", "cylinder", (0.066, 0.066, 0.12), "crimson", (160, 10, 45)),
    ObjectSpec("soda can", "cylinder", (0.066, 0.066, 0.12), "blue", (30, 110, 225)),
    ObjectSpec("tissue box", "box", (0.24, 0.12, 0.10), "cyan", (110, 215, 235)),
    ObjectSpec("green bottle", "cylinder", (0.07, 0.07, 0.25), "green", (20, 150, 45)),
    ObjectSpec("apple", "sphere", (0.08, 0.08, 0.08), "lime", (150, 210, 30)),
    ObjectSpec("orange", "sphere", (0.08, 0.08, 0.08), "orange", (250, 135, 10)),
    ObjectSpec("banana", "box", (0.19, 0.045, 0.04), "yellow", (245, 220, 40)),
    ObjectSpec("cracker box", "box", (0.16, 0.07, 0.21), "pink", (235, 100, 170)),
    ObjectSpec("cardboard box", "box", (0.30, 0.24, 0.20), "brown", (165, 115, 65)),
    ObjectSpec("small box", "box", (0.10, 0.10, 0.08), "teal", (0, 140, 140)),
    ObjectSpec("large box", "box", (0.34, 0.28, 0.24), "navy", (35, 45, 135)),
    ObjectSpec("wrench", "box", (0.20, 0.05, 0.02), "silver", (150, 150, 160)),
    ObjectSpec("screwdriver", "box", (0.18, 0.025, 0.025), "black", (25, 25, 25)),
    ObjectSpec("hammer", "box", (0.30, 0.10, 0.035), "olive", (120, 120, 0)),
)}
TOOLS = ("wrench", "screwdriver", "hammer")

FURNITURE: dict[str, FurnitureSpec] = {s.name: s for s in (
    FurnitureSpec("table", "box", (1.2, 0.8), 0.75, "white", (225, 225, 220), True),
    FurnitureSpec("round table", "cylinder", (0.9, 0.9), 0.75, "grey", (175, 175, 180), True),
    FurnitureSpec("wooden table", "box", (1.1, 0.7), 0.75, "wood", (150, 100, 55), True),
    FurnitureSpec("shelf", "box", (1.0, 0.5), 0.9, "beige", (205, 190, 160), True),
    FurnitureSpec("sink", "box", (0.8, 0.6), 0.85, "steel", (190, 200, 205), True),
    FurnitureSpec("counter", "box", (1.4, 0.6), 0.9, "dark grey", (90, 90, 95), True),
    FurnitureSpec("coffee machine", "box", (0.35, 0.35), 1.0, "black", (40, 35, 35), False),
)}
SURFACES = tuple(n for n, s in FURNITURE.items() if s.support)


@dataclass
class Entity:
    """One thing with an instance id: an object, a piece of furniture, or structure (floor, walls)."""

    id: int
    name: str
    category: Category
    shape: Shape
    center: np.ndarray  # ENU centre of the bounding box
    size: tuple[float, float, float]
    rgb: tuple[int, int, int]
    color: str = ""
    yaw: float = 0.0
    attached: bool = False
    support: str | None = None

    @property
    def top_z(self) -> float:
        return float(self.center[2] + self.size[2] / 2)

    @property
    def bottom_z(self) -> float:
        return float(self.center[2] - self.size[2] / 2)

    def contains_xy(self, x: float, y: float, margin: float = 0.0) -> bool:
        """Whether (x, y) lies inside this entity's footprint shrunk by `margin`."""
        dx, dy = x - self.center[0], y - self.center[1]
        if self.shape in ("cylinder", "sphere"):
            return math.hypot(dx, dy) <= self.size[0] / 2 - margin
        c, s = math.cos(-self.yaw), math.sin(-self.yaw)
        lx, ly = c * dx - s * dy, s * dx + c * dy
        return abs(lx) <= self.size[0] / 2 - margin and abs(ly) <= self.size[1] / 2 - margin

    def footprint_radius(self) -> float:
        if self.shape in ("cylinder", "sphere"):
            return self.size[0] / 2
        return math.hypot(self.size[0], self.size[1]) / 2


@dataclass
class World:
    """The layout plus mutable state (objects may be attached to the gripper and dropped)."""

    entities: list[Entity] = field(default_factory=list)
    version: int = 0  # bumped when geometry changes (pick, place, reset): the renderer rebuilds its scene
    collisions: list[str] = field(default_factory=list)

    # ---- lookup

    def by_name(self, name: str) -> Entity | None:
        key = name.strip().lower()
        return next((e for e in self.entities if e.name == key), None)

    @property
    def objects(self) -> list[Entity]:
        return [e for e in self.entities if e.category == "object"]

    @property
    def surfaces(self) -> list[Entity]:
        return [e for e in self.entities if e.category == "surface"]

    @property
    def obstacles(self) -> list[Entity]:
        return [e for e in self.entities if e.category in ("surface", "furniture")]

    def attached(self) -> Entity | None:
        return next((e for e in self.objects if e.attached), None)

    # ---- support and judging

    def support_below(self, x: float, y: float, z: float) -> tuple[str, float]:
        """Highest surface (or furniture top) whose footprint contains (x, y) and whose top is at or below z;
        the floor otherwise."""
        best = ("floor", FLOOR_Z)
        for e in self.obstacles:
            if e.top_z <= z + 1e-6 and e.top_z > best[1] and e.contains_xy(x, y):
                best = (e.name, e.top_z)
        return best

    def on_surface(self, obj: Entity, surface: Entity, tolerance: float = 0.05) -> tuple[bool, str]:
        if obj.attached:
            return False, f"{obj.name} is in the gripper"
        gap = obj.bottom_z - surface.top_z
        if abs(gap) > tolerance:
            return False, f"{obj.name} bottom is {gap:+.3f} m from the {surface.name} top (tolerance {tolerance})"
        if not surface.contains_xy(float(obj.center[0]), float(obj.center[1])):
            return False, f"{obj.name} centre is outside the {surface.name} footprint"
        return True, f"{obj.name} rests on the {surface.name}"

    # ---- vehicle geometry

    def vehicle_contacts(self, p: np.ndarray) -> list[str]:
        """Names of furniture/walls the vehicle collision cylinder at body origin `p` (ENU) intersects."""
        hits = []
        x, y, z = float(p[0]), float(p[1]), float(p[2])
        lim = ROOM_HALF - VEHICLE_RADIUS
        if abs(x) > lim or abs(y) > lim:
            hits.append("wall")
        if z + VEHICLE_HEIGHT - VEHICLE_BELOW > WALL_HEIGHT:
            hits.append("ceiling")
        for e in self.obstacles:
            if z - VEHICLE_BELOW >= e.top_z or z + VEHICLE_HEIGHT - VEHICLE_BELOW <= e.bottom_z:
                continue
            dx, dy = x - e.center[0], y - e.center[1]
            if e.shape == "cylinder":
                inside = math.hypot(dx, dy) < e.size[0] / 2 + VEHICLE_RADIUS
            else:  # furniture is axis-aligned: distance from a circle to the box
                qx = max(abs(dx) - e.size[0] / 2, 0.0)
                qy = max(abs(dy) - e.size[1] / 2, 0.0)
                inside = math.hypot(qx, qy) < VEHICLE_RADIUS
            if inside:
                hits.append(e.name)
        return hits

    def record_collision(self, name: str) -> None:
        tag = f"vehicle-{name}"
        if tag not in self.collisions:
            self.collisions.append(tag)

    # ---- gripper

    def try_grab(self, gripper: np.ndarray) -> Entity | None:
        """Attach the object whose grasp region contains the gripper point (nearest axis first)."""
        if self.attached() is not None:
            return None
        gx, gy, gz = (float(v) for v in gripper)
        best: tuple[float, Entity] | None = None
        for e in self.objects:
            d = math.hypot(gx - e.center[0], gy - e.center[1])
            if d <= CAPTURE_RADIUS and e.center[2] <= gz <= e.top_z + CAPTURE_ABOVE_TOP and (
                    best is None or d < best[0]):
                best = (d, e)
        if best is None:
            return None
        obj = best[1]
        obj.attached = True
        obj.support = None
        self.version += 1
        return obj

    def carry(self, gripper: np.ndarray, yaw_delta: float = 0.0) -> None:
        """Move the attached object with the gripper: hung by its top, centred under the capture point."""
        obj = self.attached()
        if obj is None:
            return
        obj.center = np.array([gripper[0], gripper[1], gripper[2] - obj.size[2] / 2], dtype=float)
        obj.yaw = (obj.yaw + yaw_delta + math.pi) % (2 * math.pi) - math.pi

    def release(self) -> Entity | None:
        """Drop the attached object straight down, upright, onto the highest support below it."""
        obj = self.attached()
        if obj is None:
            return None
        x, y = float(obj.center[0]), float(obj.center[1])
        name, top = self.support_below(x, y, obj.bottom_z + 0.02)
        obj.center = np.array([x, y, top + obj.size[2] / 2])
        obj.attached = False
        obj.support = name
        self.version += 1
        return obj

    def copy(self) -> World:
        return World([replace(e, center=e.center.copy()) for e in self.entities], self.version,
                     list(self.collisions))
