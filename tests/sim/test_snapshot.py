"""The simulator's whole state captured and restored (the flight fork's world, issue 29): a restored copy flies on
exactly as the original does; a capture of another world, or a malformed one, is refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from services.sim.app import restored
from services.sim.core import SimCore
from services.sim.settings import SimSettings
from services.sim.snapshot import SnapshotError, reseed
from services.sim.vehicle import MAIN_OFFBOARD, realism_params
from shared.errors import ConfigError
from shared.messages import JudgeRequest, Scenario, SimState
from tests.sim.flight import Clock, grasp, to_offboard

SCENARIO = Scenario(seed=3, target_object="red cup", destination="table")


def holding_the_cup(dynamics: str) -> tuple[SimCore, Clock]:
    """A realistic world (noise, drift, on the multirotor wind and thrust noise) whose vehicle holds the cup."""
    core = SimCore(SCENARIO, realism_params("realistic", seed=3), realism="realistic", dynamics=dynamics)
    clock = Clock(core)
    to_offboard(core, clock)
    assert grasp(core, clock, "red cup", 0.0)
    return core, clock


def fly_on(core: SimCore, now: float) -> list[np.ndarray]:
    """The same 3 s for any copy: a dash with the cup, then a hover; every 10 ms the true and estimated pose."""
    clock = Clock(core)
    clock.now = now
    track: list[np.ndarray] = []
    v = core.vehicle
    target = v.p + np.array([0.8, -0.5, 0.2])
    clock.run(3.0, (target, v.yaw + 0.5), record=track)
    return [np.concatenate([p, vel, [yaw], core.world.data.qpos]) for p, vel, yaw in track]


@pytest.mark.parametrize("dynamics", ["multirotor", "kinematic"])
def test_a_restored_world_flies_on_as_the_original(dynamics: str) -> None:
    core, clock = holding_the_cup(dynamics)
    doc = json.loads(json.dumps(core.capture()))  # through JSON, as it is recorded
    # Another process's settings: a different seed and realism; the capture's own win.
    copy = SimCore.from_capture(doc, realism_params("ideal", seed=99), hold=False)
    assert copy.vehicle.armed and copy.vehicle.main_mode == MAIN_OFFBOARD
    assert copy.judge(JudgeRequest(op="held")).ok  # the judge's tracks came along: held since the grasp
    a, b = fly_on(core, clock.now), fly_on(copy, clock.now)
    assert len(a) == len(b) == 300
    worst = max(float(np.abs(x - y).max()) for x, y in zip(a, b, strict=True))
    assert worst < 1e-6, worst  # MuJoCo's state, the controller's integrators and the random draws all restored
    assert np.linalg.norm(a[-1][:3] - a[0][:3]) > 0.5  # and it did fly somewhere
    assert core.judge(JudgeRequest(op="held")).ok and copy.judge(JudgeRequest(op="held")).ok


def test_a_fork_holds_where_the_vehicle_flew_offboard() -> None:
    core, clock = holding_the_cup("kinematic")
    here = core.vehicle.p.copy()
    copy = SimCore.from_capture(core.capture())
    v = copy.vehicle
    # No setpoint stream in the new process: PX4 would hold; the first skill takes it back into OFFBOARD.
    assert v.mode_name == "AUTO.LOITER" and v.armed and not v.on_ground
    assert np.allclose(v.hold_pos, here) and v.sp_pos is None and v.last_sp_wall is None
    Clock(copy).run(2.0)
    assert np.linalg.norm(v.p - here) < 0.03 and copy.judge(JudgeRequest(op="held")).ok


def test_a_capture_of_another_world_or_format_is_refused() -> None:
    core = SimCore(SCENARIO, realism="ideal", dynamics="kinematic")
    doc = core.capture()
    with pytest.raises(SnapshotError, match="differs from the recorded one"):
        SimCore.from_capture({**doc, "model_digest": "0" * 64})
    with pytest.raises(SnapshotError, match="format"):
        SimCore.from_capture({**doc, "format": 99})
    with pytest.raises(SnapshotError, match="malformed"):
        SimCore.from_capture({**doc, "world": {"sim_time": 1.0}})
    with pytest.raises(SnapshotError, match="malformed"):
        SimCore.from_capture({"format": 1})
    # A capture sets only state this simulator has: no new attribute, no property, nothing a capture never holds.
    vehicle = doc["vehicle"]["__obj"]
    for name, value in (("injected", 1), ("mode_name", "x"), ("world", None), ("step", 0)):
        bad = {**doc, "vehicle": {"__obj": {**vehicle, name: value}}}
        with pytest.raises(SnapshotError):
            SimCore.from_capture(bad)
    with pytest.raises(SnapshotError, match="rotor gains"):
        SimCore.from_capture({**doc, "rotor_gains": [1.0]})


def test_the_simulator_starts_from_a_recorded_state(tmp_path) -> None:
    core, _clock = holding_the_cup("kinematic")
    sample = SimState(task_id="task-1", step=4, skill="grasp", state=json.dumps(core.capture()))
    path = tmp_path / "state.json"
    path.write_text(sample.model_dump_json())
    settings = SimSettings(restore=str(path))
    params = realism_params(settings.realism, seed=settings.seed)
    back = restored(settings, params)
    assert back.judge(JudgeRequest(op="held")).ok and back.vehicle.mode_name == "AUTO.LOITER"
    assert np.allclose(back.vehicle.true_position_enu(), core.vehicle.true_position_enu())
    assert back.scenario == core.scenario
    fresh = restored(SimSettings(restore=str(path), restore_seed=4), params)  # AERMANI_SIM_RESTORE_SEED
    assert np.allclose(fresh.vehicle.true_position_enu(), core.vehicle.true_position_enu())
    assert fresh.vehicle.wind.rng.bit_generator.state != back.vehicle.wind.rng.bit_generator.state
    for bad in ('{"kind": "sim_state", "state": "{}"}', "not json", ""):
        path.write_text(bad)
        with pytest.raises(ConfigError, match="AERMANI_SIM_RESTORE"):
            restored(settings, params)
    with pytest.raises(ConfigError, match="AERMANI_SIM_RESTORE"):
        restored(SimSettings(restore=str(tmp_path / "missing.json")), params)


def test_a_reseeded_fork_starts_from_the_same_world_and_flies_with_other_noise() -> None:
    core, clock = holding_the_cup("multirotor")
    doc = json.loads(json.dumps(core.capture()))
    same = SimCore.from_capture(doc, hold=False)
    a1, a2 = SimCore.from_capture(doc, hold=False), SimCore.from_capture(doc, hold=False)
    other = SimCore.from_capture(doc, hold=False)
    assert reseed(a1, 1) == reseed(a2, 1) == reseed(other, 2) == ["_thrust_rng", "estimator.bias.rng", "wind.rng"]
    assert np.array_equal(a1.world.data.qpos, core.world.data.qpos)  # the world is the recorded one
    runs = {name: fly_on(c, clock.now) for name, c in
            (("original", core), ("same", same), ("a1", a1), ("a2", a2), ("other", other))}

    def apart(x: str, y: str) -> float:
        return max(float(np.abs(p - q).max()) for p, q in zip(runs[x], runs[y], strict=True))

    assert apart("original", "same") < 1e-6 and apart("a1", "a2") < 1e-6  # a seed is a realisation, repeatable
    assert apart("original", "a1") > 1e-3 and apart("a1", "other") > 1e-3  # another seed, other draws
    assert a1.judge(JudgeRequest(op="held")).ok and other.judge(JudgeRequest(op="held")).ok
