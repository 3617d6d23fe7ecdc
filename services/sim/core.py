"""The simulator state shared by the MAVLink thread, the renderer and the queryables, behind one lock."""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from dataclasses import dataclass

import numpy as np

from services.sim.physics import configured_dynamics, look_for
from services.sim.scenarios import ScenarioError, generate
from services.sim.snapshot import capture_core, restore_core
from services.sim.vehicle import Vehicle, VehicleParams, enu_to_ned, wrap
from shared.messages import (
    JudgeRequest,
    JudgeResult,
    Pose,
    Scenario,
    SimIncident,
    SimLabel,
    SimObjectTruth,
    SimResetResult,
    Vec3,
)

log = logging.getLogger("aermani.sim")


@dataclass(frozen=True)
class Snapshot:
    """What one camera frame needs, copied under the lock so rendering runs without it (or in another process:
    the MJCF text rebuilds the model there when `version` changes, `qpos` poses it)."""

    version: int
    xml: str
    qpos: np.ndarray  # MuJoCo's state: the true poses the camera sees
    geom_instance: np.ndarray  # geom id -> instance id (segmentation)
    position: np.ndarray  # ENU body origin as estimated (what tf publishes)
    yaw: float  # ENU, estimated
    roll: float = 0.0  # FLU roll and pitch (pitch positive nose down, as shared.sensors.pose_matrix), the IMU's
    pitch: float = 0.0


class SimCore:
    """The simulated world and vehicle behind one lock: physics steps, camera renders and scenario resets."""

    def __init__(self, scenario: Scenario, params: VehicleParams | None = None, realism: str = "realistic",
                 dynamics: str | None = None) -> None:
        self.lock = threading.RLock()
        self.realism = realism
        if dynamics is None:  # the configured one (AERMANI_SIM_DYNAMICS, multirotor by default)
            dynamics = configured_dynamics()
        self.dynamics = dynamics  # physics.DYNAMICS: the vehicle's body (SimSettings.dynamics)
        world, filled, start = generate(scenario, light_variation=realism != "ideal", look=look_for(realism),
                                        dynamics=dynamics)
        self.world = world
        self.scenario = filled
        self.requested = scenario  # what the layout was generated from (the filled one lays out another room)
        self.vehicle = Vehicle(world, params)
        self._place_vehicle(start)
        self.setpoint_arrivals_ns: deque[int] = deque(maxlen=20_000)
        self.counters: dict[str, int] = {}
        self.resets = 0

    @classmethod
    def from_capture(cls, doc: dict, params: VehicleParams | None = None, *, hold: bool = True) -> SimCore:
        """The world and vehicle of a capture (`capture`, services.sim.snapshot): the layout rebuilt from its
        scenario, then every state restored; raises SnapshotError when it cannot be."""
        from services.sim.snapshot import SnapshotError

        try:
            scenario = Scenario.model_validate(doc["requested"])
            realism, dynamics = str(doc["realism"]), str(doc["dynamics"])
        except (KeyError, TypeError, ValueError) as exc:
            raise SnapshotError(f"malformed simulator state: {exc}") from exc
        core = cls(scenario, params, realism=realism, dynamics=dynamics)
        with core.lock:
            restore_core(core, doc, hold=hold)
        return core

    def capture(self) -> dict:
        """Everything the next physics step depends on, as JSON (services.sim.snapshot)."""
        with self.lock:
            return capture_core(self)

    def _place_vehicle(self, start: Pose) -> None:
        p = enu_to_ned(np.array([start.position.x, start.position.y, 0.0]))
        self.vehicle.reset(p, wrap(math.pi / 2 - start.yaw), self.world)

    # ---- queryables

    def reset(self, scenario: Scenario) -> SimResetResult:
        try:
            world, filled, start = generate(scenario, light_variation=self.realism != "ideal",
                                            look=look_for(self.realism), dynamics=self.dynamics)
        except ScenarioError as exc:
            return SimResetResult(ok=False, message=str(exc))
        with self.lock:
            world.version = self.world.version + 1
            self.world = world
            self.scenario = filled
            self.requested = scenario
            self._place_vehicle(start)
            self.resets += 1
        log.info("reset to scenario %s", filled.model_dump_json())
        return SimResetResult(ok=True, message=f"world reset with seed {filled.seed}", scenario=filled)

    def judge(self, req: JudgeRequest) -> JudgeResult:
        """The ground-truth verdict by the scenario's criteria (set by the task at reset, held by the world);
        `req.tolerance` is deprecated and ignored, so no caller can loosen them."""
        with self.lock:
            w = self.world
            held = w.holding()
            incidents = tuple(SimIncident(kind=i.kind, thing=i.thing, t_s=i.t_s, detail=i.detail)
                              for i in w.incidents)
            common = {"held": held.name if held else None, "vehicle": self.vehicle_pose(),
                      "collisions": tuple(w.collisions), "incidents": incidents, "scenario": self.scenario,
                      "sim_time_s": max(0.0, float(w.sim_time))}
            if req.op == "held":
                v = w.picked()
                return JudgeResult(ok=v.ok, message=v.message, checks=v.checks, pending_s=v.pending_s, **common)
            if req.op == "on_surface":
                obj = w.by_name(req.object or "")
                surf = w.by_name(req.surface or "")
                if obj is None or obj.category != "object":
                    return JudgeResult(ok=False, message=f"unknown object {req.object!r}", **common)
                if req.surface and req.surface.strip().lower() == "floor":
                    v = w.placed(obj, None)
                elif surf is None or surf.category not in ("surface", "furniture"):
                    return JudgeResult(ok=False, message=f"unknown surface {req.surface!r}", **common)
                else:
                    v = w.placed(obj, surf)
                return JudgeResult(ok=v.ok, message=v.message, checks=v.checks, pending_s=v.pending_s, **common)
            truths = tuple(
                SimObjectTruth(name=e.name, category=e.category, position=Vec3(x=e.center[0], y=e.center[1],
                                                                               z=e.center[2]),
                               yaw=e.yaw, size=Vec3(x=e.size[0], y=e.size[1], z=e.size[2]), top_z=e.top_z,
                               attached=e.attached, support=e.support)
                for e in w.entities if e.category in ("object", "surface", "furniture"))
            return JudgeResult(ok=True, message=f"{len(truths)} things", objects=truths, **common)

    def labels(self) -> tuple[SimLabel, ...]:
        with self.lock:
            return tuple(SimLabel(id=e.id, name=e.name, category=e.category, color=e.color,
                                  size=Vec3(x=e.size[0], y=e.size[1], z=e.size[2])) for e in self.world.entities)

    def vehicle_pose(self) -> Pose:
        """The true pose (the judge's; the autopilot reports its estimate)."""
        with self.lock:
            p = self.vehicle.true_position_enu()
            return Pose(position=Vec3(x=p[0], y=p[1], z=p[2]), yaw=self.vehicle.true_yaw_enu())

    def snapshot(self) -> Snapshot:
        with self.lock:
            w = self.world
            roll, pitch, _ = w.vehicle_rpy()
            return Snapshot(w.version, w.xml, w.state_vector(), w.geom_instance, self.vehicle.position_enu(),
                            self.vehicle.yaw_enu(), roll, pitch)

    # ---- statistics

    def count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n

    def setpoint_stats(self) -> dict:
        """Intervals between received SET_POSITION_TARGET_LOCAL_NED (kernel receive timestamps), in ms."""
        arr = np.array(self.setpoint_arrivals_ns, dtype=np.int64)
        if len(arr) < 3:
            return {"n": int(len(arr))}
        iv = np.diff(arr) / 1e6
        return {"n": int(len(arr)), "interval_ms_p50": float(np.percentile(iv, 50)),
                "interval_ms_p99": float(np.percentile(iv, 99)), "interval_ms_max": float(iv.max()),
                "interval_ms_mean": float(iv.mean()),
                "jitter_ms_p99": float(np.percentile(np.abs(iv - np.median(iv)), 99))}

