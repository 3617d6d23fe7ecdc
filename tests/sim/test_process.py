"""`python -m services.sim` answers MAVLink before (and without) any Zenoh router."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mav

from aermani.launcher import free_port, free_udp_port
from tests.sim.test_mavlink import Client

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[2]


def test_mavlink_up_while_router_unreachable(tmp_path):
    api = free_udp_port()
    env = {**os.environ, "AERMANI_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}",  # nobody listens there
           "AERMANI_SIM_API_PORT": str(api), "AERMANI_SIM_API_LOCAL_PORT": str(free_udp_port()),
           "AERMANI_SIM_GCS_PORT": str(free_udp_port()), "AERMANI_SIM_GCS_LOCAL_PORT": str(free_udp_port()),
           "AERMANI_SIM_SEED": "3"}
    log = (tmp_path / "sim.log").open("w")
    proc = subprocess.Popen([sys.executable, "-m", "services.sim"], cwd=ROOT, env=env, stdout=log,
                            stderr=subprocess.STDOUT)
    client = None
    try:
        client = Client(api)  # waits for a heartbeat (20 s)
        assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
        assert client.armed()
    finally:
        if client is not None:
            client.close()
        # SIGKILL: the process still sits in zenoh.open waiting for the router, which ignores signals.
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        log.close()
