"""Replay of a recorded task into a running gateway: its SSE stream shows the task's steps, in order."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from services.recorder.settings import RecorderSettings
from services.recorder.writer import RecordWriter
from shared.bus import encode
from shared.messages import TaskState, TaskStatus
from tests.helpers import free_port, run_stack
from tests.recorder.samples import K, step_message

pytestmark = pytest.mark.integration

TOKEN = "replay-test-token-5d1e"


def write_task_log(tmp_path: Path, n_steps: int) -> Path:
    w = RecordWriter(RecorderSettings(out_dir=str(tmp_path / "rec")))
    w.start()
    t = time.time_ns()

    def put(key: str, obj, dt_ms: int) -> None:
        data, enc = encode(obj)
        w.submit(key, data, str(enc), t + dt_ms * 1_000_000)

    # Steps 200 ms apart, like a real task: the gateway consumes steps and statuses on separate queues, so
    # samples a few ms apart can be stored out of order there (reported to the gateway's owner).
    status = {"task_id": "task-replayed", "command": "pick up the red cup", "started_ns": t}
    put(K.task_status, TaskStatus(state=TaskState.RUNNING, **status), 0)
    for i in range(1, n_steps + 1):
        put(K.reasoning_step, step_message("task-replayed", i, "forward"), 200 * i)
    put(K.task_status, TaskStatus(state=TaskState.SUCCEEDED, steps=n_steps, ended_ns=t + 10**9, **status),
        200 * n_steps + 200)
    w.stop()
    [path] = (tmp_path / "rec").glob("*.mcap")
    return path


def test_replay_shows_the_steps_in_the_gateway_sse(tmp_path: Path) -> None:
    log = write_task_log(tmp_path, 4)
    port = free_port()
    env = {"AERMANI_GATEWAY_PORT": str(port), "AERMANI_GATEWAY_TOKEN": TOKEN,
           "AERMANI_GATEWAY_DB_PATH": str(tmp_path / "gw.sqlite3")}
    url = f"http://127.0.0.1:{port}/api/v1"
    with run_stack(["gateway"], tmp_path, env=env) as stack:
        deadline = time.monotonic() + 90
        while True:
            try:
                if httpx.get(f"{url}/live", timeout=5).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, "gateway not up"
            time.sleep(0.2)
        time.sleep(0.5)  # the gateway's subscriptions reach the router
        res = subprocess.run([sys.executable, "-m", "aermani.cli", "replay", str(log), "--speed", "1",
                              "--connect", stack.endpoint], capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr
        assert "replayed 6 samples" in res.stdout
        headers = {"Authorization": f"Bearer {TOKEN}"}
        deadline = time.monotonic() + 60
        while httpx.get(f"{url}/tasks/task-replayed", headers=headers, timeout=10).status_code == 404:
            assert time.monotonic() < deadline, "the gateway never saw the replayed task"
            time.sleep(0.2)
        events: list[tuple[str, dict]] = []
        kind = ""
        with httpx.stream("GET", f"{url}/tasks/task-replayed/events", headers=headers, timeout=60) as r:
            assert r.status_code == 200, r.read()
            for line in r.iter_lines():  # the stream ends after the terminal task_status
                if line.startswith("event:"):
                    kind = line.split(":", 1)[1].strip()
                elif line.startswith("data:"):
                    events.append((kind, json.loads(line.split(":", 1)[1])))
    assert [d["step"] for k, d in events if k == "step"] == [1, 2, 3, 4]
    assert events[-1][0] == "task_status" and events[-1][1]["state"] == "succeeded"
