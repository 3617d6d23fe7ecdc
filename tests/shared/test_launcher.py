"""`aermani up` / `aermani health` as a user runs them: real processes, signals, liveliness."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from aermani.launcher import free_port
from shared.keys import alive_pattern, parse_alive_key
from tests.helpers import BusCollector

pytestmark = pytest.mark.integration
AERMANI = [sys.executable, "-m", "aermani.cli"]


def _health(port: int) -> str:
    out = subprocess.run([*AERMANI, "health", "--connect", f"tcp/127.0.0.1:{port}"], capture_output=True, text=True,
                         timeout=60)
    return out.stdout


def _children(pid: int) -> set[int]:
    """Live child processes of `pid`, from /proc (no procps needed)."""
    kids = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            kids.add(int(stat.parent.name))
    return kids


def _wait(pred, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        val = pred()
        if val:
            return val
        time.sleep(0.3)
    raise AssertionError(f"timed out waiting for {what}")


def _service_of(pid: int) -> str:
    """The service a child runs (`python -m services.<name>`), from its command line."""
    argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    return argv[argv.index(b"-m") + 1].decode().removeprefix("services.")


def _changes(events: list[tuple[str, bool]]) -> list[tuple[str, bool]]:
    """Liveliness events as (service, appeared)."""
    return [(parse_alive_key(key)[1], appeared) for key, appeared in events]


def _alive_pids(pids: set[int]) -> set[int]:
    alive = set()
    for p in pids:
        try:
            os.kill(p, 0)
            alive.add(p)
        except ProcessLookupError:
            pass
    return alive


def test_up_health_restart_and_clean_stop(tmp_path: Path):
    port = free_port()
    services = "reasoner,recorder"
    env = {**os.environ, "AERMANI_RECORDER_OUT_DIR": str(tmp_path / "rec")}
    up = subprocess.Popen([*AERMANI, "up", "--services", services, "--port", str(port), "--log-dir",
                           str(tmp_path / "logs")], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          env=env)
    try:
        table = _wait(lambda: (h := _health(port)).count("alive") >= 2 and h, 90, "both services alive")
        assert "reasoner" in table and "recorder" in table
        children = _wait(lambda: _children(up.pid) if len(_children(up.pid)) >= 2 else None, 10, "children")
        # SIGKILL one service: the launcher sees it die and restarts it. Its liveliness token goes and comes
        # back within a second or two, less than one `aermani health` call takes (3-5 s of interpreter start
        # on a busy machine), so the gap is seen on a liveliness watch, which cannot miss it, not by polling.
        victim = next(iter(children))
        name = _service_of(victim)
        # The watch reports the tokens alive now first: once both are in, it is declared at the router.
        watch = BusCollector(f"tcp/127.0.0.1:{port}", lambda bus: bus.watch_liveliness(alive_pattern()).get,
                             ready=lambda items: len(items) >= 2)
        with watch:
            os.kill(victim, signal.SIGKILL)
            gone = (name, False)
            watch.wait_for(lambda ev: gone in _changes(ev), 30, "killed service to disappear")
            watch.wait_for(lambda ev: (name, True) in _changes(ev)[_changes(ev).index(gone):], 90,
                           "killed service back")
        _wait(lambda: _health(port).count("alive") >= 2, 90, "killed service restarted and alive")
        new_children = _children(up.pid)
        assert victim not in new_children and len(new_children) == 2
        all_pids = children | new_children
        # Ctrl-C: everything stops, nothing is left behind.
        up.send_signal(signal.SIGINT)
        out, _ = up.communicate(timeout=60)
        assert up.returncode == 0, out
        assert "restarting" in out and "all services stopped" in out
        assert _alive_pids(all_pids) == set()
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()


def test_health_reports_unreachable_router():
    out = subprocess.run([*AERMANI, "health", "--connect", f"tcp/127.0.0.1:{free_port()}", "--timeout", "1"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode != 0


def _wait_event(stack, text: str, timeout: float) -> str:
    return _wait(lambda: next((e for e in stack.events if text in e), None), timeout, f"launcher event {text!r}")


def test_a_hung_service_is_noticed_by_its_heartbeat_and_restarted(tmp_path: Path):
    from aermani.launcher import Stack

    with Stack(["reasoner"], log_dir=tmp_path / "logs", hung_after_s=3.0) as stack:
        p = stack.find("reasoner")
        first = p.proc.pid
        _wait(lambda: stack._beats.get((p.vehicle_id, "reasoner")), 30, "a heartbeat")
        os.kill(first, signal.SIGSTOP)  # alive to the kernel and (for Zenoh's lease) still connected: hung
        stopped = time.monotonic()
        hung = _wait_event(stack, "is hung", 30)
        noticed = time.monotonic() - stopped
        assert f"pid {first}" in hung
        _wait_event(stack, "restarted", 30)
        stack.wait_alive(timeout=60)
        assert p.proc.pid != first and p.running
        print(f"hung service noticed after {noticed:.1f} s (heartbeat every 0.5 s, limit 3 s)")


def test_a_failed_restart_does_not_end_supervision(tmp_path: Path):
    from aermani.launcher import Stack

    logs = tmp_path / "logs"
    with Stack(["reasoner"], log_dir=logs) as stack:
        p = stack.find("reasoner")
        first = p.proc.pid
        # The restart cannot open its log: the log directory is now a file (a real OS failure of Popen's set-up).
        moved = tmp_path / "logs.moved"
        logs.rename(moved)
        logs.write_text("not a directory")
        os.kill(first, signal.SIGKILL)
        _wait_event(stack, "failed", 30)
        assert stack._thread is not None and stack._thread.is_alive()
        logs.unlink()
        moved.rename(logs)
        _wait_event(stack, "restarted", 60)
        stack.wait_alive(timeout=60)
        assert p.running and p.proc.pid != first


def test_a_router_restart_is_reconnected_to_and_kills_nobody(tmp_path: Path):
    """The router closes for longer than the hung limit and reopens on its endpoint: the service (a Zenoh
    client) reconnects by itself, its token and heartbeat come back, and the supervisor, which could not hear
    it meanwhile, did not take it for hung."""
    from aermani.launcher import Stack

    with Stack(["reasoner"], log_dir=tmp_path / "logs", hung_after_s=2.0) as stack:
        p = stack.find("reasoner")
        first = p.proc.pid
        _wait(lambda: stack._beats.get((p.vehicle_id, "reasoner")), 30, "a heartbeat")
        stack.restart_router(down_s=3.0)
        stack.wait_alive(timeout=60)
        _wait(lambda: stack._beats.get((p.vehicle_id, "reasoner")), 30, "a heartbeat through the new router")
        assert p.proc.pid == first and p.running and p.restarts == 0, stack.events
        assert not any("hung" in e for e in stack.events), stack.events
