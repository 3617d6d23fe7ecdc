"""The bridge's Zenoh side on real sessions over loopback (bridge in-process, fake PX4 over UDP):
state and health publications, the command queryable, and malformed commands."""

from __future__ import annotations

import asyncio
import json
import os
import sys

import pytest

from services.autopilot_bridge.bridge import Bridge
from services.autopilot_bridge.link import MavlinkLink
from services.autopilot_bridge.settings import BridgeSettings
from shared.bus import Bus
from shared.errors import RemoteError
from shared.keys import Keys
from shared.messages import TakeoffCommand
from shared.sensors import parse_transforms
from tests.autopilot_bridge.fake_px4 import FakePX4
from tests.helpers import free_port, free_udp_port, wait_until

pytestmark = pytest.mark.integration  # starts the CLI as a process


async def test_state_health_commands_over_zenoh() -> None:
    zport, uport = free_port(), free_udp_port()
    router = await Bus.open(mode="router", listen=[f"tcp/127.0.0.1:{zport}"], connect=[])
    bus = await Bus.open(connect=[f"tcp/127.0.0.1:{zport}"])
    client = await Bus.open(connect=[f"tcp/127.0.0.1:{zport}"])
    s = BridgeSettings(connection=f"udpin:127.0.0.1:{uport}", vehicle_id="t1", offboard_warmup_s=0.3,
                       command_timeout_s=0.5, health_period_s=0.3, publish_tf=True)
    keys = Keys("t1")
    states = client.subscribe(keys.autopilot_state, maxsize=1000)
    health = client.subscribe(keys.health("autopilot_bridge"))
    tf = client.subscribe(keys.tf)
    stop = asyncio.Event()
    bridge = Bridge(bus, s, MavlinkLink(s.connection))
    task = asyncio.create_task(bridge.run(stop))
    fake = FakePX4(uport).start()
    try:
        st = await states.recv(20)
        while not st.link_ok:
            st = await states.recv(20)
        assert st.vehicle_id == "t1" and st.mode == "POSCTL"

        res = await client.query(keys.autopilot_command, TakeoffCommand(altitude=1.2),
                                 timeout=30)
        assert res.ok and res.command == "takeoff", res.message
        await wait_until(lambda: (states.latest_nowait() or st).offboard_ok or bridge.state().offboard_ok, 10)

        # Malformed requests get an error reply and change nothing.
        before = fake.setpoints[-1]
        for bad in (b"{not json", json.dumps({"kind": "teleport"}).encode(),
                    json.dumps({"kind": "goto", "position": {"x": 1, "y": 0, "z": 1}}).encode()):
            with pytest.raises(RemoteError):
                await client.query(keys.autopilot_command, bad)
        # NaN is refused when the request is decoded (the message models allow finite numbers only).
        nan_goto = b'{"kind": "goto", "position": {"x": NaN, "y": 0, "z": 1}, "yaw": 0}'
        with pytest.raises(RemoteError, match="finite number"):
            await client.query(keys.autopilot_command, nan_goto)
        await asyncio.sleep(0.2)
        after = fake.setpoints[-1]
        assert (after.x, after.y, after.z) == (before.x, before.y, before.z)

        h = await health.recv(10)
        while "jitter_p99_ms" not in h.details:
            h = await health.recv(10)
        assert h.ok and h.service == "autopilot_bridge" and h.details["setpoints_sent"] > 0
        assert h.details["interval_p50_ms"] > 0

        frames = parse_transforms(await tf.recv(10))
        assert ("world", "base_link") in frames

        # The hand-control CLI reads the same state and health.
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "aermani.cli", "autopilot", "state", "--connect", f"tcp/127.0.0.1:{zport}",
            "--vehicle", "t1", stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT,
            env={**os.environ, "COLUMNS": "200"})
        out, _ = await asyncio.wait_for(proc.communicate(), 60)
        text = out.decode()
        assert proc.returncode == 0, text
        assert "OFFBOARD" in text and "link=True" in text, text

        # >= 20 Hz: count states over one second of the publisher's own timestamps.
        first = await states.recv(5)
        n = 1
        last = first
        while last.stamp_ns - first.stamp_ns < 1_000_000_000:
            last = await states.recv(5)
            n += 1
        assert n >= 10  # nominal 30 Hz; lenient so a loaded CI box does not flake
    finally:
        stop.set()
        await asyncio.wait_for(task, 10)
        fake.stop()
        for b in (client, bus, router):
            await b.close()
