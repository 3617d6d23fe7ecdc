"""Replay onto a live bus (the real `aermani replay` process, a real router): recorded aborts and commands
stay in the log unless asked, and --vehicle/--remap move the flight to another vehicle id."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from aermani.launcher import free_port, open_router
from services.recorder.replay import is_control_key, remap_sample
from services.recorder.settings import RecorderSettings
from services.recorder.writer import RecordWriter
from shared.bus import Bus, encode
from shared.keys import Keys
from shared.messages import Abort, GotoCommand, Vec3, VehicleState
from tests.helpers import arun
from tests.recorder.samples import step_message

K = Keys("am1")


def write_log(tmp_path: Path) -> Path:
    w = RecordWriter(RecorderSettings(out_dir=str(tmp_path / "rec")))
    w.start()
    t = time.time_ns()
    items = [(K.autopilot_state, VehicleState(vehicle_id="am1", position=Vec3(z=1.5), armed=True)),
             (K.reasoning_step, step_message("task-r", 1, "forward")),
             (K.abort, Abort(reason="recorded abort")),
             # A sample on a command key (a log could hold one, e.g. written by another tool).
             (K.autopilot_command, GotoCommand(position=Vec3(x=1.0, z=1.0), yaw=0.0)),
             (K.reasoning_step, step_message("task-r", 2, "forward"))]
    for i, (key, obj) in enumerate(items):
        data, enc = encode(obj)
        w.submit(key, data, str(enc), t + i * 10_000_000)
    w.stop()
    [path] = (tmp_path / "rec").glob("*.mcap")
    return path


def replay_and_listen(log: Path, *args: str, alive: tuple[str, ...] = (),
                      code: int = 0) -> tuple[str, list[tuple[str, bytes]]]:
    """Run `aermani replay LOG ARGS` onto a router and collect what it published; `alive` tokens are declared
    first (services that answer for a vehicle), `code` is the exit status expected (its output: stdout+stderr)."""
    port = free_port()
    router = open_router(port)
    endpoint = f"tcp/127.0.0.1:{port}"

    async def main() -> tuple[str, list[tuple[str, bytes]]]:
        bus = await Bus.open(connect=[endpoint])
        try:
            sub = bus.subscribe("aermani/**", maxsize=1000)
            for token in alive:
                bus.declare_token(token)
            await asyncio.sleep(0.5)
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "aermani.cli", "replay", str(log), "--speed", "0", "--connect", endpoint,
                *args, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            out, errout = await asyncio.wait_for(proc.communicate(), 120)
            assert proc.returncode == code, errout.decode()
            got = []
            while True:
                try:
                    rec = await sub.recv_sample(timeout=1.5)
                except TimeoutError:
                    break
                got.append((rec.key, rec.payload))
            return out.decode() + errout.decode(), got
        finally:
            await bus.close()

    try:
        return arun(main())
    finally:
        router.close()


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    return write_log(tmp_path_factory.mktemp("replay"))


def test_control_keys_are_left_out_by_default(log) -> None:
    out, got = replay_and_listen(log)
    keys = [k for k, _ in got]
    assert keys == [K.autopilot_state, K.reasoning_step, K.reasoning_step], keys
    assert "left out 2 control samples" in out and "--include-control" in out


def test_include_control_republishes_them(log) -> None:
    _, got = replay_and_listen(log, "--include-control")
    keys = [k for k, _ in got]
    assert K.abort in keys and K.autopilot_command in keys and len(keys) == 5


def test_vehicle_remap_moves_keys_and_payload(log) -> None:
    _, got = replay_and_listen(log, "--vehicle", "replay1")
    r = Keys("replay1")
    assert [k for k, _ in got] == [r.autopilot_state, r.reasoning_step, r.reasoning_step]
    state = VehicleState.model_validate_json(got[0][1])
    assert state.vehicle_id == "replay1" and state.position.z == 1.5
    _, got = replay_and_listen(log, "--remap", "am1=am7")
    assert {k.split("/")[2] for k, _ in got} == {"am7"}


def test_a_live_vehicle_is_refused_unless_asked_and_a_remap_replays_beside_it(log) -> None:
    """The log is am1's; am1's autopilot bridge answers now: nothing is published onto it (its recorded state
    would pass for the vehicle's own), replaying under another id works, --onto-live does it on purpose. A
    ground service alone (the gateway under am1's prefix) leaves the id free."""
    bridge = f"{Keys('am1').key('alive')}/autopilot_bridge"
    out, got = replay_and_listen(log, alive=(bridge,), code=2)
    assert got == [] and "am1 is live" in out and "--onto-live" in out, out
    _, got = replay_and_listen(log, "--vehicle", "replay1", alive=(bridge,))
    assert {k.split("/")[2] for k, _ in got} == {"replay1"}
    _, got = replay_and_listen(log, "--onto-live", alive=(bridge,))
    assert [k for k, _ in got] == [K.autopilot_state, K.reasoning_step, K.reasoning_step]
    _, got = replay_and_listen(log, alive=(f"{Keys('am1').key('alive')}/gateway",))
    assert len(got) == 3


def test_bad_remap_is_refused_before_publishing(log) -> None:
    res = subprocess.run([sys.executable, "-m", "aermani.cli", "replay", str(log), "--vehicle", "a/b",
                          "--connect", "tcp/127.0.0.1:1"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "invalid vehicle id" in res.stderr


def test_control_key_rules() -> None:
    assert is_control_key(K.abort) and is_control_key(K.start_task) and is_control_key(K.autopilot_command)
    assert not is_control_key(K.abort_ack) and not is_control_key(K.autopilot_state)
    key, payload = remap_sample(K.task_status, json.dumps({"vehicle_id": "am1", "x": 1}).encode(),
                                "application/json;aermani.TaskStatus", {"am1": "am2"})
    assert key == Keys("am2").task_status and json.loads(payload)["vehicle_id"] == "am2"
