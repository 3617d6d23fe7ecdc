"""A crashed service waits before it exits when AERMANI_CRASH_BACKOFF_S is set (compose sets it: podman
restarts a container at once, 39 times in 28 s for one bad setting): real service processes with a bad
setting, each run as a restarted container would be, with the crash count in the temporary directory."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

from shared.service import CRASH_RESET_S, crash_delay

ROOT = Path(__file__).resolve().parents[2]


def _crash_once(tmp: Path, backoff: str | None) -> tuple[float, subprocess.CompletedProcess[str]]:
    env = {**os.environ, "TMPDIR": str(tmp), "AERMANI_CAMERA_WIDTH": "1", "PYTHONPATH": str(ROOT)}
    env.pop("AERMANI_CRASH_BACKOFF_S", None)
    if backoff is not None:
        env["AERMANI_CRASH_BACKOFF_S"] = backoff
    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-m", "services.camera"], env=env, capture_output=True, text=True,
                         timeout=120, cwd=ROOT)
    return time.monotonic() - t0, out


def test_a_misconfigured_service_backs_off_between_restarts(tmp_path: Path) -> None:
    waits = []
    for _ in range(4):
        took, out = _crash_once(tmp_path, "2")
        assert out.returncode != 0 and "width" in out.stderr, out.stderr[-1500:]
        m = re.search(r"camera failed \(ValidationError: .*\); exiting in ([0-9.]+) s \(crash (\d+) in a row",
                      out.stderr)
        assert m, out.stderr[-1500:]
        waits.append((float(m.group(1)), int(m.group(2))))
        assert took >= float(m.group(1))
    assert waits == [(0.5, 1), (1.0, 2), (2.0, 3), (2.0, 4)]


def test_without_the_setting_a_crash_exits_at_once(tmp_path: Path) -> None:
    _, out = _crash_once(tmp_path, None)
    assert out.returncode != 0 and "exiting in" not in out.stderr
    assert not list(tmp_path.glob("aermani-crashes-*"))


def test_a_long_healthy_run_starts_the_count_over(tmp_path: Path) -> None:
    assert crash_delay("x", 30, 1.0, tmp_path) == (0.5, 1)
    assert crash_delay("x", 30, 1.0, tmp_path) == (1.0, 2)
    assert crash_delay("x", 30, CRASH_RESET_S, tmp_path) == (0.5, 1)
    assert crash_delay("y", 30, 1.0, tmp_path) == (0.5, 1)  # per service
    (tmp_path / "aermani-crashes-x").write_text("garbage")
    assert crash_delay("x", 30, 1.0, tmp_path) == (0.5, 1)
