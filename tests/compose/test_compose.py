"""The compose deployment for real: build the image (no container registry needed: the base image is a build
argument), bring up the `ground`, `drone` and `sim` profiles of docker-compose.yml with podman-compose, run one
task through the gateway's HTTP API until it succeeds, take everything down with the stop grace, then read the
recorder's volume (an indexed MCAP with the task) and the gateway's store (the task, succeeded).

Run with `scripts/compose_test.sh` (installs podman, runc, podman-compose, builds a debootstrap base image) or
`pytest -m compose tests/compose` on a machine already set up. Environment:
AERMANI_COMPOSE_BASE (base image, default python:3.11-slim-bookworm from Docker Hub),
AERMANI_PODMAN_COMPOSE (the podman-compose executable, default from PATH).
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from aermani.launcher import free_port

ROOT = Path(__file__).resolve().parents[2]
IMAGE = "localhost/aermani:latest"  # what `image: aermani:latest` in the compose file resolves to
CAMERA_IMAGE = "localhost/aermani-camera:latest"  # the camera service's (Dockerfile target `camera`)
PROFILES = ("ground", "drone", "sim")
TERMINAL = {"succeeded", "failed", "aborted", "timeout"}
# pip settings passed into the build; list-valued ones are space-separated in pip's config.
PIP_KEYS = {"index-url": False, "extra-index-url": True, "find-links": True, "trusted-host": True,
            "cert": False, "constraint": False}

pytestmark = [pytest.mark.compose, pytest.mark.slow, pytest.mark.timeout(3600)]


def _run(cmd: list[str], timeout: float = 120, **kw: Any) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False, **kw)


def _base_image() -> str:
    """The build's base image, present locally (pulled if a registry is reachable)."""
    base = os.environ.get("AERMANI_COMPOSE_BASE", "python:3.11-slim-bookworm")
    if _run(["podman", "image", "exists", base]).returncode != 0:
        pull = _run(["podman", "pull", base], timeout=600)
        why = pull.stderr.strip()[-300:]
        assert pull.returncode == 0, (f"base image {base} is not here and cannot be pulled ({why}): "
                                      "scripts/compose_test.sh builds one with debootstrap")
    return base


def _podman_blocker(image: str) -> str | None:
    """Why podman cannot run a container here (None when it can)."""
    probe = _run(["podman", "run", "--rm", "--network", "none", image, "true"])
    if probe.returncode != 0:
        return ("podman cannot run containers on this machine: "
                f"{(probe.stderr or probe.stdout).strip()[-400:]} (scripts/compose_test.sh configures runc and "
                "default_ulimits = [] through CONTAINERS_CONF)")
    return None


def _pip_settings() -> dict[str, list[str]]:
    """The host's effective pip index settings (`pip config list`: environment, global and user files)."""
    out = _run([sys.executable, "-m", "pip", "config", "list"]).stdout
    found: dict[str, list[str]] = {}
    for line in out.splitlines():
        name, _, raw = line.partition("=")
        key = name.rsplit(".", 1)[-1]
        if key not in PIP_KEYS:
            continue
        values = raw.strip().strip("'\"").split()
        found.setdefault(key, [])
        if PIP_KEYS[key]:
            found[key] += [v for v in values if v not in found[key]]
        elif not found[key]:  # `pip config list` lists the environment first: it wins, as in pip
            found[key] = values
    return found


def _local_path(key: str, value: str) -> Path | None:
    """The local path a pip setting names (None for a URL); a file:// index is mounted from its parent,
    where its `simple/` pages link to the files."""
    if not value.startswith(("file://", "/")):
        return None
    path = Path(value.removeprefix("file://"))
    if key.endswith("index-url"):
        path = path.parent
    return path if path.exists() else None


def _build_args(base: str) -> list[str]:
    """Build arguments: the base image, pip's settings, and read-only mounts for the local paths they name."""
    args = ["--network", "host", "--build-arg", f"BASE={base}"]
    mounts: set[Path] = set()
    for key, values in _pip_settings().items():
        if values:
            args += ["--build-arg", f"PIP_{key.upper().replace('-', '_')}={' '.join(values)}"]
        mounts |= {p for p in (_local_path(key, v) for v in values) if p is not None}
    for path in sorted(mounts):
        args += ["--volume", f"{path}:{path}:ro"]
    return args


def _build_image(base: str, log: Path) -> float:
    """Both images compose runs: every service's, and the camera service's with the RealSense SDK (the same
    layers plus one)."""
    start = time.monotonic()
    with log.open("w") as out:
        for target, tag in ((None, IMAGE), ("camera", CAMERA_IMAGE)):
            extra = ["--target", target] if target else []
            proc = subprocess.run(["podman", "build", *_build_args(base), *extra, "-t", tag, str(ROOT)], stdout=out,
                                  stderr=subprocess.STDOUT, timeout=2400, check=False)
            assert proc.returncode == 0, f"image build of {tag} failed:\n" + log.read_text()[-3000:]
    return time.monotonic() - start


class Stack:
    """One compose project (own name, volumes and host ports) driven through podman-compose."""

    def __init__(self, compose: str, work: Path) -> None:
        self.project = f"aermani-ct-{secrets.token_hex(3)}"
        self.token = secrets.token_hex(16)
        self.http_port = free_port()
        certs = work / "certs"
        cli = _run([sys.executable, "-m", "aermani.cli", "certs", "init", "--out", str(certs)], cwd=ROOT)
        assert cli.returncode == 0, cli.stderr
        for f in certs.iterdir():  # containers run as uid 1000 (README: `chown 1000` the keys)
            if os.geteuid() == 0:
                os.chown(f, 1000, 1000)
            else:
                f.chmod(0o644)
        self.env = {**os.environ, "AERMANI_CERTS": str(certs), "AERMANI_GATEWAY_TOKEN": self.token,
                    "AERMANI_GATEWAY_PUBLISH": f"127.0.0.1:{self.http_port}",
                    "AERMANI_ROUTER_PUBLISH": f"127.0.0.1:{free_port()}",
                    "AERMANI_MAVLINK_PUBLISH": f"127.0.0.1:{free_port()}"}
        self.cmd = [compose, "-f", str(ROOT / "docker-compose.yml"), "-p", self.project]
        for p in PROFILES:
            self.cmd += ["--profile", p]

    def compose(self, *args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
        proc = _run([*self.cmd, *args], timeout=timeout, env=self.env, cwd=ROOT)
        assert proc.returncode == 0, f"podman-compose {' '.join(args)}:\n{proc.stdout[-2000:]}{proc.stderr[-2000:]}"
        return proc

    def container(self, service: str) -> str:
        return f"{self.project}_{service}_1"

    def volume(self, name: str) -> Path:
        out = _run(["podman", "volume", "inspect", f"{self.project}_{name}", "--format", "{{.Mountpoint}}"])
        assert out.returncode == 0, out.stderr
        return Path(out.stdout.strip())

    def logs(self) -> str:
        names = _run(["podman", "ps", "-a", "--filter", f"label=io.podman.compose.project={self.project}",
                      "--format", "{{.Names}}"]).stdout.split()
        tails = {n: _run(["podman", "logs", "--tail", "15", n]) for n in names}
        return "\n".join(f"== {n}\n{(p.stdout + p.stderr)[-1500:]}" for n, p in tails.items())

    def remove(self) -> None:
        _run([*self.cmd, "down", "-t", "0"], timeout=300, env=self.env, cwd=ROOT)
        for vol in ("gateway-data", "recordings"):
            _run(["podman", "volume", "rm", "-f", f"{self.project}_{vol}"])


def _wait_ready(client: httpx.Client, deadline_s: float = 240) -> None:
    """Until the gateway sees the vehicle with its reasoner, executor and simulator alive and the link up."""
    deadline, last = time.monotonic() + deadline_s, None
    needed = {"reasoner", "executor", "sim", "perception", "autopilot_bridge", "recorder"}
    while time.monotonic() < deadline:
        try:
            last = client.get("/api/v1/health").json()
            vehicles = last.get("vehicles", [])
            if vehicles and needed <= {s for s, ok in vehicles[0]["services"].items() if ok} \
                    and vehicles[0]["link_ok"]:
                return
        except (httpx.HTTPError, ValueError, KeyError):
            pass
        time.sleep(2)
    pytest.fail(f"stack not ready in {deadline_s} s; last health: {last}")


def _scenario(stack: Stack, deadline_s: float = 120) -> dict[str, Any]:
    """The simulator's scenario, from its own log line `sim ready: scenario {...}`."""
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline:
        log = _run(["podman", "logs", stack.container("sim")])
        text = log.stdout + log.stderr
        marker = text.find("sim ready: scenario ")
        if marker >= 0:
            start = text.index("{", marker)
            return json.JSONDecoder().raw_decode(text[start:])[0]
        time.sleep(2)
    pytest.fail("the simulator never logged its scenario")


def _run_task(client: httpx.Client, command: str, deadline_s: float = 600) -> dict[str, Any]:
    posted = client.post("/api/v1/tasks", json={"command": command})
    assert posted.status_code == 202, posted.text
    task_id = posted.json()["task_id"]
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline:
        task = client.get(f"/api/v1/tasks/{task_id}").json()
        if task["state"] in TERMINAL:
            return task
        time.sleep(3)
    pytest.fail(f"task {task_id} did not end in {deadline_s} s")


def _check_recording(logs: Path, task_id: str) -> None:
    """The recorder's volume: owned by uid 1000, an MCAP with its summary written (a clean stop) and the task's
    final status in it."""
    from mcap.reader import make_reader

    assert logs.stat().st_uid == 1000
    files = sorted(logs.glob("*.mcap"))
    assert files, f"no MCAP in {logs}"
    states = []
    for f in files:
        with f.open("rb") as fh:
            reader = make_reader(fh)
            assert reader.get_summary() is not None, f"{f.name} has no summary (recorder killed before its drain)"
            for _, channel, message in reader.iter_messages():
                if channel.topic.endswith("/reasoner/task_status") and task_id.encode() in message.data:
                    states.append(message.data)
    assert any(b"succeeded" in s for s in states), f"no succeeded task_status for {task_id} in {files}"


def _check_store(data: Path, task_id: str) -> None:
    with sqlite3.connect(f"file:{data / 'gateway.sqlite3'}?mode=ro", uri=True) as db:
        row = db.execute("SELECT state FROM tasks WHERE task_id = ?", (task_id,)).fetchone()
    assert row == ("succeeded",)


def test_compose_profiles_run_a_task_over_http(tmp_path: Path) -> None:
    if shutil.which("podman") is None:
        pytest.skip("podman is not installed, so no container can run here (scripts/compose_test.sh installs it)")
    base = _base_image()
    blocker = _podman_blocker(base)
    if blocker:
        pytest.skip(blocker)
    compose = os.environ.get("AERMANI_PODMAN_COMPOSE") or shutil.which("podman-compose")
    assert compose, "podman-compose not found: run scripts/compose_test.sh or `pip install podman-compose`"
    build_s = _build_image(base, tmp_path / "build.log")
    stack = Stack(compose, tmp_path)
    t0 = time.monotonic()
    try:
        stack.compose("up", "-d", "--no-build")
        with httpx.Client(base_url=f"http://127.0.0.1:{stack.http_port}", timeout=30,
                          headers={"Authorization": f"Bearer {stack.token}"}) as client:
            _wait_ready(client)
            scenario = _scenario(stack)
            task = _run_task(client, f"Pick up the {scenario['target_object']} and place it on the "
                                     f"{scenario['destination']}.")
        assert task["state"] == "succeeded", f"{task['state']}: {task.get('message')}\n{stack.logs()}"
        t_task = time.monotonic()
        stack.compose("down", timeout=600)  # each service's stop_grace_period applies
        t_down = time.monotonic()
        _check_recording(stack.volume("recordings"), task["task_id"])
        _check_store(stack.volume("gateway-data"), task["task_id"])
        print(f"compose test: image build {build_s:.0f} s, up to task end {t_task - t0:.0f} s, "
              f"down {t_down - t_task:.0f} s; task {task['task_id']} succeeded")
    except AssertionError:
        print(stack.logs())
        raise
    finally:
        stack.remove()
