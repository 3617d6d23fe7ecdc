"""The gateway as a real process: unsafe binds refused, history kept across a SIGTERM restart, no token in
its log."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from tests.gateway.conftest import TOKEN, read_sse, wait_task
from tests.gateway.fakes import Harness
from tests.helpers import free_port

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]


def gateway_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("AERMANI_")}
    return {**env, "PYTHONUNBUFFERED": "1", **extra}


def test_refuses_non_loopback_bind_without_token(tmp_path: Path) -> None:
    env = gateway_env(AERMANI_GATEWAY_HOST="0.0.0.0", AERMANI_GATEWAY_PORT=str(free_port()),
                      AERMANI_GATEWAY_DB_PATH=str(tmp_path / "db.sqlite3"),
                      AERMANI_ZENOH_CONNECT=f"tcp/127.0.0.1:{free_port()}")
    p = subprocess.run([sys.executable, "-m", "services.gateway"], env=env, cwd=ROOT, capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    assert "refusing to serve on 0.0.0.0" in p.stderr and "AERMANI_GATEWAY_TOKEN" in p.stderr
    assert "Traceback" not in p.stderr


class GatewayProcess:
    def __init__(self, tmp: Path, endpoint: str) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}/api/v1"
        self.log = tmp / "gateway.log"
        self.env = gateway_env(AERMANI_GATEWAY_PORT=str(self.port), AERMANI_GATEWAY_TOKEN=TOKEN,
                               AERMANI_GATEWAY_DB_PATH=str(tmp / "gateway.sqlite3"), AERMANI_ZENOH_CONNECT=endpoint,
                               AERMANI_LOG_LEVEL="DEBUG")
        self.proc: subprocess.Popen | None = None

    def start(self, timeout: float = 90.0) -> None:
        with open(self.log, "ab") as logf:
            self.proc = subprocess.Popen([sys.executable, "-m", "services.gateway"], env=self.env, cwd=ROOT,
                                         stdout=logf, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout
        while True:
            assert self.proc.poll() is None, self.log.read_text()
            try:
                if self.ready():
                    return
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                raise TimeoutError(f"gateway not up:\n{self.log.read_text()}")
            time.sleep(0.2)

    def ready(self) -> bool:
        """Up: the API answers and a reasoner is alive behind it."""
        h = httpx.get(f"{self.url}/health", timeout=5, headers={"Authorization": f"Bearer {TOKEN}"}).json()
        return any(v["services"].get("reasoner") for v in h["vehicles"])

    def stop(self, sig: int = signal.SIGTERM) -> int:
        assert self.proc is not None
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            raise


def test_restart_mid_task_keeps_task_and_steps(tmp_path: Path) -> None:
    h = Harness(tmp_path, step_delay_s=0.25).start()
    gw = GatewayProcess(tmp_path, h.endpoint)
    try:
        gw.start()
        with httpx.Client(base_url=gw.url, timeout=30, headers={"Authorization": f"Bearer {TOKEN}"}) as c:
            tid = c.post("/tasks", json={"command": "inspect the shelf until abort"}).json()["task_id"]
            before = read_sse(c, f"/tasks/{tid}/events", stop=6)
            # Reads need the token too (commands, reasoning and position are sensitive).
            assert c.get("/tasks", params={"limit": 1}, headers={"Authorization": "Bearer wrong"}).status_code == 401
            assert c.post("/abort", headers={"Authorization": "Bearer wrong-token"}).status_code == 401
        assert gw.stop() == 0, gw.log.read_text()

        gw.start()
        with httpx.Client(base_url=gw.url, timeout=30, headers={"Authorization": f"Bearer {TOKEN}"}) as c:
            task = c.get(f"/tasks/{tid}").json()
            assert task["state"] == "running" and task["command"] == "inspect the shelf until abort"
            steps_before = [e["data"]["step"] for e in before if e["event"] == "step"]
            assert [s["step"]["step"] for s in task["reasoning_steps"]][: len(steps_before)] == steps_before
            # The stream resumes where the client left off and keeps going live after the restart.
            resumed = read_sse(c, f"/tasks/{tid}/events", last_event_id=int(before[-1]["id"]), stop=4)
            assert int(resumed[0]["id"]) > int(before[-1]["id"])
            assert c.post(f"/tasks/{tid}/abort").status_code == 202
            assert wait_task(c, tid, {"aborted"})["metrics"]["steps"] > len(steps_before)
        assert gw.stop() == 0
    finally:
        if gw.proc is not None and gw.proc.poll() is None:
            gw.stop(signal.SIGKILL)
        h.stop()
    log = gw.log.read_text()
    assert "gateway on http://127.0.0.1" in log and "POST /api/v1/tasks" in log  # the log is really there
    assert TOKEN not in log
