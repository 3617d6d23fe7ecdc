"""The simulated world on MuJoCo: static rooms and furniture, free rigid objects, the vehicle body with a
two-finger parallel gripper, contacts and collisions (world frame ENU, z up).

The vehicle is a body on three slide joints and a yaw hinge (a multirotor's attitude is not simulated: the
position controller in `services.sim.vehicle` commands forces on those joints, limited like PX4's). It
collides with furniture, walls and objects; every contact of the airframe with furniture or walls is recorded,
and one faster than `crash_speed` is a crash. The fingers slide along the body's y axis, coupled and driven by
one force-limited servo: an object is held only by the pads' contact and friction.

Collision groups (contype/conaffinity bits): 1 furniture and walls, 2 objects, 4 fingers, 8 airframe, 16 floor.
Fingers (pads and arms) touch objects, furniture, walls and the floor (the landing gear's feet reach 5 mm below
the pads); the airframe and its gear touch furniture, walls, floor and objects.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal, get_args
from xml.sax.saxutils import quoteattr

import mujoco
import numpy as np

from services.sim.layout import (
    DEFAULT_DYNAMICS,
    DYNAMICS,
    FLOOR_Z,
    VEHICLE_BELOW,
    VEHICLE_HEIGHT,
    VEHICLE_RADIUS,
    Entity,
)
from shared.frames import CAMERA_OFFSET_BODY, CAMERA_PITCH_DOWN, DEFAULT_INTRINSICS, GRIPPER_OFFSET_BODY
from shared.messages import JudgeCheck, JudgeCriteria

TIMESTEP = 0.002  # s; contacts of small objects in a gripper want a few ms at most
# The vehicle's dynamics: layout.DYNAMICS (SimSettings.dynamics, multirotor by default).
KINEMATIC_MASS = 1.5  # kg, the kinematic body's airframe (fingers add FINGER_MASS each)
VEHICLE_YAW_INERTIA = 0.03  # kg m^2 about z, the kinematic body's (its yaw torque's scale)
VEHICLE_MASS = 1.0  # kg, the multirotor's airframe (battery, motors, gear and fingers add ~0.86 kg: ~1.86 kg in all)
BATTERY_MASS = 0.5  # kg, a 4S pack low in the frame: with it the centre of mass is at the body origin
BATTERY_Z = -0.04  # m
# A quadrotor in X (PX4's "quadrotor x" numbering): rotors 0..3 front-right, back-left, front-left, back-right,
# the first two spinning counter-clockwise seen from above. Figures of a 1.5-2.5 kg indoor aerial
# manipulator with 6-inch propellers behind the airframe's guard cylinder (README: sources).
ROTOR_ARM = 0.17  # m, body centre to rotor axis
ROTOR_RADIUS = 0.075  # m, propeller radius (6 inch)
ROTOR_Z = 0.08  # m, rotor plane above the body origin
ROTOR_MASS = 0.06  # kg, motor + propeller at each arm tip
ROTOR_MAX_THRUST = 10.0  # N per rotor: thrust-to-weight ~2.2
ROTOR_TAU = 0.02  # s, first-order motor + propeller lag (PX4's gazebo x500: 12.5 ms up, 25 ms down)
ROTOR_YAW_MOMENT = 0.016  # m: reaction torque per newton of thrust (x500's momentConstant)
ROTOR_XY = tuple((ROTOR_ARM * math.cos(a), ROTOR_ARM * math.sin(a))
                 for a in (-math.pi / 4, 3 * math.pi / 4, math.pi / 4, -3 * math.pi / 4))
ROTOR_SPIN = (1.0, 1.0, -1.0, -1.0)  # +1 counter-clockwise from above: its reaction torque turns the body clockwise
FINGER_MASS = 0.04
FINGER_MAX_HALF = 0.09  # each finger travels 0..9 cm from the centre line: opening 0..18 cm
FINGER_MAX_OPENING = 2 * FINGER_MAX_HALF
# A small servo-driven parallel gripper (README "Gripper" has the sources): one motor drives both fingers through
# a linkage, so they are coupled (equal travel); each pad squeezes with at most GRIP_FORCE; the opening changes at
# CLOSING_SPEED. The heaviest catalogue object (0.55 kg) lifted at the 2 m/s^2 vertical acceleration limit needs
# 0.55 * (9.81 + 2) / (2 * PAD_FRICTION) = 4.1 N per pad: GRIP_FORCE holds it with a margin of 1.7.
GRIP_FORCE = 7.0  # N per pad: the force limit on the opening tendon (each finger joint sees it with arm 1)
CLOSING_SPEED = 0.15  # m/s of opening: the full 18 cm in 1.2 s
FINGER_KP = 600.0  # N/m, the servo's stiffness on the opening (it saturates at GRIP_FORCE 1.2 cm off its target)
FINGER_PAD = (0.025, 0.006, 0.03)  # half sizes: along body x (width), thickness (y), height (z)
FINGER_PAD_Z = 0.005  # pad centre above the gripper point: the pad spans 2.5 cm below to 3.5 cm above it
# Rubber pads: dry rubber slides at mu ~0.8 on hard surfaces (kinetic; static ~1.0; README "Gripper"), the
# kinetic value because a grasp fails by sliding. A higher contact `priority` than everything else makes MuJoCo
# use the pad's own friction in its contacts (otherwise it takes the larger of the two geoms' coefficients).
PAD_FRICTION = 0.8
PAD_PRIORITY = 1
ARM_FRICTION = 0.4  # the finger links (aluminium or hard plastic; without priority the larger coefficient applies)
GEAR_OFFSETS = ((0.12, 0.12), (0.12, -0.12), (-0.12, 0.12), (-0.12, -0.12))
GEAR_RADIUS = 0.02  # the feet: spheres at the bottom of the legs, on the floor when the body origin is at z = 0
LEG_RADIUS = 0.006  # the legs: carbon tubes from the airframe's bottom down to the feet
LEG_MASS = 0.005
CRASH_SPEED = 0.5  # m/s: the airframe meeting furniture or a wall faster than this is a crash
# An object is at rest while both stay below these (a sleeping body is at rest by definition): a ball rolling at
# 5 mm/s turns at 0.125 rad/s (a 8 cm orange), so a slow roll is movement, not rest.
REST_SPEED = 0.005  # m/s
REST_SPIN = 0.1  # rad/s
# Incidents (README "Gripper"): an object not in the pads whose own up axis tips this far from where it stood
# upright, or that comes to rest on something else than it stood on, was knocked; an object that left the pads
# after a lift and came to rest this much lower was dropped (a placement lets go a few centimetres above the top).
KNOCK_TILT = math.radians(45.0)
DROP_FALL = 0.10  # m, of its centre

GROUP_ENV, GROUP_OBJ, GROUP_FINGER, GROUP_AIRFRAME, GROUP_FLOOR = 1, 2, 4, 8, 16


def _f(v: float) -> str:
    return f"{v:.6g}"


def _vec(v) -> str:
    return " ".join(_f(float(x)) for x in v)


def _rgba(rgb: tuple[int, int, int]) -> str:
    return _vec([c / 255 for c in rgb] + [1.0])


def _yaw_quat(yaw: float) -> str:
    return _vec([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def camera_quat() -> np.ndarray:
    """Quaternion (w, x, y, z) of the MuJoCo camera in the body frame: MuJoCo cameras look along their -z with
    +y up, the optical frame along +z with +y down."""
    from shared.frames import base_to_camera

    r = base_to_camera(CAMERA_PITCH_DOWN, CAMERA_OFFSET_BODY)[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, r.reshape(-1))
    return q


def entity_geom_name(e: Entity) -> str:
    return f"e{e.id}"


LOOKS = ("primitive", "textured")


def configured_dynamics() -> str:
    """The dynamics `AERMANI_SIM_DYNAMICS` names, DEFAULT_DYNAMICS when unset: the variable `SimSettings.dynamics`
    reads, for code that builds a world without the settings (`SimCore` in-process, tests)."""
    value = os.environ.get("AERMANI_SIM_DYNAMICS", "").strip().lower() or DEFAULT_DYNAMICS
    if value not in DYNAMICS:
        raise ValueError(f"AERMANI_SIM_DYNAMICS={value!r}: {' or '.join(DYNAMICS)}")
    return value


def look_for(realism: str) -> str:
    """The look a camera realism level renders: `ideal` keeps the colour-coded primitives (debugging, geometry
    tests), every other level the textured meshes of `services.sim.assets`."""
    return "primitive" if realism == "ideal" else "textured"


def _vehicle_xml(fovy: float, dynamics: str = "kinematic") -> str:
    """The vehicle's body up to its fingers; the caller closes the body after the fingers. `kinematic`: sliding
    x/y/z joints and a yaw hinge (the body never tilts), the airframe's guard cylinder, landing gear and the
    camera. `multirotor`: a free joint, the same airframe and gear, a battery, four rotor sites (where the rotor
    actuators push) with their motors' mass, and the camera."""
    air = f'contype="{GROUP_AIRFRAME}" conaffinity="{GROUP_ENV | GROUP_OBJ | GROUP_FLOOR}"'
    half_h = VEHICLE_HEIGHT / 2
    gear_z = FLOOR_Z + GEAR_RADIUS  # gear bottom on the floor when the body origin is at z = 0
    legs = "".join(f'<geom name="leg{i}" type="capsule" size="{_f(LEG_RADIUS)}" '
                   f'fromto="{_vec([gx, gy, -VEHICLE_BELOW])} {_vec([gx, gy, gear_z])}" mass="{_f(LEG_MASS)}" '
                   f'rgba="0.1 0.1 0.1 1" {air}/>' for i, (gx, gy) in enumerate(GEAR_OFFSETS))
    camera = (f'<camera name="camera" pos="{_vec(CAMERA_OFFSET_BODY)}" quat="{_vec(camera_quat())}" '
              f'fovy="{_f(fovy)}"/>')
    if dynamics == "kinematic":
        out = ['<body name="vehicle" pos="0 0 0" sleep="never">'
               '<joint name="vx" type="slide" axis="1 0 0"/><joint name="vy" type="slide" axis="0 1 0"/>'
               '<joint name="vz" type="slide" axis="0 0 1"/><joint name="vyaw" type="hinge" axis="0 0 1"/>']
        out.append(f'<geom name="airframe" type="cylinder" size="{_f(VEHICLE_RADIUS)} {_f(half_h)}" '
                   f'pos="0 0 {_f(half_h - VEHICLE_BELOW)}" mass="{_f(KINEMATIC_MASS)}" rgba="0.15 0.15 0.17 1" '
                   f'{air}/>')
        for i, (gx, gy) in enumerate(GEAR_OFFSETS):
            out.append(f'<geom name="gear{i}" type="sphere" size="{_f(GEAR_RADIUS)}" pos="{_vec([gx, gy, gear_z])}" '
                       f'mass="0.01" rgba="0.1 0.1 0.1 1" {air} friction="1 0.01 0.001"/>')
        out.append(legs)
        out.append(camera)
        return "".join(out)
    out = ['<body name="vehicle" pos="0 0 0" sleep="never"><freejoint name="vehicle"/>']
    out.append(f'<geom name="airframe" type="cylinder" size="{_f(VEHICLE_RADIUS)} {_f(half_h)}" '
               f'pos="0 0 {_f(half_h - VEHICLE_BELOW)}" mass="{_f(VEHICLE_MASS)}" rgba="0.15 0.15 0.17 1" {air}/>')
    # The battery puts the centre of mass at the body origin (the fingers hang below, the motors sit above):
    # the origin, whose motion the autopilot reports, then moves as the centre of mass does when the body tilts.
    out.append(f'<geom name="battery" type="box" size="0.07 0.035 0.012" pos="0 0 {_f(BATTERY_Z)}" '
               f'mass="{_f(BATTERY_MASS)}" contype="0" conaffinity="0" group="3"/>')
    for i, (gx, gy) in enumerate(GEAR_OFFSETS):
        out.append(f'<geom name="gear{i}" type="sphere" size="{_f(GEAR_RADIUS)}" pos="{_vec([gx, gy, gear_z])}" '
                   f'mass="0.01" rgba="0.1 0.1 0.1 1" {air} friction="1 0.01 0.001"/>')
    out.append(legs)
    for i, (rx, ry) in enumerate(ROTOR_XY):
        # The motor's mass at the arm tip (it sets the roll and pitch inertia); never collides, never rendered.
        out.append(f'<geom name="motor{i}" type="cylinder" size="0.014 0.012" pos="{_vec([rx, ry, ROTOR_Z - 0.012])}" '
                   f'mass="{_f(ROTOR_MASS)}" contype="0" conaffinity="0" group="3" rgba="0.3 0.3 0.3 1"/>'
                   f'<site name="rotor{i}" pos="{_vec([rx, ry, ROTOR_Z])}" size="0.01"/>')
    out.append(camera)
    return "".join(out)


def _rotor_actuators_xml() -> str:
    """Each rotor: thrust along its site's z axis and the propeller's reaction torque about it, through a first-order
    filter (MuJoCo's `filter` dynamics: the actuator's activation is the thrust, lagging the command by
    ROTOR_TAU). ctrl = commanded thrust in newtons; gainprm[0] scales it (ground effect, thrust noise)."""
    return "".join(
        f'<general name="rotor{i}" site="rotor{i}" gear="0 0 1 0 0 {_f(-spin * ROTOR_YAW_MOMENT)}" dyntype="filter" '
        f'dynprm="{_f(ROTOR_TAU)}" gaintype="fixed" gainprm="1" biastype="none" '
        f'ctrlrange="0 {_f(ROTOR_MAX_THRUST)}"/>'
        for i, spin in enumerate(ROTOR_SPIN))


def build_xml(entities: list[Entity], light_seed: int = 0, light_variation: bool = True,
              look: str = "primitive", dynamics: str = "kinematic") -> str:
    """MJCF for a layout: structure and furniture static, objects free, the vehicle at the origin. `look`:
    `primitive` (colour-coded boxes, cylinders and spheres) or `textured` (meshes and textures, `_textured_*`);
    `dynamics`: the vehicle body (`DYNAMICS`, `_vehicle_xml`)."""
    if look not in LOOKS:
        raise ValueError(f"unknown look {look!r}: {' or '.join(LOOKS)}")
    if dynamics not in DYNAMICS:
        raise ValueError(f"unknown dynamics {dynamics!r}: {' or '.join(DYNAMICS)}")
    textured = look == "textured"
    rng = np.random.default_rng(light_seed)
    intr = DEFAULT_INTRINSICS
    fovy = math.degrees(2 * math.atan(intr.height / 2 / intr.fy))
    parts: list[str] = []
    add = parts.append
    add('<mujoco model="aermani">')
    add('<compiler angle="radian" autolimits="true"/>')
    # Sleeping islands: objects at rest cost nothing until something touches them (MuJoCo >= 3.3).
    add(f'<option timestep="{TIMESTEP}" integrator="implicitfast" cone="elliptic" impratio="10">'
        '<flag sleep="enable"/></option>')
    add(f'<visual><global offwidth="{intr.width}" offheight="{intr.height}"/>'
        '<quality shadowsize="1024"/><map znear="0.01" zfar="50"/>'
        '<headlight ambient="0.3 0.3 0.3" diffuse="0.15 0.15 0.15" specular="0 0 0"/></visual>')
    add('<asset><texture name="tiles" type="2d" builtin="checker" width="256" height="256" '
        'rgb1="0.50 0.50 0.48" rgb2="0.42 0.42 0.40"/>'
        '<material name="floor" texture="tiles" texrepeat="8 8" specular="0.05"/>'
        + (_textured_assets(entities) if textured else '') + '</asset>')
    add('<default><geom solref="0.004 1" solimp="0.95 0.99 0.001" condim="4"/></default>')
    add('<worldbody>')
    # Room light from above (a directional key light, slanted, and a weaker fill): its brightness and
    # direction vary per layout (another office, another time of day).
    k = float(rng.uniform(0.45, 0.65)) if light_variation else 0.55
    tilt = float(rng.uniform(0.25, 0.6)) if light_variation else 0.4
    az = float(rng.uniform(-math.pi, math.pi)) if light_variation else 0.7
    key_dir = [math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), -math.cos(tilt)]
    add(f'<light name="key" directional="true" pos="0 0 2.5" dir="{_vec(key_dir)}" '
        f'diffuse="{_vec([k, k, k * 0.97])}" specular="0.05 0.05 0.05" castshadow="true"/>')
    add(f'<light name="fill" directional="true" pos="0 0 2.5" dir="{_vec([-key_dir[0], -key_dir[1], -0.6])}" '
        f'diffuse="{_vec([0.15, 0.15, 0.16])}" specular="0 0 0" castshadow="false"/>')
    for e in entities:
        if e.category == "object":
            continue
        add(_textured_static(e) if textured else _static_geom(e, "floor", f'rgba="{_rgba(e.rgb)}"'))
    from services.sim.layout import OBJECTS

    for e in entities:
        if e.category != "object":
            continue
        spec = OBJECTS[e.name]
        if textured:
            add(_textured_object(e, spec.mass, spec.friction))
            continue
        name = quoteattr(entity_geom_name(e))
        if e.shape == "cylinder":
            geom = f'type="cylinder" size="{_f(e.size[0] / 2)} {_f(e.size[2] / 2)}"'
        elif e.shape == "sphere":
            geom = f'type="sphere" size="{_f(e.size[0] / 2)}"'
        else:
            geom = f'type="box" size="{_vec(np.array(e.size) / 2)}"'
        add(f'<body name={quoteattr("obj " + e.name)} pos="{_vec(e.center)}" quat="{_yaw_quat(e.yaw)}">'
            f'<freejoint/><geom name={name} {geom} mass="{_f(spec.mass)}" rgba="{_rgba(e.rgb)}" '
            f'{_object_friction(e, spec.friction)} contype="{GROUP_OBJ}" '
            f'conaffinity="{GROUP_ENV | GROUP_OBJ | GROUP_FINGER | GROUP_FLOOR}"/></body>')
    # The vehicle: a free rigid body (airframe, landing gear, rotors, camera) carrying the two fingers.
    add(_vehicle_xml(fovy, dynamics))
    add(_gripper_xml(GRIPPER_OFFSET_BODY[2]))
    add('</body>')
    add('</worldbody>')
    add(_gripper_coupling_xml())
    add('<actuator>')
    add(_gripper_actuator_xml())
    if dynamics == "multirotor":
        add(_rotor_actuators_xml())
    add('</actuator>')
    add('</mujoco>')
    return "\n".join(parts)


def _gripper_xml(gz: float) -> str:
    """The two fingers, children of the "vehicle" body at the gripper point `gz` below its origin: each a rubber
    pad and the link (arm) carrying it up to 5 cm under the body origin, on a slide joint along the body's y axis.
    Pads and arms collide with objects, furniture, walls and the floor (never rendered by the camera: group 3)."""
    pad = FINGER_PAD
    hit = f'contype="{GROUP_FINGER}" conaffinity="{GROUP_ENV | GROUP_FLOOR}"'
    arm_half = (-gz - 0.05 - pad[2] - FINGER_PAD_Z) / 2
    out = []
    for side, sign in (("left", 1.0), ("right", -1.0)):
        out.append(
            f'<body name="finger_{side}" pos="0 0 {_f(gz)}">'
            f'<joint name="finger_{side}" type="slide" axis="0 {_f(sign)} 0" range="0 {_f(FINGER_MAX_HALF)}" '
            'damping="8" armature="0.01"/>'
            f'<geom name="finger_{side}" type="box" size="{_vec(pad)}" pos="0 {_f(sign * pad[1])} '
            f'{_f(FINGER_PAD_Z)}" mass="{_f(FINGER_MASS)}" rgba="0.2 0.2 0.2 1" group="3" {hit} '
            f'friction="{_f(PAD_FRICTION)} 0.02 0.001" priority="{PAD_PRIORITY}"/>'
            # The arm sits 2 mm behind the pad's face: an object squeezed between the pads touches the pads.
            f'<geom name="finger_{side}_arm" type="box" size="0.01 0.004 {_f(arm_half)}" '
            f'pos="0 {_f(sign * pad[1])} {_f(FINGER_PAD_Z + pad[2] + arm_half)}" mass="0.001" {hit} '
            f'friction="{_f(ARM_FRICTION)} 0.005 0.0005" rgba="0.2 0.2 0.2 1" group="3"/></body>')
    return "".join(out)


def _gripper_coupling_xml() -> str:
    """The linkage of a single-motor gripper: a fixed tendon whose length is the opening (left + right travel),
    which the servo drives, and an equality that keeps the two travels equal."""
    return ('<tendon><fixed name="opening"><joint joint="finger_left" coef="1"/>'
            '<joint joint="finger_right" coef="1"/></fixed></tendon>'
            '<equality><joint name="finger_coupling" joint1="finger_left" joint2="finger_right" '
            'polycoef="0 1 0 0 0" solref="0.004 1"/></equality>')


def _gripper_actuator_xml() -> str:
    """The servo: a position actuator on the opening tendon, its force limited to GRIP_FORCE (per pad: the
    tendon's force acts on each finger with arm 1); `World.step` moves its target at CLOSING_SPEED."""
    return (f'<position name="gripper" tendon="opening" kp="{_f(FINGER_KP)}" ctrlrange="0 {_f(FINGER_MAX_OPENING)}" '
            f'forcerange="{_f(-GRIP_FORCE)} {_f(GRIP_FORCE)}"/>')


# ---- the textured look (services.sim.assets): meshes and textures by absolute path in the asset cache, which the
# render worker process finds as well.

_OBJ_COLLIDE = f'contype="{GROUP_OBJ}" conaffinity="{GROUP_ENV | GROUP_OBJ | GROUP_FINGER | GROUP_FLOOR}"'


def _asset_key(name: str) -> str:
    return name.replace(" ", "_")


def _textured_assets(entities: list[Entity]) -> str:
    """Mesh, texture and material assets of the layout's objects, furniture and room."""
    from services.sim import assets

    root = assets.asset_dir()
    out: list[str] = []
    textures: set[tuple[str, str]] = set()

    def texture(tex: str, kind: str = "2d") -> None:
        if (tex, kind) not in textures:
            textures.add((tex, kind))
            suffix = "" if kind == "2d" else "_cube"
            out.append(f'<texture name="{tex}{suffix}" type="{kind}" file={quoteattr(str(root / (tex + ".png")))}/>')

    texture("floor_parquet")
    out.append('<material name="floor_parquet" texture="floor_parquet" texrepeat="3 3" texuniform="true" '
               'specular="0.1" shininess="0.3"/>')
    texture("wall_paint")
    out.append('<material name="wall_paint" texture="wall_paint" texrepeat="1 1" texuniform="true" specular="0"/>')
    for e in entities:
        key = _asset_key(e.name)
        if e.category in ("surface", "furniture"):
            tex = assets.furniture_texture(e.name)
            texture(tex, "cube")
            out.append(f'<material name="mat_{key}" texture="{tex}_cube" specular="0.1" shininess="0.2"/>')
        elif e.category == "object":
            for part in assets.OBJECT_MODELS[e.name].parts:
                out.append(f'<mesh name="mesh_{part.mesh}" file={quoteattr(str(root / (part.mesh + ".obj")))} '
                           'inertia="shell"/>')
                attrs = f'specular="{_f(part.specular)}" shininess="{_f(part.shininess)}"'
                if part.texture:
                    texture(part.texture)
                    out.append(f'<material name="mat_{part.mesh}" texture="{part.texture}" {attrs}/>')
                else:
                    out.append(f'<material name="mat_{part.mesh}" rgba="{_rgba(part.rgb)}" {attrs}/>')
    return "".join(out)


def _textured_static(e: Entity) -> str:
    """Floor, walls, ceiling and furniture with their textures; the same colliders as the primitive look."""
    look = 'material="wall_paint"' if e.category == "structure" else f'material="mat_{_asset_key(e.name)}"'
    return _static_geom(e, "floor_parquet", look)


def _static_geom(e: Entity, floor_material: str, look: str) -> str:
    """One static collider (floor, wall, ceiling, furniture): its shape and friction are the same in every look;
    `look` is its appearance attribute (an rgba or a material), the floor's is `floor_material`."""
    name = quoteattr(entity_geom_name(e))
    if e.name == "floor":
        return (f'<geom name={name} type="box" size="{_vec(np.array(e.size) / 2)}" pos="{_vec(e.center)}" '
                f'material="{floor_material}" contype="{GROUP_FLOOR}" conaffinity="0" friction="0.8 0.01 0.001"/>')
    if e.shape == "cylinder":
        geom = f'type="cylinder" size="{_f(e.size[0] / 2)} {_f(e.size[2] / 2)}"'
    else:
        geom = f'type="box" size="{_vec(np.array(e.size) / 2)}"'
    return (f'<geom name={name} {geom} pos="{_vec(e.center)}" quat="{_yaw_quat(e.yaw)}" {look} '
            f'contype="{GROUP_ENV}" conaffinity="0" friction="0.6 0.01 0.001"/>')


def _primitive_collider(e: Entity) -> tuple[str, str]:
    if e.shape == "cylinder":
        return "cylinder", f"{_f(e.size[0] / 2)} {_f(e.size[2] / 2)}"
    if e.shape == "sphere":
        return "sphere", _f(e.size[0] / 2)
    return "box", _vec(np.array(e.size) / 2)


def _object_friction(e: Entity, friction: float) -> str:
    """An object collider's friction attributes (both looks: primitive and textured). A round object gets condim
    6: the friction's third (rolling) coefficient only acts in 6-D contacts (a pair takes the larger condim of its
    two geoms), and without it a fruit set down with a few mm/s rolls on for as long as the table lasts, which no
    real one does (dev episode localization/017: an orange still rolling at 4 mm/s when the task ended). With the
    furniture's 1 mm it slows at about 0.17 m/s^2."""
    rolling = ' condim="6"' if e.shape == "sphere" else ""
    return f'friction="{_f(friction)} 0.005 0.0005"{rolling}'


def _textured_object(e: Entity, mass: float, friction: float) -> str:
    """A free body: the object's mass and box inertia, primitive colliders (the first one named like the
    primitive look's geom), and visual-only meshes (group 0, no contacts)."""
    from services.sim import assets

    model = assets.OBJECT_MODELS[e.name]
    sx, sy, sz = e.size
    inertia = [mass / 12 * (sy * sy + sz * sz), mass / 12 * (sx * sx + sz * sz), mass / 12 * (sx * sx + sy * sy)]
    parts = [f'<body name={quoteattr("obj " + e.name)} pos="{_vec(e.center)}" quat="{_yaw_quat(e.yaw)}">',
             f'<freejoint/><inertial pos="0 0 0" mass="{_f(mass)}" diaginertia="{_vec(inertia)}"/>']
    fr = _object_friction(e, friction)
    colliders = model.colliders or (assets.Collider(*_primitive_collider(e)),)  # type: ignore[arg-type]
    for i, c in enumerate(colliders):
        name = entity_geom_name(e) if i == 0 else f"{entity_geom_name(e)}c{i}"
        size = c.size if isinstance(c.size, str) else _vec(c.size)
        parts.append(f'<geom name="{name}" type="{c.type}" size="{size}" pos="{_vec(c.pos)}" quat="{_vec(c.quat)}" '
                     f'{fr} {_OBJ_COLLIDE} group="3" rgba="{_rgba(e.rgb)}"/>')
    for k, part in enumerate(model.parts):
        parts.append(f'<geom name="{entity_geom_name(e)}v{k}" type="mesh" mesh="mesh_{part.mesh}" '
                     f'material="mat_{part.mesh}" contype="0" conaffinity="0" group="0"/>')
    parts.append('</body>')
    return "".join(parts)


def entity_geoms(model: mujoco.MjModel, e: Entity) -> list[int]:
    """Every geom of an entity: its named geom and, for an object, all geoms of its body (colliders, meshes)."""
    gid = model.geom(entity_geom_name(e)).id
    if e.category != "object":
        return [gid]
    b = int(model.geom_bodyid[gid])
    adr, num = int(model.body_geomadr[b]), int(model.body_geomnum[b])
    return list(range(adr, adr + num))


def quat_to_rpy(q: tuple[float, float, float, float]) -> tuple[float, float, float]:
    """z-y-x Euler angles (roll, pitch, yaw) of a unit quaternion (w, x, y, z)."""
    w, x, y, z = q
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


@dataclass
class Contact:
    """A contact the airframe made with something static (furniture, walls, ceiling)."""

    name: str
    speed: float  # vehicle speed towards the surface (along the contact normal) when the contact began, m/s
    crash: bool


@dataclass(frozen=True)
class Verdict:
    """A judge's answer: whether, why (the first failed check, or what passed), every check with its measured
    number, and how many more simulated seconds would turn it true if nothing moved (only a hold or a rest time
    is short; None otherwise)."""

    ok: bool
    message: str
    checks: tuple[JudgeCheck, ...]
    pending_s: float | None = None


@dataclass
class ObjectTrack:
    """What the judge needs of one object's history, in simulated time (`World.sim_time`), advanced every step:
    durations are the world's, never sampled by the judge's caller."""

    rest_since: float | None = None  # at rest (REST_SPEED, REST_SPIN, or asleep) continuously since
    clear_since: float | None = None  # in both pads and touching no other thing continuously since
    lifted_since: float | None = None  # ... and its bottom `criteria.lift_m` above `lifted_from` since
    lifted_from: float | None = None  # top z of what it stood on when both pads took it
    # The incidents' history (knocked, dropped):
    in_pads: bool = False  # in both pads at the last step
    lifted: bool = False  # lifted clear (`lifted_since`) during the current hold
    released_z: float | None = None  # centre z where it left the pads after a lift, until it comes to rest
    ref_set: bool = False  # what it stood on and whether upright, at its last rest out of the gripper's doing:
    ref_support: str | None = None  # the layout, or where a lifted object came to rest after leaving the pads
    ref_upright: bool = False


IncidentKind = Literal["vehicle", "gripper", "knocked", "dropped"]


def incident_kind(value: object) -> IncidentKind:
    """`value` as an incident kind; ValueError when it is none."""
    for kind in get_args(IncidentKind):
        if value == kind:
            return kind  # type: ignore[no-any-return]
    raise ValueError(f"unknown incident kind {value!r}")


@dataclass(frozen=True)
class Incident:
    """One incident since the reset (`World.incidents`; shared.messages.SimIncident on the wire)."""

    kind: IncidentKind
    thing: str
    t_s: float  # simulated time since the reset
    detail: str = ""

    @property
    def tag(self) -> str:
        return f"{self.kind}-{self.thing}"


@dataclass
class World:
    """A layout simulated by MuJoCo. `entities` mirror the simulation (object poses, support, held) after every
    `step`; `version` changes whenever the model is rebuilt (reset)."""

    entities: list[Entity]
    light_seed: int = 0
    light_variation: bool = True
    look: str = "primitive"  # `LOOKS`: what the camera sees (`look_for(realism)`); the physics is alike
    dynamics: str = "kinematic"  # `DYNAMICS`: the vehicle's body (sliding joints, or a free body with rotors)
    version: int = 0
    collisions: list[str] = field(default_factory=list)
    crash_speed: float = CRASH_SPEED
    settle_s: float = 0.3  # let the objects come to rest on their supports before anything else
    criteria: JudgeCriteria = field(default_factory=JudgeCriteria)  # the task's (`Scenario.criteria`)
    target: str | None = None  # the task's object (`Scenario.target_object`): the pads may touch it, not others

    def __post_init__(self) -> None:
        self.xml = build_xml(self.entities, self.light_seed, self.light_variation, self.look, self.dynamics)
        self.model = mujoco.MjModel.from_xml_string(self.xml)
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.multirotor = self.dynamics == "multirotor"
        joints = ("vehicle",) if self.multirotor else ("vx", "vy", "vz", "vyaw")
        self._jnt = {n: m.joint(n).qposadr[0] for n in (*joints, "finger_left", "finger_right")}
        self._dof = {n: m.joint(n).dofadr[0] for n in (*joints, "finger_left", "finger_right")}
        # Free joint: pos, quat at _q0; velocity, body rates at _v0. Kinematic: x, y, z, yaw from _q0 and _v0 on.
        self._q0, self._v0 = int(self._jnt[joints[0]]), int(self._dof[joints[0]])
        self.vehicle_body = m.body("vehicle").id
        n_rotors = len(ROTOR_XY) if self.multirotor else 0
        self.rotor_actuators = [m.actuator(f"rotor{i}").id for i in range(n_rotors)]
        self.rotor_sites = [m.site(f"rotor{i}").id for i in range(n_rotors)]
        self._rotor_act = [int(m.actuator_actadr[a]) for a in self.rotor_actuators]
        first = self.rotor_actuators[0] if self.rotor_actuators else 0
        if self.rotor_actuators != list(range(first, first + n_rotors)):
            raise RuntimeError(f"rotor actuators {self.rotor_actuators} are not contiguous in the model")
        self._rotor_ctrl = slice(first, first + n_rotors)
        self.finger_geoms = (m.geom("finger_left").id, m.geom("finger_right").id)
        self.gripper_geoms = set(self.finger_geoms) | {m.geom("finger_left_arm").id, m.geom("finger_right_arm").id}
        self._grip_act = m.actuator("gripper").id
        self._opening_target = FINGER_MAX_OPENING  # where the servo's target is heading (CLOSING_SPEED)
        self.airframe_geoms = ({m.geom("airframe").id} | {m.geom(f"gear{i}").id for i in range(len(GEAR_OFFSETS))}
                               | {m.geom(f"leg{i}").id for i in range(len(GEAR_OFFSETS))})
        self.vehicle_mass = float(m.body_subtreemass[self.vehicle_body])
        # Inertia of the airframe body about its own axes (the fingers' small bodies left out: the gains need no more).
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, m.body_iquat[self.vehicle_body])
        rot3 = rot.reshape(3, 3)
        inertia = rot3 @ np.diag(m.body_inertia[self.vehicle_body]) @ rot3.T  # principal axes -> body axes
        self.vehicle_inertia = (float(inertia[0, 0]), float(inertia[1, 1]), float(inertia[2, 2]))
        self.geom_entity: dict[int, Entity] = {}
        self.obj_body: dict[str, int] = {}
        self.obj_qadr: dict[str, int] = {}
        self.obj_geoms: dict[str, set[int]] = {}  # an object's colliders (contacts) and meshes
        for e in self.entities:
            geoms = entity_geoms(m, e)
            for gid in geoms:
                self.geom_entity[gid] = e
            if e.category == "object":
                self.obj_geoms[e.name] = set(geoms)
                b = m.body("obj " + e.name)
                self.obj_body[e.name] = b.id
                self.obj_qadr[e.name] = m.jnt_qposadr[b.jntadr[0]]
        # Segmentation lookup: geom id -> instance id (0 for the vehicle's own geoms).
        self.geom_instance = np.zeros(m.ngeom + 1, dtype=np.uint16)
        for gid, e in self.geom_entity.items():
            self.geom_instance[gid] = e.id
        self._static_contact: set[int] = set()
        self._gripper_touching: set[str] = set()  # what a pad or arm touches that is a strike (`_struck`)
        self.incidents: list[Incident] = []  # each tag of `collisions` once, with its time
        self.tracks: dict[str, ObjectTrack] = {e.name: ObjectTrack() for e in self.objects}
        self._ray_geom = np.zeros(1, dtype=np.int32)
        self.contacts: list[Contact] = []
        self.sim_time = 0.0
        self._pending = 0.0
        self.set_fingers(FINGER_MAX_HALF)
        self.data.ctrl[self._grip_act] = FINGER_MAX_OPENING
        self.data.qpos[self._jnt["finger_left"]] = self.data.qpos[self._jnt["finger_right"]] = FINGER_MAX_HALF
        mujoco.mj_forward(self.model, self.data)
        if self.settle_s > 0:
            self.settle(self.settle_s)
        # The layout's objects stand where the generator put them (the settling only absorbed the contact
        # penetration): those at rest count as at rest since the layout, and that is where they belong.
        for e in self.objects:
            t = self.tracks[e.name]
            if t.rest_since is not None:
                t.rest_since = -math.inf
            t.ref_set, t.ref_support, t.ref_upright = True, e.support, self._upright(e)

    # ---- lookup (same names as the layout)

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

    # ---- vehicle state

    def set_vehicle(self, pos: np.ndarray, yaw: float) -> None:
        """Place the vehicle level at `pos` facing `yaw`, at rest, rotors stopped."""
        d, q, v = self.data, self._q0, self._v0
        d.qpos[q:q + 3] = pos
        if self.multirotor:
            d.qpos[q + 3:q + 7] = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
            d.qvel[v:v + 6] = 0.0
        else:
            d.qpos[q + 3] = yaw
            d.qvel[v:v + 4] = 0.0
        for a, adr in zip(self.rotor_actuators, self._rotor_act, strict=True):
            d.ctrl[a] = 0.0
            d.act[adr] = 0.0
        mujoco.mj_forward(self.model, d)
        self._static_contact = set(self._airframe_static_contacts())

    def vehicle_position(self) -> np.ndarray:
        """Body origin in the world (ENU)."""
        return self.data.qpos[self._q0:self._q0 + 3].copy()

    def vehicle_velocity(self) -> np.ndarray:
        """Velocity of the body origin in the world (ENU; a free joint's linear velocity is in the world frame)."""
        return self.data.qvel[self._v0:self._v0 + 3].copy()

    def vehicle_quat(self) -> tuple[float, float, float, float]:
        """Attitude (w, x, y, z) of the body (FLU) in the world (ENU); the kinematic body only yaws."""
        if not self.multirotor:
            yaw = float(self.data.qpos[self._q0 + 3])
            return math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)
        q = self.data.qpos[self._q0 + 3:self._q0 + 7].tolist()
        return q[0], q[1], q[2], q[3]

    def vehicle_rates(self) -> tuple[float, float, float]:
        """Body angular velocity (FLU, rad/s; a free joint's angular velocity is in the body frame)."""
        if not self.multirotor:
            return 0.0, 0.0, float(self.data.qvel[self._v0 + 3])
        w = self.data.qvel[self._v0 + 3:self._v0 + 6].tolist()
        return w[0], w[1], w[2]

    def vehicle_rpy(self) -> tuple[float, float, float]:
        """Roll, pitch, yaw (z-y-x Euler angles of FLU in ENU; pitch positive nose down, as `pose_matrix`)."""
        return quat_to_rpy(self.vehicle_quat())

    def vehicle_roll(self) -> float:
        return self.vehicle_rpy()[0]

    def vehicle_pitch(self) -> float:
        return self.vehicle_rpy()[1]

    def vehicle_yaw(self) -> float:
        if not self.multirotor:
            return float(self.data.qpos[self._q0 + 3])
        return self.vehicle_rpy()[2]

    def vehicle_yaw_rate(self) -> float:
        """Rate of the heading about the world's z axis (rad/s)."""
        if not self.multirotor:
            return float(self.data.qvel[self._v0 + 3])
        w, x, y, z = self.vehicle_quat()
        p, q, r = self.vehicle_rates()
        # Third row of the body-to-world rotation applied to the body rates.
        return 2 * (x * z - w * y) * p + 2 * (y * z + w * x) * q + (1 - 2 * (x * x + y * y)) * r

    def rotor_thrusts(self) -> list[float]:
        """Each rotor's thrust now (the motors' lagged state, before ground effect and noise), newtons."""
        return [float(self.data.act[adr]) for adr in self._rotor_act]

    def set_rotor_commands(self, thrusts: list[float]) -> None:
        """Commanded thrust of each rotor, newtons (one slice assignment: this runs every physics step)."""
        self.data.ctrl[self._rotor_ctrl] = thrusts

    def set_rotor_gains(self, gains: list[float]) -> None:
        """Thrust produced per commanded newton, each rotor (ground effect times thrust noise)."""
        for a, g in zip(self.rotor_actuators, gains, strict=True):
            self.model.actuator_gainprm[a, 0] = g

    def gripper_position(self) -> np.ndarray:
        """World position of the gripper point (between the finger pads)."""
        return self.data.xpos[self.vehicle_body] + self.data.xmat[self.vehicle_body].reshape(3, 3) @ np.array(
            GRIPPER_OFFSET_BODY)

    def finger_width(self) -> float:
        """Opening between the finger pads, metres."""
        return float(self.data.qpos[self._jnt["finger_left"]] + self.data.qpos[self._jnt["finger_right"]])

    def set_fingers(self, half_opening: float) -> None:
        """Command each finger to `half_opening` from the centre line: the servo's target moves there at
        CLOSING_SPEED (of the opening), as a real gripper's does, and it squeezes with at most GRIP_FORCE."""
        self._opening_target = 2 * min(max(half_opening, 0.0), FINGER_MAX_HALF)

    def fingers_closing(self) -> bool:
        return self._opening_target < FINGER_MAX_OPENING / 2

    def _ramp_gripper(self, dt: float) -> None:
        """Move the servo's target towards the commanded opening by CLOSING_SPEED * dt (callers step 20 ms at most:
        3 mm of opening). The target never runs further than twice the force limit's travel (2 x 1.2 cm) past the
        fingers: stopped by an object, the servo pushes with its full force and stalls there, as a real one does,
        so an open command moves the fingers off the object at once instead of first winding its target back."""
        a = self._grip_act
        cmd = float(self.data.ctrl[a])
        ramp = CLOSING_SPEED * dt
        cmd += max(-ramp, min(ramp, self._opening_target - cmd))
        band = 2 * GRIP_FORCE / FINGER_KP
        width = self.finger_width()
        self.data.ctrl[a] = min(max(cmd, width - band), width + band)

    def apply_vehicle_force(self, force: np.ndarray, torque_z: float = 0.0) -> None:
        """Multirotor: an external force on the vehicle's centre of mass (wind, rotor drag), world frame, newtons.
        Kinematic: the whole force and yaw torque that move the body along its sliding joints (its controller's)."""
        if self.multirotor:
            self.data.xfrc_applied[self.vehicle_body, :3] = force
            return
        d, v = self.data, self._v0
        d.qfrc_applied[v:v + 3] = force
        d.qfrc_applied[v + 3] = torque_z

    def rotor_clearance(self, max_dist: float = 2.0) -> list[float]:
        """Distance below each rotor to the first thing under it along the body's -z (floor, furniture, an
        object), capped at `max_dist`: the ground effect's height."""
        d = self.data
        down = -d.xmat[self.vehicle_body].reshape(3, 3)[:, 2]
        out = []
        for sid in self.rotor_sites:
            dist = mujoco.mj_ray(self.model, d, d.site_xpos[sid], down, None, 1, self.vehicle_body, self._ray_geom)
            out.append(max_dist if dist < 0 else min(float(dist), max_dist))
        return out

    # ---- contacts

    def _contact_pairs(self) -> np.ndarray:
        n = self.data.ncon
        if n == 0:
            return np.zeros((0, 2), dtype=int)
        return np.array(self.data.contact.geom[:n], dtype=int).reshape(-1, 2)

    def _airframe_static_contacts(self) -> dict[int, np.ndarray]:
        """Furniture, wall and ceiling geoms the airframe or its landing gear touches (the floor is not a
        collision: landing), each with a contact normal pointing from it towards the vehicle."""
        out: dict[int, np.ndarray] = {}
        for i, (g1, g2) in enumerate(self._contact_pairs()):
            for a, b, sign in ((g1, g2, -1.0), (g2, g1, 1.0)):  # MuJoCo's normal points from geom1 to geom2
                if a in self.airframe_geoms and self.model.geom_bodyid[b] == 0:
                    e = self.geom_entity.get(int(b))
                    if e is not None and e.name != "floor":
                        out[int(b)] = sign * self.data.contact.frame[i, :3]
        return out

    def gear_on_something(self) -> bool:
        """Whether the landing gear (or the airframe) rests on something below it."""
        for g1, g2 in self._contact_pairs():
            for a, b in ((g1, g2), (g2, g1)):
                if a in self.airframe_geoms and b not in self.finger_geoms and self.model.geom_bodyid[b] != \
                        self.vehicle_body:
                    below = self.data.geom_xpos[b][2] < self.data.xpos[self.vehicle_body][2] or \
                        self.geom_entity.get(b) is not None and self.geom_entity[b].category != "object"
                    if below:
                        return True
        return False

    def step(self, dt: float, before_step: Callable[[], None] | None = None) -> list[Contact]:
        """Advance `dt` seconds with the forces and finger targets set now; `before_step` runs before every
        MuJoCo step (the vehicle's attitude and rate loops and mixer, at the physics rate as PX4's rate loop).
        Returns the airframe's new contacts with furniture, walls or the ceiling (each also recorded in
        `collisions`); one begun faster than `crash_speed` is a crash."""
        new: list[Contact] = []
        self._pending += dt  # simulated time not yet stepped (callers' dt need not be a multiple of TIMESTEP)
        n = int(self._pending / TIMESTEP + 1e-9)
        if n == 0:
            return new
        self._pending -= n * TIMESTEP
        velocity = self.vehicle_velocity()
        self._ramp_gripper(n * TIMESTEP)
        if before_step is None:
            mujoco.mj_step(self.model, self.data, nstep=n)
        else:
            for _ in range(n):
                before_step()
                mujoco.mj_step(self.model, self.data)
        self.sim_time += n * TIMESTEP
        now = self._airframe_static_contacts()
        for gid in sorted(now.keys() - self._static_contact):
            # The speed towards the surface is what breaks propellers: a tilting multirotor that brushes a
            # wall it climbs along is not a crash. The kinematic body keeps its whole speed (it never tilts).
            speed = max(0.0, -float(velocity @ now[gid])) if self.multirotor else float(np.linalg.norm(velocity))
            name = _static_name(self.geom_entity[gid])
            c = Contact(name, speed, speed > self.crash_speed)
            new.append(c)
            self.contacts.append(c)
            self._record("vehicle", name, f"{speed:.2f} m/s")
        self._static_contact = set(now)
        struck = self._struck()
        for name in sorted(struck - self._gripper_touching):
            self._record("gripper", name, f"vehicle at {float(np.linalg.norm(velocity)):.2f} m/s")
        self._gripper_touching = struck
        self.sync()
        return new

    def _record(self, kind: IncidentKind, thing: str, detail: str = "") -> None:
        """An incident, each tag once since the reset (`collisions`, `incidents`)."""
        incident = Incident(kind, thing, self.sim_time, detail)
        if incident.tag not in self.collisions:
            self.collisions.append(incident.tag)
            self.incidents.append(incident)

    def _struck(self) -> set[str]:
        """What a finger pad or arm touches that it should not: furniture, a wall, the ceiling (not the floor,
        which a landing may bring the pads down to), or an object other than the task's target."""
        out: set[str] = set()
        for g1, g2 in self._contact_pairs():
            for a, b in ((g1, g2), (g2, g1)):
                e = self.geom_entity.get(int(b)) if a in self.gripper_geoms else None
                if e is None or e.name == "floor" or e.category == "object" and e.name == self.target:
                    continue
                out.add(_static_name(e) if e.category == "structure" else e.name)
        return out

    def settle(self, seconds: float) -> None:
        """Let the objects come to rest (after a reset), the vehicle held where it is."""
        pos, yaw = self.vehicle_position(), self.vehicle_yaw()
        self.step(seconds)
        self.set_vehicle(pos, yaw)
        self.collisions.clear()
        self.incidents.clear()
        self.contacts.clear()
        self._gripper_touching = self._struck()
        self.sim_time = 0.0

    # ---- mirror MuJoCo's state into the entities

    def sync(self) -> None:
        d = self.data
        touching: dict[int, set[int]] = {}
        for g1, g2 in self._contact_pairs():
            touching.setdefault(int(g1), set()).add(int(g2))
            touching.setdefault(int(g2), set()).add(int(g1))
        left, right = self.finger_geoms
        for e in self.objects:
            b = self.obj_body[e.name]
            e.center = d.xpos[b].copy()
            rot = d.xmat[b].reshape(3, 3)
            e.yaw = math.atan2(rot[1, 0], rot[0, 0])
            # Signed: the object's own z axis against the world's up, so upside down is pi, not 0. A sphere has no
            # up.
            e.tilt = math.acos(max(-1.0, min(1.0, float(rot[2, 2])))) if e.shape != "sphere" else 0.0
            track = self.tracks.setdefault(e.name, ObjectTrack())
            if not d.body_awake[b]:
                # Asleep: at rest, no contacts computed; what it rests on stays as it was, and it is not held
                # (a held object shares the never-sleeping vehicle's island).
                e.attached = False
                self._advance(e, track, at_rest=True, clear=False)
                self._watch(e, track)
                continue
            others = set().union(*(touching.get(g, set()) for g in self.obj_geoms[e.name]))
            was_attached = e.attached
            e.attached = left in others and right in others and self.finger_width() > 0.005
            if e.attached and not was_attached:
                below = self.by_name(e.support) if e.support else None
                track.lifted_from = below.top_z if below is not None else e.bottom_z
            support = None
            lowest = math.inf
            for o in others:
                oe = self.geom_entity.get(o)
                if oe is None or o in (left, right):
                    continue
                z = float(d.geom_xpos[o][2]) if oe.category == "object" else oe.top_z
                if z < e.center[2] and z < lowest:
                    support, lowest = oe.name, z
            e.support = None if e.attached else support
            speed, spin = self._motion(e.name)
            # Clear: nothing but the vehicle (pads, airframe) touches it; every other thing is an entity.
            clear = e.attached and not any(o in self.geom_entity for o in others)
            self._advance(e, track, at_rest=speed < REST_SPEED and spin < REST_SPIN and not e.attached, clear=clear)
            self._watch(e, track)

    @staticmethod
    def _upright(e: Entity) -> bool:
        return e.shape != "sphere" and e.tilt < KNOCK_TILT

    def _watch(self, e: Entity, t: ObjectTrack) -> None:
        """Knocked and dropped: an object that left the pads after a lift is watched until it rests (dropped when
        it came to rest more than DROP_FALL lower; where it rests becomes where it belongs, a placement's doing);
        any other object not in the pads is knocked when it tips past KNOCK_TILT from upright or comes to rest on
        something else than it stood on."""
        if e.attached:
            t.in_pads = True
            t.lifted = t.lifted or t.lifted_since is not None
            return
        if t.in_pads:  # just left the pads
            t.in_pads = False
            if t.lifted:
                t.released_z = float(e.center[2])
            t.lifted = False
        at_rest = t.rest_since is not None
        if t.released_z is not None:
            if not at_rest:
                return
            fall = t.released_z - float(e.center[2])
            if fall > DROP_FALL:
                self._record("dropped", e.name, f"fell {fall:.2f} m after leaving the pads")
            t.released_z = None
            t.ref_set = False
        if not t.ref_set:
            if at_rest:
                t.ref_set, t.ref_support, t.ref_upright = True, e.support, self._upright(e)
            return
        if t.ref_upright and e.shape != "sphere" and e.tilt > KNOCK_TILT:
            self._record("knocked", e.name, f"tipped {math.degrees(e.tilt):.0f} deg")
        elif at_rest and t.ref_support is not None and e.support != t.ref_support:
            self._record("knocked", e.name, f"moved from the {t.ref_support} to the {e.support or 'air'}")

    def _motion(self, name: str) -> tuple[float, float]:
        """Linear speed (world, m/s) and spin (rad/s) of an object's free joint."""
        b = self.obj_body[name]
        da = int(self.model.jnt_dofadr[self.model.body_jntadr[b]])
        qv = self.data.qvel
        return float(np.linalg.norm(qv[da:da + 3])), float(np.linalg.norm(qv[da + 3:da + 6]))

    def _advance(self, e: Entity, t: ObjectTrack, at_rest: bool, clear: bool) -> None:
        now = self.sim_time
        if not at_rest:
            t.rest_since = None
        elif t.rest_since is None:
            t.rest_since = now
        if not clear:
            t.clear_since = t.lifted_since = None
            return
        if t.clear_since is None:
            t.clear_since = now
        top = t.lifted_from if t.lifted_from is not None else e.bottom_z
        if e.bottom_z - top < self.criteria.lift_m:
            t.lifted_since = None
        elif t.lifted_since is None:
            t.lifted_since = now

    def object_speed(self, name: str) -> float:
        return self._motion(name)[0]

    def holding(self) -> Entity | None:
        """The object both finger pads touch, if any."""
        return self.attached()

    # ---- the judge's questions: criteria from the task (`criteria`), durations in simulated time

    def picked(self) -> Verdict:
        """Whether the gripper has picked an object: in both pads, touching nothing else, its bottom
        `criteria.lift_m` above the top it was taken from, continuously for `criteria.hold_s`. Returns the
        verdict, why, and each check with its measured number."""
        c = self.criteria
        held = self.holding()
        if held is None:
            state = "closed" if self.fingers_closing() else "open"
            return Verdict(False, f"gripper {state} ({self.finger_width():.3f} m), nothing in both pads", (
                JudgeCheck(name="in_gripper", ok=False, detail="no object touches both pads"),))
        t = self.tracks[held.name]
        top = t.lifted_from if t.lifted_from is not None else held.bottom_z
        lift = held.bottom_z - top
        checks = [JudgeCheck(name="in_gripper", ok=True, detail=f"{held.name} touches both pads"),
                  JudgeCheck(name="clear", ok=t.clear_since is not None,
                             detail="touches nothing but the vehicle" if t.clear_since is not None else
                             "still touches something besides the vehicle"),
                  JudgeCheck(name="lift", ok=t.lifted_since is not None, measured=lift, limit=c.lift_m, unit="m")]
        held_for = self.sim_time - t.lifted_since if t.lifted_since is not None else 0.0
        checks.append(JudgeCheck(name="hold", ok=t.lifted_since is not None and held_for >= c.hold_s,
                                 measured=held_for, limit=c.hold_s, unit="s"))
        if t.clear_since is None:
            why = (f"{held.name} is in the pads but not lifted clear: it still touches something besides the "
                   f"vehicle (bottom {lift:+.3f} m from the top it stood on)")
        elif t.lifted_since is None:
            why = (f"{held.name} is in the pads, lifted only {lift:.3f} m above the top it stood on (needs "
                   f"{c.lift_m:.3f} m)")
        elif held_for < c.hold_s:
            return Verdict(False, f"{held.name} is lifted {lift:.3f} m but held clear for only {held_for:.2f} s "
                           f"(needs {c.hold_s:.2f} s)", tuple(checks), c.hold_s - held_for)
        else:
            return Verdict(True, f"picked {held.name}: lifted {lift:.3f} m, held clear for {held_for:.2f} s",
                           tuple(checks))
        return Verdict(False, why, tuple(checks))

    def placed(self, obj: Entity, surface: Entity | None) -> Verdict:
        """Whether `obj` is placed on `surface` (None: the floor): out of the gripper, resting on it by contact,
        upright within the tolerance (signed: upside down fails; a sphere has no up), its centre inside the
        top's footprint, its bottom within `criteria.top_tolerance_m` of the top, and at rest for
        `criteria.rest_s`. Returns the verdict, why (the first check that fails), and every check."""
        c = self.criteria
        where = surface.name if surface is not None else "floor"
        checks: list[JudgeCheck] = []
        why: list[str] = []

        def check(name: str, ok: bool, reason: str, **kw: float | str | None) -> None:
            checks.append(JudgeCheck(name=name, ok=ok, detail=reason, **kw))  # type: ignore[arg-type]
            if not ok:
                why.append(reason)

        check("released", not obj.attached, "out of the gripper" if not obj.attached else
              f"{obj.name} is in the gripper, not placed on the {where}")
        on = obj.support == where
        check("support", on, f"rests on the {where} by contact" if on else
              f"{obj.name} {'rests on the ' + obj.support if obj.support else 'touches nothing below it'}, not on "
              f"the {where}")
        tilt = math.degrees(obj.tilt)
        upright = tilt <= c.upright_tolerance_deg
        how = "upside down" if tilt > 90 else "tilted"
        check("upright", upright, f"tilt {tilt:.0f} deg" if upright else
              f"{obj.name} lies {how}: its up axis {tilt:.0f} deg from vertical (tolerance "
              f"{c.upright_tolerance_deg:.0f} deg)", measured=tilt, limit=c.upright_tolerance_deg, unit="deg")
        if surface is not None:
            edge = _edge_distance(obj, surface)
            check("footprint", edge >= 0.0, f"centre {edge:.3f} m inside the edge" if edge >= 0 else
                  f"{obj.name}'s centre is {-edge:.3f} m outside the {where}'s top", measured=edge, limit=0.0,
                  unit="m")
            gap = obj.bottom_z - surface.top_z
            check("top", abs(gap) <= c.top_tolerance_m, f"bottom {gap:+.3f} m from the top"
                  if abs(gap) <= c.top_tolerance_m else f"{obj.name}'s bottom is {gap:+.3f} m from the {where}'s "
                  f"top (tolerance {c.top_tolerance_m:.3f} m)", measured=gap, limit=c.top_tolerance_m, unit="m")
        t = self.tracks[obj.name]
        if t.rest_since is None:
            check("rest", False, f"{obj.name} is moving ({self.object_speed(obj.name):.3f} m/s, "
                  f"{self._motion(obj.name)[1]:.2f} rad/s; at rest below {REST_SPEED} m/s and {REST_SPIN} rad/s)",
                  measured=0.0, limit=c.rest_s, unit="s")
        else:
            rest_for = self.sim_time - t.rest_since
            shown = "since the layout" if math.isinf(rest_for) else f"for {rest_for:.2f} s"
            check("rest", rest_for >= c.rest_s, f"at rest {shown}" if rest_for >= c.rest_s else
                  f"{obj.name} at rest for only {rest_for:.2f} s (needs {c.rest_s:.2f} s)",
                  measured=min(rest_for, 1e6), limit=c.rest_s, unit="s")
        failed = [k for k in checks if not k.ok]
        if failed:
            more = "" if len(failed) == 1 else f" (and {len(failed) - 1} more: {', '.join(k.name for k in failed[1:])})"
            rest = checks[-1]
            pending = (rest.limit - rest.measured if [k.name for k in failed] == ["rest"] and t.rest_since is not None
                       and rest.limit is not None and rest.measured is not None else None)
            return Verdict(False, why[0] + more, tuple(checks), pending)
        return Verdict(True, f"{obj.name} placed on the {where}: " + ", ".join(k.detail for k in checks[1:]),
                       tuple(checks))

    def set_object_state(self, name: str, center, quat=(1.0, 0.0, 0.0, 0.0), velocity=(0.0, 0.0, 0.0),
                         spin=(0.0, 0.0, 0.0)) -> Entity:
        """Put an object at `center` (ENU) with orientation `quat` (w, x, y, z), linear `velocity` (world, m/s) and
        `spin` (body frame, rad/s); its judge history restarts (tests and scenario tooling; physics from then
        on)."""
        e = self.by_name(name)
        if e is None or e.category != "object":
            raise KeyError(f"no object {name!r} in this layout; objects: {', '.join(o.name for o in self.objects)}")
        b, qa = self.obj_body[e.name], self.obj_qadr[e.name]
        da = int(self.model.jnt_dofadr[self.model.body_jntadr[b]])
        d = self.data
        d.qpos[qa:qa + 3] = center
        d.qpos[qa + 3:qa + 7] = np.asarray(quat, float) / np.linalg.norm(quat)
        d.qvel[da:da + 3] = velocity
        d.qvel[da + 3:da + 6] = spin
        mujoco.mj_forward(self.model, d)
        self.tracks[e.name] = ObjectTrack()
        e.attached, e.support = False, None
        self.sync()
        return e

    def knock_over(self, name: str) -> bool:
        """Tip an object onto its side where it stands (fault injection: the knock a failed grasp can cause,
        which the contact physics does not reproduce on demand); False when there is no such free object."""
        e = self.by_name(name)
        if e is None or e.category != "object" or e.attached:
            return False
        m, d = self.model, self.data
        adr = self.obj_qadr[name]
        dof = m.jnt_dofadr[m.body(self.obj_body[name]).jntadr[0]]
        # A quarter turn about its own x axis (its long side, as it stands yawed): its own z axis now lies
        # horizontal and its y side stands up. (About the world x axis, a yawed box stood up partly on its long
        # side, taller than the height it was set at: a tissue box yawed 0.4 rad sank 4 cm into the counter and
        # was thrown through the floor.)
        yaw_q = np.array([math.cos(e.yaw / 2), 0.0, 0.0, math.sin(e.yaw / 2)])
        roll_q = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])
        q = np.zeros(4)
        mujoco.mju_mulQuat(q, yaw_q, roll_q)
        d.qpos[adr + 3:adr + 7] = q
        lying = e.size[1]  # its y side now stands up
        d.qpos[adr + 2] = e.bottom_z + lying / 2 + 0.002
        d.qvel[dof:dof + 6] = 0.0
        mujoco.mj_forward(m, d)
        return True

    def slip(self, name: str) -> bool:
        """Pull a held object out of the gripper (fault injection: a grasp that gives way in flight, which the
        contact physics does not produce on demand): it drops from 10 cm below the pads; False when the named
        object is not held."""
        e = self.by_name(name)
        if e is None or e.category != "object" or not e.attached:
            return False
        m, d = self.model, self.data
        adr = self.obj_qadr[name]
        dof = m.jnt_dofadr[m.body(self.obj_body[name]).jntadr[0]]
        d.qpos[adr + 2] -= 0.10 + e.size[2]
        d.qvel[dof:dof + 6] = 0.0
        mujoco.mj_forward(m, d)
        return True

    def state_vector(self) -> np.ndarray:
        """qpos: what a renderer needs besides the model."""
        return self.data.qpos.copy()


def _static_name(e: Entity) -> str:
    """How an incident names a static thing: every wall is "wall"."""
    return "wall" if e.name.startswith("wall") else e.name


def _edge_distance(obj: Entity, surface: Entity) -> float:
    """How far `obj`'s centre lies inside `surface`'s footprint (negative: outside), metres."""
    dx, dy = obj.center[0] - surface.center[0], obj.center[1] - surface.center[1]
    if surface.shape in ("cylinder", "sphere"):
        return float(surface.size[0] / 2 - math.hypot(dx, dy))
    c, s = math.cos(-surface.yaw), math.sin(-surface.yaw)
    lx, ly = c * dx - s * dy, s * dx + c * dy
    return float(min(surface.size[0] / 2 - abs(lx), surface.size[1] / 2 - abs(ly)))
