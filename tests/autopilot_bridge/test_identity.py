"""Who the autopilot is (issue 32): only a PX4 HEARTBEAT from the configured system and component (PX4's 1/1 by
default) is taken for it, and while it holds the link a second autopilot (another system id, or the same ids from
another address) is ignored, logged once with its address and never put on the bus as the vehicle's state.
Real MAVLink over UDP on loopback, fake PX4s from fake_px4.py, a real Zenoh router for the published state."""

from __future__ import annotations

import asyncio
import logging

import pytest

from services.autopilot_bridge.bridge import Bridge
from services.autopilot_bridge.link import MavlinkLink
from services.autopilot_bridge.settings import BridgeSettings
from shared.bus import Bus
from shared.keys import Keys
from tests.autopilot_bridge.fake_px4 import FakePX4
from tests.autopilot_bridge.rig import running_bridge
from tests.helpers import free_port, free_udp_port, wait_until

REFUSED = "refused a second autopilot"


def _refusals(caplog: pytest.LogCaptureFixture, port: int) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if REFUSED in r.getMessage() and f"127.0.0.1:{port} " in r.getMessage()]


def _intruder(port: int, system: int, component: int = 1) -> FakePX4:
    """A fake PX4 that says the vehicle is armed in OFFBOARD at (7, 7, 3) ENU: if any of that reaches the state,
    the test sees it."""
    fake = FakePX4(port, system=system, component=component)
    fake.ned = [7.0, 7.0, -3.0]
    fake.armed, fake.mode = True, "OFFBOARD"
    return fake.start()


async def test_a_second_autopilot_beside_the_first_does_not_change_the_published_state(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="aermani.autopilot_bridge")
    zport, uport = free_port(), free_udp_port()
    router = await Bus.open(mode="router", listen=[f"tcp/127.0.0.1:{zport}"], connect=[])
    bus = await Bus.open(connect=[f"tcp/127.0.0.1:{zport}"])
    client = await Bus.open(connect=[f"tcp/127.0.0.1:{zport}"])
    s = BridgeSettings(connection=f"udpin:127.0.0.1:{uport}", vehicle_id="t1", health_period_s=0.3,
                       state_rate_hz=30.0)
    keys = Keys("t1")
    states = client.subscribe(keys.autopilot_state, maxsize=10000)
    health = client.subscribe(keys.health("autopilot_bridge"), maxsize=100)
    stop = asyncio.Event()
    bridge = Bridge(bus, s, MavlinkLink(s.connection))
    task = asyncio.create_task(bridge.run(stop))
    ours = FakePX4(uport).start()
    intruders: list[FakePX4] = []
    try:
        st = await states.recv(20)
        while not (st.link_ok and st.landed_state == "on_ground"):
            st = await states.recv(20)
        assert st.mode == "POSCTL" and not st.armed
        peer = bridge.link.peer
        assert peer == ("127.0.0.1", ours.port)

        # Another vehicle's system id, and our own ids from another address, both while ours holds the link.
        intruders = [_intruder(uport, system=2), _intruder(uport, system=1)]
        await wait_until(lambda: bridge.counters["refused_autopilot"] >= 20, 20, what="the intruders' heartbeats")
        seen = 0
        while (sample := states.recv_nowait()) is not None:
            seen += 1
            assert sample.link_ok and sample.mode == "POSCTL" and not sample.armed, sample
            assert abs(sample.position.x) < 0.01 and abs(sample.position.y) < 0.01 and abs(sample.position.z) < 0.01
        assert seen > 0  # the state kept being published while the intruders sent
        assert bridge.link.peer == peer and bridge.target_system == 1
        # Nothing of ours went to them: no setpoints, no commands, not even our heartbeat.
        assert all(fake.received == [] for fake in intruders)
        assert bridge.counters["wrong_system"] > 0 and bridge.counters["wrong_address"] > 0
        # Each logged once, with its address, however many heartbeats it sent.
        for fake in intruders:
            lines = _refusals(caplog, fake.port)
            assert len(lines) == 1, lines
            assert f"system {fake.system} component 1" in lines[0]
        h = await health.recv(10)
        while len(h.details.get("refused_autopilots", [])) < 2:
            h = await health.recv(10)
        assert sorted(h.details["refused_autopilots"]) == sorted(f"{f.system}/1 at 127.0.0.1:{f.port}"
                                                                  for f in intruders)
    finally:
        stop.set()
        await asyncio.wait_for(task, 10)
        for fake in (ours, *intruders):
            fake.stop()
        for b in (client, bus, router):
            await b.close()


@pytest.mark.parametrize(("system", "component"), [(2, 1), (1, 2), (255, 190)],
                         ids=["wrong sysid", "wrong compid", "both wrong"])
async def test_a_fake_with_other_ids_is_not_taken_for_the_autopilot(system: int, component: int,
                                                                     caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="aermani.autopilot_bridge")
    port = free_udp_port()
    s = BridgeSettings(connection=f"udpin:127.0.0.1:{port}")
    assert (s.target_system, s.target_component) == (1, 1)  # PX4's own ids by default
    link = MavlinkLink(s.connection)
    async with running_bridge(s, link) as bridge:
        fake = _intruder(port, system, component)
        try:
            await wait_until(lambda: bridge.counters["refused_autopilot"] >= 10, 20, what="the fake's heartbeats")
            st = bridge.state()
            assert not st.link_ok and not st.armed and st.mode == "UNKNOWN"
            assert (st.position.x, st.position.y, st.position.z) == (0.0, 0.0, 0.0)
            assert bridge.target_system is None and link.peer is None and not bridge.have_position
            assert fake.received == []
            assert len(_refusals(caplog, fake.port)) == 1
        finally:
            fake.stop()


async def test_configured_ids_are_the_ones_taken() -> None:
    """The same kind of fake is the autopilot once the settings name its ids (so the refusal above is the ids,
    not the fake)."""
    port = free_udp_port()
    s = BridgeSettings(connection=f"udpin:127.0.0.1:{port}", target_system=2, target_component=2)
    link = MavlinkLink(s.connection)
    async with running_bridge(s, link) as bridge:
        default_ids = _intruder(port, 1, 1)
        fake = _intruder(port, 2, 2)
        try:
            await wait_until(lambda: bridge.link_ok and bridge.have_position, 20, what="the configured autopilot")
            assert (bridge.target_system, bridge.target_component) == (2, 2)
            assert link.peer == ("127.0.0.1", fake.port)
            await wait_until(lambda: "HEARTBEAT" in fake.names(), 10, what="our heartbeat to it")
            ours = next(m for m in fake.received if m.get_type() == "HEARTBEAT")
            assert ours.get_srcSystem() == s.source_system
            st = bridge.state()
            assert st.armed and st.mode == "OFFBOARD" and abs(st.position.z - 3.0) < 0.01
            assert default_ids.received == []
        finally:
            fake.stop()
            default_ids.stop()


def test_ids_are_settings_with_px4_defaults(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AERMANI_AUTOPILOT_BRIDGE_TARGET_SYSTEM", "3")
    monkeypatch.setenv("AERMANI_AUTOPILOT_BRIDGE_TARGET_COMPONENT", "4")
    s = BridgeSettings()
    assert (s.target_system, s.target_component) == (3, 4)
    monkeypatch.setenv("AERMANI_AUTOPILOT_BRIDGE_TARGET_SYSTEM", "0")  # no "take whoever comes first"
    with pytest.raises(ValueError, match="target_system"):
        BridgeSettings()
