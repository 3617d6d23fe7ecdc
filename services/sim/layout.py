"""The simulator's catalogue and layout records: furniture and objects with size, mass, friction and colour (ENU).

A layout (`services.sim.scenarios.generate`) is a list of `Entity`; `services.sim.physics.World` builds the MuJoCo
model from it and keeps the entities' poses in step with the simulation."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

Shape = Literal["box", "cylinder", "sphere"]
Category = Literal["object", "surface", "furniture", "structure"]

ROOM_HALF = 4.0  # the room is 8 m x 8 m centred on the world origin; its walls are the geofence
# The autopilot's ground is z = 0 (the body origin of a landed vehicle, as PX4 reports it); the floor plane
# sits one landing-gear height below. The gear is taller than the gripper (its feet 5 mm below the finger pads'
# bottom, 0.245 m under the body origin), as an aerial manipulator's must be for the vehicle to land on its gear
# with the pads clear of the floor: the pads collide with the floor too (services/sim/README.md "Gripper").
GEAR_HEIGHT = 0.25
FLOOR_Z = -GEAR_HEIGHT
WALL_HEIGHT = 2.6
VEHICLE_RADIUS = 0.25  # collision cylinder of the airframe around the body origin
# The vehicle's body (SimSettings.dynamics; physics builds it): `multirotor`, a free rigid body with four lagged
# rotors under a PX4-style cascade, the default; `kinematic`, an ideal body on sliding joints pushed by a perfect
# world-frame force (it never tilts). README "Dynamics".
DYNAMICS = ("kinematic", "multirotor")
DEFAULT_DYNAMICS: Literal["kinematic", "multirotor"] = "multirotor"
VEHICLE_HEIGHT = 0.15  # ... from VEHICLE_BELOW under the body origin up
VEHICLE_BELOW = 0.05


@dataclass(frozen=True)
class ObjectSpec:
    """A graspable object of a scenario layout: shape, size, colour and physical properties."""

    name: str
    shape: Shape
    size: tuple[float, float, float]  # extent x, y, z in metres (cylinder/sphere: diameter, diameter, height)
    color: str
    rgb: tuple[int, int, int]
    mass: float  # kg
    friction: float = 0.7  # sliding friction coefficient against the (rougher) other surface


@dataclass(frozen=True)
class FurnitureSpec:
    """A piece of furniture of a scenario layout: shape, footprint, height, colour and whether it supports objects."""

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
    ObjectSpec("red cup", "cylinder", (0.08, 0.08, 0.11), "red", (215, 25, 25), 0.12),
    ObjectSpec("purple cup", "cylinder", (0.08, 0.08, 0.11), "purple", (125, 45, 200), 0.12),
    ObjectSpec("coke can", "cylinder", (0.066, 0.066, 0.12), "crimson", (160, 10, 45), 0.37),
    ObjectSpec("soda can", "cylinder", (0.066, 0.066, 0.12), "blue", (30, 110, 225), 0.37),
    ObjectSpec("tissue box", "box", (0.24, 0.12, 0.10), "cyan", (110, 215, 235), 0.15),
    ObjectSpec("green bottle", "cylinder", (0.07, 0.07, 0.25), "green", (20, 150, 45), 0.55),
    ObjectSpec("apple", "sphere", (0.08, 0.08, 0.08), "lime", (150, 210, 30), 0.2),
    ObjectSpec("orange", "sphere", (0.08, 0.08, 0.08), "orange", (250, 135, 10), 0.18),
    ObjectSpec("banana", "box", (0.19, 0.045, 0.04), "yellow", (245, 220, 40), 0.15),
    ObjectSpec("cracker box", "box", (0.16, 0.07, 0.21), "pink", (235, 100, 170), 0.45),
    # Graspable across its 16 cm side (the fingers open to 18 cm); twice the cracker box's volume.
    ObjectSpec("cardboard box", "box", (0.22, 0.16, 0.15), "brown", (165, 115, 65), 0.35),
    ObjectSpec("wrench", "box", (0.20, 0.05, 0.02), "silver", (150, 150, 160), 0.25),
    ObjectSpec("screwdriver", "box", (0.18, 0.025, 0.025), "black", (25, 25, 25), 0.1),
    ObjectSpec("hammer", "box", (0.30, 0.10, 0.035), "olive", (120, 120, 0), 0.55),
)}
TOOLS = ("wrench", "screwdriver", "hammer")

# Tops differ in chromaticity, not only in brightness: under the varying room light a white top in shadow is as
# dark as a grey one in full light, and a colour segmenter can only tell them apart by hue.
FURNITURE: dict[str, FurnitureSpec] = {s.name: s for s in (
    FurnitureSpec("table", "box", (1.2, 0.8), 0.75, "white", (225, 225, 220), True),
    FurnitureSpec("round table", "cylinder", (0.9, 0.9), 0.75, "sage", (120, 165, 140), True),
    FurnitureSpec("wooden table", "box", (1.1, 0.7), 0.75, "wood", (150, 100, 55), True),
    FurnitureSpec("shelf", "box", (1.0, 0.5), 0.9, "beige", (205, 190, 160), True),
    FurnitureSpec("sink", "box", (0.8, 0.6), 0.85, "blue steel", (140, 165, 200), True),
    FurnitureSpec("counter", "box", (1.4, 0.6), 0.9, "dark grey", (70, 70, 75), True),
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
    attached: bool = False  # held by the gripper (both fingers in contact)
    support: str | None = None  # what it rests on, by contact ("floor", a furniture name, another object)
    tilt: float = 0.0  # angle between the object's own z axis and the world's, radians (0 = upright)

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
