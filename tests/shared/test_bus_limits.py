"""Bus limits: oversize samples and requests refused before they are copied, a bounded hand-off while the loop
is busy, a cap on concurrent queries, rate-limited warnings, and the counters in the service's health."""

from __future__ import annotations

import asyncio
import logging
import time

import pytest

from shared import messages as m
from shared.bus import QUERY_CONCURRENCY, RateLimitedWarning
from shared.errors import RemoteError
from shared.keys import MESSAGE_MAX_BYTES, Query, Topic
from tests.helpers import bus_pair, first_answer, matched, wait_until

pytestmark = pytest.mark.integration



async def test_oversize_samples_are_dropped_and_counted(router):
    async with bus_pair(router) as (a, b):
        capped = Topic("test/capped", m.Health, "test", "test", max_bytes=4096).bind("t1")
        default = Topic("test/default", m.Health, "test", "test").bind("t1")
        sub, sub_default = b.subscribe(capped), b.subscribe(default)
        await matched(a, capped, default)
        a.publish(capped, m.Health(service="s", ok=True, message="x" * 10_000))
        a.publish(capped, m.Health(service="s", ok=True, message="small"))
        # Built without validation: the contract's own bound (MAX_TEXT_CHARS) would refuse it; the cap is tested.
        a.publish(default, m.Health.model_construct(service="s", ok=True, message="y" * (MESSAGE_MAX_BYTES + 10)))
        a.publish(default, m.Health(service="s", ok=True, message="fits"))
        assert (await sub.recv(timeout=5)).message == "small"
        assert (await sub_default.recv(timeout=5)).message == "fits"
        assert sub.oversize == 1 and sub_default.oversize == 1
        assert b.stats()["oversize"] == 2


async def test_hand_off_is_bounded_while_the_loop_is_busy(router):
    async with bus_pair(router) as (a, b):
        t = Topic("test/flood", m.Health, "test", "test").bind("t1")
        sub = b.subscribe(t, maxsize=20)
        await matched(a, t)
        for i in range(500):
            a.publish(t, m.Health(service="s", ok=True, details={"i": i}))
        time.sleep(1.5)  # the loop is blocked: every sample waits in the hand-off, which must stay bounded
        assert sub.qsize() <= 20  # the hand-off is the subscription's one bounded queue
        await wait_until(lambda: sub.received == 500, 30, what="500 handed off")
        assert sub.qsize() <= 20
        kept = []
        while (v := sub.recv_nowait()) is not None:
            kept.append(v.details["i"])
        assert sub.received == 500 and len(kept) + sub.dropped == 500 and kept[-1] == 499
        assert b.stats()["dropped"] == sub.dropped > 0
        # Health published on this bus now carries the counters.
        h = Topic("test/health", m.Health, "test", "test").bind("t1")
        hs = a.subscribe(h)
        await matched(b, h)
        b.publish(h, m.Health(service="s", ok=True))
        got = await hs.recv(timeout=5)
        assert got.details["bus"]["dropped"] == sub.dropped


async def test_latest_value_subscription_counts_superseded_not_dropped(router):
    """`overflow="latest"`: the consumer reads only the newest value; older ones it never read are superseded,
    not lost, so they stay out of `dropped` and out of the health counters."""
    async with bus_pair(router) as (a, b):
        t = Topic("test/state", m.Health, "test", "test").bind("t1")
        sub = b.subscribe(t, maxsize=2, overflow="latest")
        await matched(a, t)
        for i in range(200):
            a.publish(t, m.Health(service="s", ok=True, details={"i": i}))
        time.sleep(1.0)  # a busy loop: the samples wait in the hand-off
        await wait_until(lambda: sub.received == 200, 30, what="200 handed off")
        kept = []
        while (v := sub.recv_nowait()) is not None:
            kept.append(v.details["i"])
        assert kept[-1] == 199 and len(kept) <= 2
        assert sub.received == 200 and sub.superseded == 200 - len(kept) and sub.dropped == 0
        assert b.stats()["dropped"] == 0 and b.stats()["superseded"] == sub.superseded
        h = Topic("test/health", m.Health, "test", "test").bind("t1")
        hs = a.subscribe(h)
        await matched(b, h)
        b.publish(h, m.Health(service="s", ok=True))
        assert "bus" not in (await hs.recv(timeout=5)).details


async def test_concurrent_queries_beyond_the_cap_get_busy_and_big_requests_are_refused(router):
    async with bus_pair(router) as (a, b):
        release = asyncio.Event()

        async def slow(req: m.SkillRequest) -> m.SkillAccept:
            await release.wait()
            return m.SkillAccept(accepted=True, goal_id="g")

        q = Query("test/slowq", m.SkillRequest, m.SkillAccept, "test", "test").bind("t1")
        a.serve(q, slow)
        # A quick queryable declared after the slow one: once it answers, the router knows both.
        ping = Query("test/ping", m.SkillRequest, m.SkillAccept, "test", "test").bind("t1")

        async def pong(req: m.SkillRequest) -> m.SkillAccept:
            return m.SkillAccept(accepted=True, goal_id="pong")

        a.serve(ping, pong)
        await first_answer(b, ping, m.SkillRequest(skill="x"))
        calls = [asyncio.create_task(b.query(q, m.SkillRequest(skill="x"), timeout=10))
                 for _ in range(QUERY_CONCURRENCY + 5)]
        for _ in range(100):  # every request has reached the server: the first QUERY_CONCURRENCY wait
            if a.stats()["refused_queries"] >= 5 and sum(c.done() for c in calls) >= 5:
                break
            await asyncio.sleep(0.1)
        done = [c for c in calls if c.done()]
        assert len(done) == 5 and all("busy" in str(c.exception()) for c in done)
        release.set()
        results = await asyncio.gather(*calls, return_exceptions=True)
        assert sum(isinstance(r, m.SkillAccept) for r in results) == QUERY_CONCURRENCY
        assert sum(isinstance(r, RemoteError) for r in results) == 5
        assert a.stats()["refused_queries"] == 5
        with pytest.raises(RemoteError, match="exceeds"):
            await b.query(f"{q}", b"{" + b" " * (MESSAGE_MAX_BYTES + 1) + b"}", timeout=10)


def test_rate_limited_warning_holds_back_repeats(caplog):
    warn = RateLimitedWarning(period_s=60)
    with caplog.at_level(logging.WARNING, logger="aermani.bus"):
        for i in range(100):
            warn("bad sample %d", i)
    assert len(caplog.records) == 1
    warn._last -= 61
    with caplog.at_level(logging.WARNING, logger="aermani.bus"):
        warn("bad sample %d", 100)
    assert len(caplog.records) == 2 and "99 more like it" in caplog.records[-1].getMessage()
