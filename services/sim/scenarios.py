"""Seeded layouts: furniture around an 8 m x 8 m room, the target, distractors and extras on surfaces."""

from __future__ import annotations

import math
import random

import numpy as np

from services.sim.layout import (
    FLOOR_Z,
    FURNITURE,
    OBJECTS,
    ROOM_HALF,
    SURFACES,
    WALL_HEIGHT,
    Category,
    Entity,
)
from services.sim.physics import World
from shared.frames import DEFAULT_INTRINSICS, base_to_camera
from shared.messages import Pose, Scenario, Vec3
from shared.sensors import pose_matrix

FURNITURE_GAP = 0.5  # free space between furniture pieces and to the walls, so the drone can pass
START_CLEAR = 1.3  # no furniture within this distance of the start position (take-off room)
EDGE_MARGIN = 0.15  # object centres keep this far from surface edges
OBJECT_GAP = 0.04  # minimum gap between object footprints
VIEW_ALTITUDES = (0.0, 1.0, 1.5)  # "initial view" means on the ground and after the usual take-off

STRUCTURE_IDS = {"floor": 1, "wall north": 2, "wall south": 3, "wall east": 4, "wall west": 5, "ceiling": 6}
FURNITURE_IDS = {name: 10 + i for i, name in enumerate(FURNITURE)}
OBJECT_IDS = {name: 100 + i for i, name in enumerate(OBJECTS)}


class ScenarioError(ValueError):
    """A scenario names something the simulator does not have, or cannot be laid out."""


def canonical(name: str, table: dict, what: str) -> str:
    key = " ".join(name.strip().lower().split())
    if key not in table:
        raise ScenarioError(f"unknown {what} {name!r}; known: {', '.join(table)}")
    return key


def _structure() -> list[Entity]:
    h, t = ROOM_HALF, 0.1
    grey, wall = (120, 120, 115), (200, 195, 185)
    wh = WALL_HEIGHT - FLOOR_Z
    wz = (WALL_HEIGHT + FLOOR_Z) / 2
    return [
        Entity(STRUCTURE_IDS["floor"], "floor", "structure", "box", np.array([0.0, 0.0, FLOOR_Z - 0.05]),
               (2 * h + 2 * t, 2 * h + 2 * t, 0.1), grey, "grey"),
        Entity(STRUCTURE_IDS["wall north"], "wall north", "structure", "box",
               np.array([0.0, h + t / 2, wz]), (2 * h + 2 * t, t, wh), wall, "cream"),
        Entity(STRUCTURE_IDS["wall south"], "wall south", "structure", "box",
               np.array([0.0, -h - t / 2, wz]), (2 * h + 2 * t, t, wh), wall, "cream"),
        Entity(STRUCTURE_IDS["wall east"], "wall east", "structure", "box",
               np.array([h + t / 2, 0.0, wz]), (t, 2 * h, wh), wall, "cream"),
        Entity(STRUCTURE_IDS["wall west"], "wall west", "structure", "box",
               np.array([-h - t / 2, 0.0, wz]), (t, 2 * h, wh), wall, "cream"),
        Entity(STRUCTURE_IDS["ceiling"], "ceiling", "structure", "box",
               np.array([0.0, 0.0, WALL_HEIGHT + 0.05]), (2 * h + 2 * t, 2 * h + 2 * t, 0.1), (235, 235, 235),
               "white"),
    ]


def _place_furniture(rng: random.Random, start: tuple[float, float]) -> list[Entity]:
    for _ in range(200):
        placed: list[Entity] = []
        for name, spec in FURNITURE.items():
            sx, sy = spec.footprint
            if spec.shape == "box" and rng.random() < 0.5:
                sx, sy = sy, sx
            for _ in range(300):
                lim_x = ROOM_HALF - FURNITURE_GAP - sx / 2
                lim_y = ROOM_HALF - FURNITURE_GAP - sy / 2
                x, y = rng.uniform(-lim_x, lim_x), rng.uniform(-lim_y, lim_y)
                # Distance from the start point to the footprint must leave take-off room.
                qx, qy = max(abs(start[0] - x) - sx / 2, 0.0), max(abs(start[1] - y) - sy / 2, 0.0)
                if math.hypot(qx, qy) < START_CLEAR:
                    continue
                if all(abs(x - o.center[0]) >= (sx + o.size[0]) / 2 + FURNITURE_GAP
                       or abs(y - o.center[1]) >= (sy + o.size[1]) / 2 + FURNITURE_GAP for o in placed):
                    cat: Category = "surface" if spec.support else "furniture"
                    placed.append(Entity(FURNITURE_IDS[name], name, cat, spec.shape,
                                         np.array([x, y, (spec.height + FLOOR_Z) / 2]),
                                         (sx, sy, spec.height - FLOOR_Z), spec.rgb,
                                         spec.color))
                    break
            else:
                break
        else:
            return placed
    raise ScenarioError("could not lay out the furniture; this seed is unlucky, try another")


def _fits(surface: Entity, obj: Entity, others: list[Entity]) -> bool:
    x, y = float(obj.center[0]), float(obj.center[1])
    if not surface.contains_xy(x, y, EDGE_MARGIN):
        return False
    # Every footprint corner (or the rim of a round object) stays on the surface.
    if obj.shape == "box":
        c, s = math.cos(obj.yaw), math.sin(obj.yaw)
        for ex, ey in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            hx, hy = ex * obj.size[0] / 2, ey * obj.size[1] / 2
            if not surface.contains_xy(x + c * hx - s * hy, y + s * hx + c * hy, 0.03):
                return False
    elif not surface.contains_xy(x, y, obj.size[0] / 2 + 0.03):
        return False
    r = obj.footprint_radius()
    return all(math.hypot(x - o.center[0], y - o.center[1]) >= r + o.footprint_radius() + OBJECT_GAP
               for o in others)


def visible_from(entity: Entity, start: Pose, altitudes: tuple[float, ...] = VIEW_ALTITUDES) -> bool:
    """Whether any corner or the centre of `entity`'s box projects into the image from the start pose at
    any of `altitudes` (occlusion ignored: conservative for out-of-view checks)."""
    intr = DEFAULT_INTRINSICS
    pts = [entity.center]
    hx, hy, hz = (s / 2 for s in entity.size)
    for ex in (-1, 1):
        for ey in (-1, 1):
            for ez in (-1, 1):
                pts.append(entity.center + np.array([ex * hx, ey * hy, ez * hz]))
    pw = np.column_stack([np.array(pts), np.ones(len(pts))])
    for alt in altitudes:
        cam = pose_matrix(start.position.x, start.position.y, start.position.z + alt, start.yaw) @ base_to_camera()
        pc = (np.linalg.inv(cam) @ pw.T).T[:, :3]
        for x, y, z in pc:
            if z > 0.05:
                u, v = intr.fx * x / z + intr.cx, intr.fy * y / z + intr.cy
                if -0.5 <= u <= intr.width - 0.5 and -0.5 <= v <= intr.height - 0.5:
                    return True
    return False


def _named(scenario: Scenario) -> tuple[str | None, str | None, tuple[str, ...], dict[str, str]]:
    """The scenario's names in canonical form -> (target, destination, extra objects, fixed placements);
    raises ScenarioError for a destination or placement that is no surface, or a target placed on its
    destination."""
    target = canonical(scenario.target_object, OBJECTS, "object") if scenario.target_object else None
    dest = canonical(scenario.destination, FURNITURE, "surface") if scenario.destination else None
    if dest is not None and dest not in SURFACES:
        raise ScenarioError(f"{dest!r} has no top to place things on; surfaces: {', '.join(SURFACES)}")
    extras = tuple(canonical(n, OBJECTS, "object") for n in scenario.extra_objects)
    fixed = {canonical(o, OBJECTS, "object"): canonical(s, FURNITURE, "surface")
             for o, s in (scenario.placements or {}).items()}
    for obj_name, surf_name in fixed.items():
        if surf_name not in SURFACES:
            raise ScenarioError(f"{surf_name!r} has no top to place the {obj_name} on; surfaces: {', '.join(SURFACES)}")
        if obj_name == target and surf_name == dest:
            raise ScenarioError(f"the {obj_name} cannot start on its destination, the {dest}")
    return target, dest, extras, fixed


def _place_object(rng: random.Random, name: str, choices: list[Entity], placed: list[Entity], start: Pose,
                  want_visible: bool | None) -> Entity | None:
    """Draw a free spot for object `name` on one of the `choices` surfaces (up to 600 tries); None: no room."""
    spec = OBJECTS[name]
    for attempt in range(600):
        surf = rng.choice(choices)
        yaw = rng.uniform(-math.pi, math.pi) if spec.shape == "box" else 0.0
        r = surf.footprint_radius()
        x = surf.center[0] + rng.uniform(-r, r)
        y = surf.center[1] + rng.uniform(-r, r)
        obj = Entity(OBJECT_IDS[name], name, "object", spec.shape,
                     np.array([x, y, surf.top_z + spec.size[2] / 2]), spec.size, spec.rgb, spec.color, yaw,
                     support=surf.name)
        if not _fits(surf, obj, placed):
            continue
        # Visibility is a preference for the normal case (the policy should see the target) and a hard
        # requirement for search tasks.
        if want_visible is not None and attempt < 500 and visible_from(obj, start) != want_visible:
            continue
        return obj
    return None


def generate(scenario: Scenario, light_variation: bool = True,
             look: str = "primitive", dynamics: str = "kinematic") -> tuple[World, Scenario, Pose]:
    """Build the world for `scenario` (a MuJoCo simulation, objects settled on their supports); returns it, the
    scenario with every choice filled in, and the start. `look`: `physics.LOOKS` (the layout is the same);
    `dynamics`: `physics.DYNAMICS`, the vehicle's body."""
    rng = random.Random(scenario.seed)
    target, dest, extras, fixed = _named(scenario)

    if scenario.start is not None:
        start = scenario.start
    else:
        start = Pose(position=Vec3(x=rng.uniform(-0.3, 0.3), y=rng.uniform(-0.3, 0.3), z=0.0),
                     yaw=rng.uniform(-math.pi, math.pi))
    if abs(start.position.x) > ROOM_HALF - 0.5 or abs(start.position.y) > ROOM_HALF - 0.5:
        raise ScenarioError(f"start ({start.position.x:.2f}, {start.position.y:.2f}) is outside the room")
    start = Pose(position=Vec3(x=start.position.x, y=start.position.y, z=0.0), yaw=start.yaw)

    target = target or rng.choice(list(OBJECTS))
    furniture = _place_furniture(rng, (start.position.x, start.position.y))
    surfaces = {e.name: e for e in furniture if e.category == "surface"}
    target_surface_choices = [fixed[target]] if target in fixed else [s for s in surfaces if s != dest]
    if scenario.start is None and not scenario.target_out_of_view:
        # The normal case has the target in view at the start: face the candidate surface closest to the
        # drawn heading (no extra random draws, so the furniture of a seed does not change).
        def off(name: str) -> float:
            c = surfaces[name].center
            d = math.atan2(c[1] - start.position.y, c[0] - start.position.x) - start.yaw
            return abs(math.atan2(math.sin(d), math.cos(d)))

        facing = min(target_surface_choices, key=off)
        c = surfaces[facing].center
        start = Pose(position=start.position, yaw=math.atan2(c[1] - start.position.y, c[0] - start.position.x))
        target_surface_choices = [facing]

    if scenario.distractors is not None:
        distractors = tuple(canonical(n, OBJECTS, "object") for n in scenario.distractors)
    else:
        pool = [n for n in OBJECTS if n != target and n not in extras]
        distractors = tuple(rng.sample(pool, rng.randint(2, 4)))
    names = [target, *[n for n in extras if n != target]]
    names += [n for n in distractors if n not in names]
    names += [n for n in fixed if n not in names]

    placed: list[Entity] = []

    def place(name: str, choices: list[str], want_visible: bool | None) -> Entity | None:
        return _place_object(rng, name, [surfaces[c] for c in choices], placed, start, want_visible)

    want = not scenario.target_out_of_view
    obj = place(target, target_surface_choices, want)
    if obj is None or (scenario.target_out_of_view and visible_from(obj, start)):
        raise ScenarioError(f"could not place the {target} {'out of view' if scenario.target_out_of_view else ''}"
                            f" with seed {scenario.seed}; try another seed")
    placed.append(obj)
    for name in names[1:]:
        obj = place(name, [fixed[name]] if name in fixed else list(surfaces), None)
        if obj is None:
            raise ScenarioError(f"no room left for the {name} with seed {scenario.seed}")
        placed.append(obj)

    if dest is None:
        dest = rng.choice([s for s in surfaces if s != placed[0].support])
    world = World(entities=_structure() + furniture + placed, light_seed=scenario.seed,
                  light_variation=light_variation, look=look, dynamics=dynamics,
                  criteria=scenario.criteria, target=target)
    filled = Scenario(seed=scenario.seed, target_object=target, destination=dest, distractors=distractors,
                      target_out_of_view=scenario.target_out_of_view, extra_objects=extras, start=start,
                      placements=fixed or None, criteria=scenario.criteria)
    return world, filled, start
