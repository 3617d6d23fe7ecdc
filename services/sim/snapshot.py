"""The simulator's whole state, captured and restored: the flight fork's world (issue 29).

A capture holds what the next physics step depends on (but which islands sleep: see `restore_core`): the rotors'
current thrust gains, MuJoCo's integration state (time, qpos, qvel,
actuator activations, warm start, controls, applied forces: `mjSTATE_INTEGRATION`), the world's own book-keeping
(the judge's per-object tracks, collisions, what each object rests on), and the vehicle's: the mode logic, the
cascaded controller's integrators and filters, the estimator and the disturbances with their random generators'
states, the gripper, the battery. The layout itself is not copied: it is rebuilt from the scenario it was generated
from (the request: seed, target, destination...; the filled-in one would draw another room), and the rebuilt model
must be the recorded one byte for byte (its MJCF's digest), so a
capture of another version of the simulator is refused rather than restored into a different world.

The encoding is JSON with tagged arrays: no pickle, so reading a log from elsewhere runs no code.
"""

from __future__ import annotations

import base64
import hashlib
import json
import math
from dataclasses import fields, is_dataclass
from typing import Any

import mujoco
import numpy as np

from services.sim.physics import Contact, Incident, incident_kind
from services.sim.vehicle import MAIN_AUTO, MAIN_OFFBOARD, SUB_LOITER, Vehicle

FORMAT = 1
"""Version of the capture's layout: a capture of another format is refused."""
STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION
# Attributes of the vehicle that are not its state: the world it flies (rebuilt from the scenario), views into
# MuJoCo's arrays and the list of the world's objects (rebound when the vehicle is reset on that world), and the
# STATUSTEXT queue (drained by the link).
VEHICLE_SKIP = frozenset({"world", "_qpos", "_qvel", "_objects", "events"})
# Timers on the wall clock of the process that flew (link and failsafe timers): meaningless in another process.
WALL_TIMERS = ("last_sp_wall", "stream_start_wall", "failsafe_since", "landing_touch_wall")


class SnapshotError(ValueError):
    """A capture that cannot be restored here (another format, another world model, a malformed document)."""


def model_digest(xml: str) -> str:
    return hashlib.sha256(xml.encode()).hexdigest()


# --------------------------------------------------------------------------- values


def encode(value: Any) -> Any:
    """A JSON-able form of a state value; objects (plain classes and dataclasses) by their attributes."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        f = float(value)
        return f if math.isfinite(f) else {"__float": repr(f)}
    if isinstance(value, np.ndarray):
        arr = np.ascontiguousarray(value)
        return {"__nd": arr.dtype.str, "shape": list(arr.shape), "data": base64.b64encode(arr.tobytes()).decode()}
    if isinstance(value, np.random.Generator):
        return {"__rng": _plain(value.bit_generator.state)}
    if isinstance(value, tuple):
        return {"__tuple": [encode(v) for v in value]}
    if isinstance(value, list):
        return [encode(v) for v in value]
    if isinstance(value, (set, frozenset)):
        return {"__set": [encode(v) for v in sorted(value)]}
    if isinstance(value, dict):
        return {"__dict": [[encode(k), encode(v)] for k, v in value.items()]}
    if is_dataclass(value) or hasattr(value, "__dict__"):
        return {"__obj": {k: encode(v) for k, v in _attributes(value).items()}}
    raise TypeError(f"cannot capture a {type(value).__name__}")


def decode(doc: Any) -> Any:
    """The value `encode` wrote (objects excepted: those are restored in place, `restore_into`)."""
    if isinstance(doc, list):
        return [decode(v) for v in doc]
    if not isinstance(doc, dict):
        return doc
    if "__float" in doc:
        return float(doc["__float"])
    if "__nd" in doc:
        raw = base64.b64decode(doc["data"])
        return np.frombuffer(raw, dtype=np.dtype(doc["__nd"])).reshape(doc["shape"]).copy()
    if "__tuple" in doc:
        return tuple(decode(v) for v in doc["__tuple"])
    if "__set" in doc:
        return {decode(v) for v in doc["__set"]}
    if "__dict" in doc:
        return {_hashable(decode(k)): decode(v) for k, v in doc["__dict"]}
    raise SnapshotError(f"an object or generator where a value was expected: {sorted(doc)}")


def _hashable(v: Any) -> Any:
    return tuple(v) if isinstance(v, list) else v


def _plain(state: Any) -> dict:
    """A bit generator's state with numpy integers made JSON integers."""
    return json.loads(json.dumps(state, default=int))


def _attributes(obj: Any) -> dict[str, Any]:
    if is_dataclass(obj) and not hasattr(obj, "__dict__"):
        return {f.name: getattr(obj, f.name) for f in fields(obj)}
    return dict(vars(obj))


def restore_into(obj: Any, doc: dict, where: str = "") -> None:
    """Set `obj`'s attributes from an `encode`d object in place: nested objects and random generators are
    restored into the live ones, so references shared between them (one generator drawn by the estimator and
    its filters, the gains the controller reads) stay shared."""
    if "__obj" not in doc:
        raise SnapshotError(f"{where or type(obj).__name__}: expected an object")
    known = _attributes(obj)
    for name, value in doc["__obj"].items():
        here = f"{where}.{name}" if where else name
        if name not in known:
            # Only state this simulator has: a capture cannot create attributes (or reach properties and methods).
            raise SnapshotError(f"{here}: the capture has state this simulator does not have")
        live = known[name]
        if isinstance(value, dict) and "__rng" in value:
            if not isinstance(live, np.random.Generator):
                raise SnapshotError(f"{here}: a generator was captured, this simulator has {type(live).__name__}")
            live.bit_generator.state = value["__rng"]
        elif isinstance(value, dict) and "__obj" in value:
            if live is None:
                raise SnapshotError(f"{here}: an object was captured, this simulator has none there")
            restore_into(live, value, here)
        else:
            setattr(obj, name, decode(value))


def generators(obj: Any, skip: frozenset[str] = frozenset()) -> dict[str, np.random.Generator]:
    """Every random generator reachable through `obj`'s attributes but `skip` (objects walked as `encode` walks
    them), by its path; a generator shared by two owners appears once, under the first path in attribute order."""
    found: dict[str, np.random.Generator] = {}
    seen: set[int] = set()

    def walk(o: Any, path: str) -> None:
        for name, value in sorted(_attributes(o).items()):
            if not path and name in skip:
                continue
            here = f"{path}.{name}" if path else name
            if isinstance(value, np.random.Generator):
                if id(value) not in seen:
                    seen.add(id(value))
                    found[here] = value
            elif not isinstance(value, (type, np.ndarray)) and (is_dataclass(value) or hasattr(value, "__dict__")):
                walk(value, here)

    walk(obj, "")
    return found


def reseed(core: Any, seed: int) -> list[str]:
    """Draw every random process of the vehicle (estimator error, air, thrust noise...) afresh from `seed`,
    keeping the world's state: the same moment with another realisation of the noise (`aermani eval
    --fork-from`'s forks after the first). Each generator gets its own stream, keyed by its path, so the draws
    do not depend on how many generators there are. Returns the paths reseeded."""
    gens = generators(core.vehicle, VEHICLE_SKIP)
    for path, gen in gens.items():
        key = int.from_bytes(hashlib.sha256(path.encode()).digest()[:4], "little")
        gen.bit_generator.state = np.random.default_rng([seed, key]).bit_generator.state
    return sorted(gens)


# --------------------------------------------------------------------------- the world and the vehicle


def capture_core(core: Any) -> dict[str, Any]:
    """The state of a `SimCore` (caller holds its lock) as a JSON-able document."""
    w, v = core.world, core.vehicle
    state = np.empty(mujoco.mj_stateSize(w.model, STATE_SPEC))
    mujoco.mj_getState(w.model, w.data, state, STATE_SPEC)
    entities = {e.name: {"center": encode(np.asarray(e.center, dtype=float)), "yaw": float(e.yaw),
                         "tilt": float(e.tilt), "attached": bool(e.attached), "support": e.support}
                for e in w.entities if e.category == "object"}
    world = {"sim_time": w.sim_time, "pending": w._pending, "collisions": list(w.collisions),
             "contacts": [[c.name, c.speed, c.crash] for c in w.contacts],
             "static_contact": sorted(int(g) for g in w._static_contact),
             "opening_target": float(w._opening_target),
             "gripper_touching": sorted(w._gripper_touching),
             "incidents": [[i.kind, i.thing, i.t_s, i.detail] for i in w.incidents],
             "tracks": {name: encode(t) for name, t in w.tracks.items()}, "entities": entities}
    return {"format": FORMAT, "requested": core.requested.model_dump(mode="json"),
            "scenario": core.scenario.model_dump(mode="json"), "realism": core.realism,
            "dynamics": core.dynamics, "model_digest": model_digest(w.xml), "mujoco": encode(state),
            "world": world, "rotor_gains": [float(w.model.actuator_gainprm[a, 0]) for a in w.rotor_actuators],
            "vehicle": {"__obj": {k: encode(val) for k, val in vars(v).items() if k not in VEHICLE_SKIP}}}


def restore_core(core: Any, doc: dict[str, Any], *, hold: bool = True) -> None:
    """Put a `SimCore` built from the capture's scenario, realism and dynamics into the captured state (caller
    holds its lock). With `hold` (what a fork wants), a vehicle that flew OFFBOARD is left in Hold where it is:
    this process has no setpoint stream yet, as PX4 when its companion computer restarts, and the
    first skill takes it back into OFFBOARD; the wall-clock timers of the process that flew are cleared."""
    if doc.get("format") != FORMAT:
        raise SnapshotError(f"simulator state format {doc.get('format')!r}; this simulator reads {FORMAT}")
    w, v = core.world, core.vehicle
    if doc.get("model_digest") != model_digest(w.xml):
        raise SnapshotError("the world rebuilt from the recorded scenario differs from the recorded one (another "
                            "version of the simulator or its assets): refusing to restore into a different world")
    try:
        state = decode(doc["mujoco"])
        if state.shape != (mujoco.mj_stateSize(w.model, STATE_SPEC),):
            raise SnapshotError(f"MuJoCo state of {state.size} numbers; this model has "
                                f"{mujoco.mj_stateSize(w.model, STATE_SPEC)}")
        mujoco.mj_setState(w.model, w.data, state, STATE_SPEC)
        # Model parameters the vehicle changes between its outer-loop ticks (ground effect x thrust noise). Which
        # islands sleep is not restored: it lies outside MuJoCo's integration state, and writing `tree_asleep`
        # back broke the restored flight here (the 3 s dash 0.8 m off), so a restore wakes every island and they
        # fall asleep again after MuJoCo's sleep delay (resting objects stay where they rest).
        gains = [float(g) for g in doc.get("rotor_gains", [])]
        if len(gains) != len(w.rotor_actuators):
            raise SnapshotError(f"{len(gains)} rotor gains captured; this vehicle has {len(w.rotor_actuators)} rotors")
        w.set_rotor_gains(gains)
        mujoco.mj_forward(w.model, w.data)
        ws = doc["world"]
        w.sim_time, w._pending = float(ws["sim_time"]), float(ws["pending"])
        w.collisions[:] = [str(c) for c in ws["collisions"]]
        w.contacts[:] = [Contact(str(n), float(s), bool(c)) for n, s, c in ws["contacts"]]
        w._static_contact = {int(g) for g in ws["static_contact"]}
        w._opening_target = float(ws["opening_target"])
        w._gripper_touching = {str(n) for n in ws["gripper_touching"]}
        w.incidents[:] = [Incident(incident_kind(k), str(n), float(t), str(d)) for k, n, t, d in ws["incidents"]]
        for name, track in ws["tracks"].items():
            if name not in w.tracks:
                raise SnapshotError(f"object {name!r} of the capture is not in the rebuilt world")
            restore_into(w.tracks[name], track, f"tracks[{name}]")
        for e in w.entities:
            saved = ws["entities"].get(e.name)
            if e.category != "object":
                continue
            if saved is None:
                raise SnapshotError(f"object {e.name!r} of the rebuilt world is not in the capture")
            e.center, e.yaw, e.tilt = decode(saved["center"]), float(saved["yaw"]), float(saved["tilt"])
            e.attached, e.support = bool(saved["attached"]), saved["support"]
        captured = doc["vehicle"].get("__obj", {}) if isinstance(doc["vehicle"], dict) else {}
        skipped = sorted(set(captured) & VEHICLE_SKIP)
        if skipped:
            raise SnapshotError(f"vehicle: the capture sets {', '.join(skipped)}, which no capture holds")
        restore_into(v, doc["vehicle"], "vehicle")
    except SnapshotError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, RecursionError) as exc:
        raise SnapshotError(f"malformed simulator state: {type(exc).__name__}: {exc}") from exc
    v.events = []
    if hold:
        _hold_where_flying(v)


def _hold_where_flying(v: Vehicle) -> None:
    for name in WALL_TIMERS:
        setattr(v, name, None)
    if v.main_mode == MAIN_OFFBOARD:
        # Where it is, as PX4's failsafe holds: the skill that ended had stopped it there (the old setpoint may
        # still be the goto's target, which the skill's arrival tolerance left a few centimetres ahead).
        v.main_mode, v.sub_mode = MAIN_AUTO, SUB_LOITER
        v.hold_pos, v.hold_yaw = v.p.copy(), float(v.yaw)
    v.sp_pos = v.sp_vel = v.sp_yaw = v.sp_yaw_rate = None
