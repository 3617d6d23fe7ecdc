"""Host tools reach a secure deployment's router: `aermani --client-certs DIR ... --connect tls/...` presents a
client certificate over mutual TLS (compose's ground router publishes only such a listener). A real secure
stack (the launcher's ground and drone routers from shared/routers/, the simulator as a process behind the
drone router) and the real `aermani` command in a subprocess."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from aermani.launcher import Stack, free_udp_port
from shared.security import init_certs

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.integration


def _aermani(*args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("AERMANI_ZENOH_")}
    env.update(PYTHONPATH=str(ROOT), COLUMNS="200", NO_COLOR="1")
    return subprocess.run([sys.executable, "-m", "aermani.cli", *args], env=env, capture_output=True, text=True,
                          timeout=120, cwd=ROOT)


def test_aermani_commands_take_a_client_certificate(tmp_path: Path) -> None:
    certs = tmp_path / "certs"
    init_certs(certs)
    env = {"AERMANI_SIM_API_PORT": str(free_udp_port()), "AERMANI_SIM_API_LOCAL_PORT": str(free_udp_port()),
           "AERMANI_SIM_GCS_PORT": str(free_udp_port()), "AERMANI_SIM_GCS_LOCAL_PORT": str(free_udp_port()),
           "AERMANI_SIM_FPS": "2"}
    stack = Stack(["sim"], env=env, log_dir=tmp_path / "logs", supervise=False, secure=certs)
    tls = stack.tls_listen[0]
    with stack:
        ok = _aermani("--client-certs", str(certs), "health", "--connect", tls, "--timeout", "4")
        ground = _aermani("--client-certs", str(certs), "--identity", "ground", "health", "--connect", tls,
                          "--timeout", "4")
        bare = _aermani("health", "--connect", tls, "--timeout", "2")
        wrong = _aermani("--client-certs", str(tmp_path / "nowhere"), "health", "--connect", tls)
    assert ok.returncode == 0 and "sim" in ok.stdout, ok.stdout[-1500:] + ok.stderr[-1500:]
    assert ground.returncode == 0 and "sim" in ground.stdout, ground.stderr[-1500:]
    assert bare.returncode != 0 and "needs a client certificate" in bare.stdout + bare.stderr, bare.stderr[-1500:]
    assert "--client-certs" in bare.stdout + bare.stderr
    assert wrong.returncode != 0 and "missing certificate files" in wrong.stdout + wrong.stderr, wrong.stderr[-800:]
