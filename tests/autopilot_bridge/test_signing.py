"""MAVLink 2 signing (issue 32): with AERMANI_AUTOPILOT_BRIDGE_SIGNING_KEY the bridge signs every frame it sends
and hears only frames signed with that key. Real MAVLink over UDP on loopback against fake PX4s that sign with
pymavlink's own code (as PX4 with a key on its SD card does)."""

from __future__ import annotations

import contextlib
import socket
import time

import pytest

from services.autopilot_bridge import px4
from services.autopilot_bridge.link import MavlinkLink
from services.autopilot_bridge.settings import BridgeSettings
from shared.errors import ConfigError
from shared.messages import ArmCommand
from tests.autopilot_bridge.fake_px4 import FakePX4, mavlink
from tests.autopilot_bridge.rig import running_bridge
from tests.helpers import free_udp_port, wait_until

KEY_HEX = "5f" * 16 + "a3" * 16
KEY = bytes.fromhex(KEY_HEX)
OTHER_KEY = bytes(32)


@contextlib.asynccontextmanager
async def signing_bridge(monkeypatch: pytest.MonkeyPatch):
    port = free_udp_port()
    monkeypatch.setenv("AERMANI_AUTOPILOT_BRIDGE_SIGNING_KEY", KEY_HEX)
    s = BridgeSettings(connection=f"udpin:127.0.0.1:{port}", command_timeout_s=0.5)
    link = MavlinkLink(s.connection, signing_key=s.signing_key_bytes)
    assert link.signing
    async with running_bridge(s, link) as bridge:
        yield bridge, port


async def test_a_signing_autopilot_is_heard_and_gets_signed_frames(monkeypatch: pytest.MonkeyPatch) -> None:
    async with signing_bridge(monkeypatch) as (bridge, port):
        fake = FakePX4(port, signing_key=KEY).start()
        try:
            await wait_until(lambda: bridge.link_ok and bridge.have_position, 20, what="the signing PX4")
            res = await bridge.handle(ArmCommand())
            assert res.ok and res.ack_name == "MAV_RESULT_ACCEPTED", res
            await wait_until(lambda: "HEARTBEAT" in fake.names(), 10, what="our heartbeat")
            # The fake checks signatures with pymavlink's own code and accepts only signed frames: everything it
            # decoded from us was signed with the key, nothing came out as bad data.
            assert fake.mav.signing.goodsig_count > 0 and fake.mav.signing.badsig_count == 0
            assert "BAD_DATA" not in fake.names() and "COMMAND_LONG" in fake.names()
            assert bridge.counters["bad_signature"] == 0 and bridge.health().details["signing"] is True
        finally:
            fake.stop()


@pytest.mark.parametrize("key", [None, OTHER_KEY], ids=["unsigned", "another key"])
async def test_an_unsigned_or_wrongly_signed_autopilot_is_not_heard(key: bytes | None,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """PX4's own ids, from loopback, first on the port: without the key it is not the autopilot."""
    async with signing_bridge(monkeypatch) as (bridge, port):
        fake = FakePX4(port, signing_key=key)
        fake.ned, fake.armed = [7.0, 7.0, -3.0], True
        fake.start()
        try:
            await wait_until(lambda: bridge.counters["bad_signature"] >= 30, 20, what="the fake's frames")
            st = bridge.state()
            assert not st.link_ok and not st.armed and (st.position.x, st.position.y, st.position.z) == (0, 0, 0)
            assert bridge.target_system is None and bridge.link.peer is None
            assert fake.received == []
        finally:
            fake.stop()


async def test_a_forged_future_timestamp_does_not_lock_the_autopilot_out(monkeypatch: pytest.MonkeyPatch) -> None:
    """A forged frame claiming PX4's stream (same ids and link id) with a timestamp years ahead, before the real
    PX4 speaks: pymavlink's own check would store that timestamp before finding the signature wrong, and every
    real frame after it would be 'old'. The bridge checks the signature first."""
    async with signing_bridge(monkeypatch) as (bridge, port):
        forger = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        forger.signing.secret_key, forger.signing.link_id, forger.signing.sign_outgoing = OTHER_KEY, 0, True
        forger.signing.timestamp = int((time.time() - 1420070400 + 10 * 365 * 86400) * 100_000)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            for _ in range(5):
                tx.sendto(forger.heartbeat_encode(2, px4.MAV_AUTOPILOT_PX4, 0, 0, 4).pack(forger),
                          ("127.0.0.1", port))
        await wait_until(lambda: bridge.counters["bad_signature"] >= 5, 10, what="the forged frames")
        fake = FakePX4(port, signing_key=KEY, link_id=0).start()
        try:
            await wait_until(lambda: bridge.link_ok and bridge.have_position, 20, what="the real PX4 after the forgery")
        finally:
            fake.stop()


async def test_a_replayed_signed_frame_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """A signed frame recorded off the link and sent again (same timestamp) is not heard twice."""
    async with signing_bridge(monkeypatch) as (bridge, port):
        mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        mav.signing.secret_key, mav.signing.link_id, mav.signing.sign_outgoing = KEY, 0, True
        mav.signing.timestamp = int((time.time() - 1420070400) * 100_000)
        frame = mav.heartbeat_encode(2, px4.MAV_AUTOPILOT_PX4, 0, 0, 4).pack(mav)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            tx.sendto(frame, ("127.0.0.1", port))
            await wait_until(lambda: bridge.target_system == 1, 10, what="the signed heartbeat")
            heard = bridge.counters["mavlink_received"]
            for _ in range(3):
                tx.sendto(frame, ("127.0.0.1", port))
            await wait_until(lambda: bridge.counters["mavlink_received"] >= heard + 3, 10, what="the replays")
        assert bridge.counters["bad_signature"] == 3


def test_the_key_is_64_hex_digits_and_never_repeated(monkeypatch: pytest.MonkeyPatch) -> None:
    assert BridgeSettings().signing_key is None  # off by default, as PX4 without a key
    monkeypatch.setenv("AERMANI_AUTOPILOT_BRIDGE_SIGNING_KEY", "")  # compose passes an unset variable so
    assert BridgeSettings().signing_key is None
    for bad in ("00" * 31, "zz" * 32, "secret-password"):
        monkeypatch.setenv("AERMANI_AUTOPILOT_BRIDGE_SIGNING_KEY", bad)
        with pytest.raises(ConfigError, match="AERMANI_AUTOPILOT_BRIDGE_SIGNING_KEY") as refused:
            BridgeSettings()
        assert bad not in str(refused.value)
    monkeypatch.setenv("AERMANI_AUTOPILOT_BRIDGE_SIGNING_KEY", KEY_HEX.upper())
    s = BridgeSettings()
    assert s.signing_key_bytes == KEY and KEY_HEX not in repr(s) and KEY_HEX.upper() not in str(s.model_dump())
