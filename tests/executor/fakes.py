"""Stand-ins for the autopilot bridge, perception and the depth camera, served on a real Zenoh bus.

They answer the same keys with the same messages as the real services, with a simple kinematic vehicle and
a toy world (objects, surfaces, a camera frustum), so executor logic can be tested without the simulator."""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from dataclasses import dataclass, field

import numpy as np

from shared.bus import Bus
from shared.frames import DEFAULT_INTRINSICS
from shared.keys import Keys
from shared.messages import (
    AutopilotResult,
    Detection,
    Detections,
    GripperState,
    LandedState,
    LocalizeRequest,
    ObjectEstimate,
    PlacementEstimate,
    Pose,
    Vec3,
    VehicleState,
    now_ns,
)
from shared.sensors import calibration_message, color_message, depth_message, encode_jpeg

_GREY_JPEG = encode_jpeg(np.full((480, 640, 3), 128, np.uint8))


@dataclass
class Thing:
    name: str
    center: np.ndarray
    size: tuple[float, float, float]
    attached: bool = False
    catalog: tuple[float, float, float] | None = None  # what perception's catalogue says of it standing
    hang: float | None = None  # held: its centre this far below the gripper point (where the fingers took it)

    @property
    def top(self) -> float:
        return float(self.center[2] + self.size[2] / 2)


ROCK_LOOKS = 10


@dataclass
class ToyWorld:
    objects: dict[str, Thing] = field(default_factory=dict)
    surfaces: dict[str, Thing] = field(default_factory=dict)
    topple: set[str] = field(default_factory=set)
    """Objects that fall over when next released: they lie on their side (x and z swap: the height becomes the
    length) and rock, each of the next `ROCK_LOOKS` localizations seeing them 3 cm to the other side. Once."""
    slip_below: dict[str, float] = field(default_factory=dict)
    """Objects that slip out of the fingers when the gripper point, carrying them, comes below this height: they
    fall onto what is under them there (lying, when also in `topple`). Once."""
    rocking: dict[str, int] = field(default_factory=dict)
    looks: dict[str, list[tuple[float, ...]]] = field(default_factory=dict)
    """Per object, what its next localizations read off the truth, one (dx, dtop) or (dx, dtop, dz) per look, in
    metres: a view that scatters (dx back and forth), one that runs off (dx growing: rolling), a top read low
    (dtop < 0: the height read short), the whole view lower or higher (dz: the vehicle's estimate wandered)."""

    def add_object(self, name: str, x: float, y: float, support_z: float, size=(0.08, 0.08, 0.11),
                   catalog: tuple[float, float, float] | None = None) -> Thing:
        t = Thing(name, np.array([x, y, support_z + size[2] / 2]), size, catalog=catalog)
        self.objects[name] = t
        return t

    def add_surface(self, name: str, x: float, y: float, top: float, size=(1.2, 0.8)) -> Thing:
        t = Thing(name, np.array([x, y, top / 2]), (size[0], size[1], top))
        self.surfaces[name] = t
        return t

    def grab(self, g: np.ndarray) -> Thing | None:
        for t in self.objects.values():
            if (not t.attached and math.hypot(g[0] - t.center[0], g[1] - t.center[1]) <= 0.07
                    and t.center[2] <= g[2] <= t.top + 0.05):
                t.attached = True
                t.hang = min(float(g[2] - t.center[2]), t.size[2] / 2)
                return t
        return None

    def carry(self, g: np.ndarray) -> None:
        for t in self.objects.values():
            if t.attached:
                t.center = np.array([g[0], g[1], g[2] - (t.size[2] / 2 if t.hang is None else t.hang)])
                if t.name in self.slip_below and g[2] < self.slip_below[t.name]:
                    del self.slip_below[t.name]
                    self._drop(t)

    def release(self) -> None:
        for t in self.objects.values():
            if t.attached:
                self._drop(t)

    def _drop(self, t: Thing) -> None:
        """Out of the fingers: it comes to rest on what is under it (lying, when it is to topple)."""
        t.attached = False
        support = 0.0
        for s in self.surfaces.values():
            if (abs(t.center[0] - s.center[0]) <= s.size[0] / 2 and abs(t.center[1] - s.center[1])
                    <= s.size[1] / 2 and s.top <= t.center[2] - t.size[2] / 2 + 0.02):
                support = max(support, s.top)
        if t.name in self.topple:
            self.topple.discard(t.name)
            t.size = (t.size[2], t.size[1], t.size[0])
            self.rocking[t.name] = ROCK_LOOKS
        t.center = np.array([t.center[0], t.center[1], support + t.size[2] / 2])


class FakeAutopilot:
    """Kinematic vehicle: goto ramps at max_speed, yaw at 90 deg/s; hold freezes; publishes state at 50 Hz."""

    def __init__(self, bus: Bus, keys: Keys, world: ToyWorld | None = None, airborne_at: float | None = None,
                 rate_hz: float = 50.0) -> None:
        self.bus, self.keys, self.world = bus, keys, world
        self.pos = np.zeros(3)
        self.vel = np.zeros(3)
        self.yaw = 0.0
        self.target: np.ndarray | None = None
        self.target_yaw = 0.0
        self.speed = 1.0
        self.armed = False
        self.landed = LandedState.ON_GROUND
        self.gripper = GripperState.OPEN
        self.link_ok = True
        self.offboard_ok = False
        self.px4_mode = "POSCTL"  # the mode reported when not in OFFBOARD (the pilot's, or PX4's AUTO.LOITER)
        self.publishing = True
        self.fingers = False
        """Report the finger gap and contact (as the simulator's gripper does: the held thing's narrower side, 0
        closed on nothing, 0.18 m open); off, a gripper without sensing."""
        self.commands: list[str] = []
        self.dt = 1.0 / rate_hz
        if airborne_at is not None:
            self.pos[2] = airborne_at
            self.armed, self.landed, self.offboard_ok = True, LandedState.IN_AIR, True
            self.target = self.pos.copy()

    def moving_commands(self) -> list[str]:
        return [c for c in self.commands if c in ("goto", "takeoff", "land", "arm")]

    def state(self) -> VehicleState:
        return VehicleState(vehicle_id=self.keys.vehicle_id, position=Vec3(x=self.pos[0], y=self.pos[1], z=self.pos[2]),
                            velocity=Vec3(x=self.vel[0], y=self.vel[1], z=self.vel[2]), yaw=self.yaw, armed=self.armed,
                            mode="OFFBOARD" if self.offboard_ok else self.px4_mode, landed_state=self.landed,
                            gripper=self.gripper, link_ok=self.link_ok, offboard_ok=self.offboard_ok,
                            **self.finger_sense())

    def finger_sense(self) -> dict[str, float | bool]:
        if not self.fingers:
            return {}
        held = next((t for t in self.world.objects.values() if t.attached), None) if self.world else None
        if held is not None:
            return {"gripper_width": min(held.size[0], held.size[1]), "gripper_holding": True}
        return {"gripper_width": 0.0 if self.gripper == GripperState.CLOSED else 0.18, "gripper_holding": False}

    def gripper_point(self) -> np.ndarray:
        return self.pos + np.array([0.0, 0.0, -0.22])

    async def handle(self, cmd) -> AutopilotResult:
        self.commands.append(cmd.kind)
        ok = True
        if cmd.kind == "arm":
            self.armed = True
        elif cmd.kind == "takeoff":
            self.armed = True  # like the bridge: takeoff arms (PX4 ACK) and returns once at altitude
            self.landed = LandedState.TAKEOFF
            self.target, self.speed = np.array([self.pos[0], self.pos[1], cmd.altitude]), 1.0
            while self.pos[2] < cmd.altitude - 1e-6:
                await asyncio.sleep(self.dt)
            self.landed, self.offboard_ok = LandedState.IN_AIR, True
        elif cmd.kind == "goto":
            self.offboard_ok = True  # like the bridge: a goto from PX4's Hold enters OFFBOARD first
            p = cmd.position
            self.target, self.target_yaw = np.array([p.x, p.y, p.z]), cmd.yaw
            self.speed = cmd.max_speed or 1.0
        elif cmd.kind == "hold":
            self.target, self.target_yaw = self.pos.copy(), self.yaw
            self.vel[:] = 0.0
        elif cmd.kind == "land":
            self.landed = LandedState.LANDING
            self.target, self.speed = np.array([self.pos[0], self.pos[1], 0.0]), 0.8
        elif cmd.kind == "gripper":
            self.gripper = GripperState.CLOSED if cmd.action == "close" else GripperState.OPEN
            if self.world is not None:
                if cmd.action == "close":
                    self.world.grab(self.gripper_point())
                else:
                    self.world.release()
        return AutopilotResult(ok=ok, command=cmd.kind, message="ok")

    def step(self) -> None:
        if self.target is not None:
            d = self.target - self.pos
            n = float(np.linalg.norm(d))
            stepn = self.speed * self.dt
            if n <= stepn:
                self.pos = self.target.copy()
                self.vel[:] = 0.0
            else:
                self.vel = d / n * self.speed
                self.pos = self.pos + self.vel * self.dt
            err = (self.target_yaw - self.yaw + math.pi) % (2 * math.pi) - math.pi
            turn = math.radians(90) * self.dt
            self.yaw = self.target_yaw if abs(err) <= turn else self.yaw + math.copysign(turn, err)
            self.yaw = (self.yaw + math.pi) % (2 * math.pi) - math.pi
        if self.landed == LandedState.LANDING and self.pos[2] <= 0.01:
            self.landed, self.armed, self.offboard_ok, self.target = LandedState.ON_GROUND, False, False, None
        if self.world is not None:
            self.world.carry(self.gripper_point())

    async def run(self) -> None:
        self.bus.serve(self.keys.autopilot_command, lambda cmd: self.handle(cmd))  # a test may swap handle
        while True:
            self.step()
            if self.publishing:
                self.bus.publish(self.keys.autopilot_state, self.state())
            await asyncio.sleep(self.dt)


class FakePerception:
    """Localizes toy-world things inside a camera frustum pitched 35 deg down (never right below)."""

    def __init__(self, bus: Bus, keys: Keys, world: ToyWorld, vehicle: FakeAutopilot) -> None:
        self.bus, self.keys, self.world, self.vehicle = bus, keys, world, vehicle
        self.queries: list[str] = []

    def visible(self, p: np.ndarray) -> bool:
        cam = self.vehicle.pos + np.array([0.12 * math.cos(self.vehicle.yaw), 0.12 * math.sin(self.vehicle.yaw), -0.05])
        d = p - cam
        horiz = math.hypot(d[0], d[1])
        if horiz < 0.05:
            return False
        bearing = (math.atan2(d[1], d[0]) - self.vehicle.yaw + math.pi) % (2 * math.pi) - math.pi
        depression = math.degrees(math.atan2(-d[2], horiz))
        return abs(bearing) < math.radians(40) and 1.0 < depression < 68.0 and horiz < 4.0

    async def localize_object(self, req: LocalizeRequest) -> ObjectEstimate:
        self.queries.append(req.query)
        for t in self.world.objects.values():
            if req.query.lower() in t.name and not t.attached and self.visible(t.center):
                rock = self.world.rocking.get(t.name, 0)
                dx = 0.03 * (1 if rock % 2 else -1) if rock else 0.0
                if rock:
                    self.world.rocking[t.name] = rock - 1
                queued = self.world.looks.get(t.name)
                ox, otop, oz = (*queued.pop(0), 0.0)[:3] if queued else (0.0, 0.0, 0.0)
                # A top read low is a height read short (perception measures the height from the support under
                # it); `oz` shifts the whole view (the vehicle's vertical estimate wandered since the last look).
                return ObjectEstimate(query=req.query, found=True, label=t.name,
                                      pose=Pose(position=Vec3(x=t.center[0] + dx + ox, y=t.center[1],
                                                              z=t.center[2] + oz)),
                                      size=Vec3(x=t.size[0], y=t.size[1], z=t.size[2] + otop), top_z=t.top + otop + oz,
                                      support_z=t.center[2] - t.size[2] / 2 + oz, confidence=0.9,
                                      frame_stamp_ns=now_ns(),
                                      catalog_size=Vec3(x=t.catalog[0], y=t.catalog[1], z=t.catalog[2])
                                      if t.catalog else None)
        return ObjectEstimate(query=req.query, found=False, reason="not_visible", message=f"{req.query} not visible")

    async def localize_placement(self, req: LocalizeRequest) -> PlacementEstimate:
        self.queries.append(req.query)
        for t in self.world.surfaces.values():
            if req.query.lower() in t.name and self.visible(np.array([t.center[0], t.center[1], t.top])):
                return PlacementEstimate(query=req.query, found=True, label=t.name,
                                         pose=Pose(position=Vec3(x=t.center[0], y=t.center[1], z=t.top + 0.02)),
                                         surface_z=t.top, vertical_offset=0.02, confidence=0.9,
                                         frame_stamp_ns=now_ns())
        return PlacementEstimate(query=req.query, found=False, reason="not_visible", message=f"{req.query} not visible")

    def serve(self) -> None:
        self.bus.serve(self.keys.localize_object, self.localize_object)
        self.bus.serve(self.keys.localize_placement, self.localize_placement)

    async def run(self) -> None:
        """Publish what is in view at 5 Hz, like perception's `perception/detections`."""
        while True:
            items = tuple(Detection(label=t.name, category="object", confidence=0.9,
                                    centroid=Vec3(x=t.center[0], y=t.center[1], z=t.center[2]))
                          for t in self.world.objects.values() if not t.attached and self.visible(t.center))
            self.bus.publish(self.keys.detections, Detections(stamp_ns=now_ns(), items=items))
            await asyncio.sleep(0.2)


class FakeDepth:
    """The camera: a uniform depth image (`distance_m` along the optical axis everywhere) at 10 Hz, with a
    grey colour frame of the same stamp and the calibration, like the camera service."""

    def __init__(self, bus: Bus, keys: Keys, distance_m: float = 8.0) -> None:
        self.bus, self.keys, self.distance_m = bus, keys, distance_m
        self.publishing = True

    async def run(self) -> None:
        while True:
            if self.publishing:
                stamp = time.time_ns()
                img = np.full((480, 640), int(self.distance_m * 1000), dtype=np.uint16)
                self.bus.publish(self.keys.camera_depth, depth_message(img, stamp))
                self.bus.publish(self.keys.camera_color, color_message(None, stamp, jpeg=_GREY_JPEG))  # type: ignore[arg-type]
                self.bus.publish(self.keys.camera_calibration, calibration_message(DEFAULT_INTRINSICS, stamp))
            await asyncio.sleep(0.1)


async def cancel_all(tasks: list[asyncio.Task]) -> None:
    for t in tasks:
        t.cancel()
    for t in tasks:
        with contextlib.suppress(BaseException):
            await t
