"""The bus over real Zenoh sessions on loopback (a router and two or more clients, multicast scouting off)."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import textwrap

import pytest

from shared import messages as m
from shared.bus import Bus, zenoh_config
from shared.errors import NoResponder, QueryTimeout, RemoteError
from shared.keys import Protobuf, Query, Topic
from tests.helpers import bus_pair, first_answer, matched, wait_until
from tests.shared.samples import sample_messages


def topic(name: str, t: object, reliable: bool = True, vehicle: str = "t1") -> object:
    """A test topic declared like the real ones, bound to vehicle `t1` (a payload that names its vehicle is
    published on that vehicle's key: the bus refuses one on another's)."""
    return Topic(f"test/{name}", t, "test", "test", reliable=reliable).bind(vehicle)



def test_config_turns_multicast_off():
    cfg = zenoh_config(mode="client", connect=["tcp/127.0.0.1:1"])
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False


async def test_every_message_type_round_trips(router):
    async with bus_pair(router) as (a, b):
        samples = sample_messages()
        topics = {i: topic(f"rt/{i}", type(s), vehicle=getattr(s, "vehicle_id", "t1")) for i, s in enumerate(samples)}
        subs = {i: b.subscribe(topics[i]) for i, s in enumerate(samples)}
        await matched(a, *topics.values())
        for i, s in enumerate(samples):
            a.publish(topics[i], s)
        for i, s in enumerate(samples):
            rec = await subs[i].recv_sample(timeout=5)
            assert rec.value == s
            assert rec.encoding.endswith(s.full_schema_name())


async def test_union_and_raw_bytes_subscriptions(router):
    async with bus_pair(router) as (a, b):
        cmd_topic = topic("cmd", m.AutopilotCommand)
        raw_topic = topic("raw", Protobuf("foxglove.RawImage"))
        cmds = b.subscribe(cmd_topic)
        raw = b.subscribe(raw_topic)
        await matched(a, cmd_topic, raw_topic)
        a.publish(cmd_topic, m.TakeoffCommand(altitude=2.0))
        with pytest.raises(TypeError, match="carries"):
            a.publish(cmd_topic, m.Health(service="s", ok=True))  # not what the key declares
        a.publish(raw_topic, b"\x00\x01binary")
        got = await cmds.recv(timeout=5)
        assert isinstance(got, m.TakeoffCommand) and got.altitude == 2.0
        rec = await raw.recv_sample(timeout=5)
        assert rec.value == b"\x00\x01binary" and "foxglove.RawImage" in rec.encoding


async def test_malformed_payload_is_dropped_and_subscriber_keeps_working(router):
    async with bus_pair(router) as (a, b):
        state = topic("state", m.VehicleState)
        sub = b.subscribe(state)
        await matched(a, state)
        a.publish(state.key, b"\xff\xfenot json", schema="aermani.VehicleState")
        a.publish(state.key, {"kind": "vehicle_state", "armed": "maybe"})
        a.publish(state, m.VehicleState(vehicle_id="t1", armed=True))
        got = await sub.recv(timeout=5)
        assert got.armed is True
        assert sub.malformed == 2


async def test_query_reply_errors_and_timeout(router):
    async with bus_pair(router) as (a, b):
        async def accept(req: m.SkillRequest) -> m.SkillAccept:
            if req.skill == "slow":
                await asyncio.sleep(3)
            if req.skill == "boom":
                raise RuntimeError("handler failed")
            if req.skill == "upstream":
                raise TimeoutError("the VLM endpoint: read timeout")
            return m.SkillAccept(accepted=True, goal_id=f"g-{req.skill}")

        q = Query("test/q", m.SkillRequest, m.SkillAccept, "test", "test").bind("t1")
        nobody = Query("test/nobody", m.SkillRequest, m.SkillAccept, "test", "test").bind("t1")
        a.serve(q, accept)
        ok = await first_answer(b, q, m.SkillRequest(skill="forward"))
        assert ok.goal_id == "g-forward"
        with pytest.raises(RemoteError, match="skill"):
            await b.query(q, {"kind": "skill_request"}, timeout=5)
        with pytest.raises(RemoteError, match="handler failed"):
            await b.query(q, m.SkillRequest(skill="boom"), timeout=5)
        with pytest.raises(QueryTimeout):
            await b.query(q, m.SkillRequest(skill="slow"), timeout=0.5)
        # A service's own error that mentions a timeout is its error, not this query timing out.
        with pytest.raises(RemoteError, match="read timeout") as err:
            await b.query(q, m.SkillRequest(skill="upstream"), timeout=5)
        assert not isinstance(err.value, QueryTimeout)
        with pytest.raises(NoResponder):
            await b.query(nobody, m.SkillRequest(skill="x"), timeout=1)
        # The queryable survives all of that.
        ok = await b.query(q, m.SkillRequest(skill="left"), timeout=5)
        assert ok.goal_id == "g-left"


async def test_burst_of_1000_arrives_in_order_or_is_counted(router):
    async with bus_pair(router) as (a, b):
        burst = topic("burst", m.Health)
        small = b.subscribe(burst, maxsize=100)  # will overflow: drop_oldest
        big = b.subscribe(burst, maxsize=2000)  # will not
        await matched(a, burst)
        for i in range(1000):
            a.publish(burst, m.Health(service="s", ok=True, details={"i": i}))
        await wait_until(lambda: big.received == 1000, 20, what="1000 samples received")
        got = [(await big.recv(timeout=5)).details["i"] for _ in range(1000)]
        assert got == list(range(1000))
        assert big.dropped == 0
        kept = []
        while small.qsize():
            kept.append((await small.recv(timeout=1)).details["i"])
        assert small.received == 1000
        assert len(kept) + small.dropped == 1000
        assert kept == sorted(kept) and kept[-1] == 999  # newest kept, order preserved


async def test_drop_newest_policy_keeps_the_first(router):
    async with bus_pair(router) as (a, b):
        dn = topic("dn", m.Health)
        sub = b.subscribe(dn, maxsize=10, overflow="drop_newest")
        await matched(a, dn)
        for i in range(50):
            a.publish(dn, m.Health(service="s", ok=True, details={"i": i}))
        await wait_until(lambda: sub.received == 50, 10)
        kept = [(await sub.recv(timeout=1)).details["i"] for _ in range(sub.qsize())]
        assert kept == list(range(10)) and sub.dropped == 40


OWNER = textwrap.dedent("""
    import asyncio, sys
    from shared.bus import Bus
    async def main():
        bus = await Bus.open(connect=[sys.argv[1]])
        bus.declare_token("aermani/v1/t1/alive/owner")
        print("ready", flush=True)
        await asyncio.sleep(600)
    asyncio.run(main())
""")


async def settled(bus: Bus, pattern: str, want: list[str], timeout: float = 30.0) -> list[str]:
    """The router's liveliness view of `pattern` once it equals `want`, or its last answer after `timeout` s: the
    view converges a moment after the event that announced the change (longer on a loaded machine), so the
    bound is generous and only a view that never converges fails."""
    deadline = asyncio.get_running_loop().time() + timeout
    while (seen := await bus.alive(pattern)) != want and asyncio.get_running_loop().time() < deadline:
        await asyncio.sleep(0.1)
    return seen


async def test_liveliness_appears_and_disappears_after_sigkill(router):
    watcher = await Bus.open(connect=[router])
    proc = subprocess.Popen([sys.executable, "-c", OWNER, router], stdout=subprocess.PIPE, text=True,
                            env={**os.environ})
    try:
        events = watcher.watch_liveliness("aermani/v1/*/alive/*")
        assert (await asyncio.to_thread(proc.stdout.readline)).strip() == "ready"
        key, alive = await asyncio.wait_for(events.get(), 30)
        assert key == "aermani/v1/t1/alive/owner" and alive
        # A liveliness get may run a moment before the router's view has the token the event announced.
        assert await settled(watcher, "aermani/v1/*/alive/*", [key]) == [key]
        proc.send_signal(signal.SIGKILL)
        # The subscriber may see the token's appearance twice (history and live); what matters is the removal.
        while alive:
            key, alive = await asyncio.wait_for(events.get(), 30)
        assert key == "aermani/v1/t1/alive/owner" and not alive
        # The router's view converges right after the DELETE event (not always in the same instant).
        assert await settled(watcher, "aermani/v1/*/alive/*", []) == []
    finally:
        proc.kill()
        proc.wait()
        await watcher.close()


async def test_publish_after_close_is_an_error(router):
    a = await Bus.open(connect=[router])
    await a.close()
    with pytest.raises(Exception, match="closed"):
        a.publish("test/x", m.Health(service="s", ok=True))


def test_newer_minor_version_is_accepted_and_newer_major_rejected(router):
    """The versioning rule: unknown fields of a newer minor version are ignored; a newer major is refused
    with an error naming both versions."""
    from shared.bus import decoder

    dec = decoder(m.VehicleState)
    base = json.loads(m.VehicleState(armed=True).model_dump_json())
    newer_minor = {**base, "schema_minor": m.SCHEMA_MINOR + 1, "wind_estimate": {"x": 1.0},
                   "position": {**base["position"], "covariance": [0.1, 0.2]}}
    got = dec(json.dumps(newer_minor).encode())
    assert got.armed is True
    same_minor = {**base, "wind_estimate": 1.0}
    with pytest.raises(Exception, match="wind_estimate"):
        dec(json.dumps(same_minor).encode())
    newer_major = {**base, "schema_version": m.SCHEMA_VERSION + 1, "schema_minor": 0, "new": 1}
    with pytest.raises(Exception, match=f"version {m.SCHEMA_VERSION + 1}.0.*version {m.SCHEMA_VERSION}"):
        dec(json.dumps(newer_major).encode())
    valid_newer_major = {**base, "schema_version": m.SCHEMA_VERSION + 1}
    with pytest.raises(Exception, match="cannot be read"):
        dec(json.dumps(valid_newer_major).encode())
