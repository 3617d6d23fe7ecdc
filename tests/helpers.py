"""Test helpers shared by every test package: free ports, a running stack, async helpers."""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

from aermani.launcher import Stack, free_port, free_udp_port, loopback_mavlink_env
from shared.bus import Bus, Subscription
from shared.errors import NoResponder
from shared.keys import BoundTopic
from shared.messages import SkillStatus

__all__ = ["Stack", "free_port", "free_udp_port", "run_stack", "bus_for", "wait_until", "skill_outcome", "arun"]


@contextlib.contextmanager
def run_stack(services: list[str], tmp_path: Path, *, vehicle_id: str = "am1", env: dict[str, str] | None = None,
              timeout: float = 120.0, supervise: bool = False) -> Iterator[Stack]:
    """Router on a free port + the named services as real processes; stopped with SIGTERM at exit.

    Services get free UDP ports for MAVLink (AERMANI_SIM_API_PORT / AERMANI_AUTOPILOT_BRIDGE_CONNECTION) so
    parallel test runs never collide. Logs go to tmp_path/logs; a failure prints their tails."""
    base_env = loopback_mavlink_env(env)
    stack = Stack(services, vehicle_id=vehicle_id, env=base_env, log_dir=tmp_path / "logs", supervise=supervise)
    try:
        stack.start(wait=True, timeout=timeout)
        yield stack
    except BaseException:
        for p in stack.procs:
            print(f"--- log of {p.label} ---\n{p.tail(40)}")
        raise
    finally:
        stack.stop()


@contextlib.asynccontextmanager
async def bus_pair(endpoint: str) -> AsyncIterator[tuple[Bus, Bus]]:
    """Two client Buses on one router (a publisher/server and a subscriber/client), closed at exit."""
    a = await Bus.open(connect=[endpoint])
    try:
        b = await Bus.open(connect=[endpoint])
        try:
            yield a, b
        finally:
            await b.close()
    finally:
        await a.close()


@contextlib.asynccontextmanager
async def bus_for(stack: Stack):
    """A client Bus connected to the stack's router."""
    bus = await Bus.open(connect=[stack.endpoint])
    try:
        yield bus
    finally:
        await bus.close()


async def wait_until(pred: Callable[[], bool], timeout: float = 30.0, interval: float = 0.05, what: str = "") -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError(f"condition not met in {timeout} s: {what}")
        await asyncio.sleep(interval)


async def matched(publisher: Bus, *topics: BoundTopic[Any]) -> None:
    """Wait until the router has told `publisher` of a subscriber on every topic: a fixed pause before the first
    publish races the subscription's way through the router, and loses it on a loaded machine."""
    for t in topics:
        await wait_until(lambda t=t: publisher.has_subscribers(t), 30, what=f"a subscriber on {t.key}")


async def first_answer(bus: Bus, q: Any, request: Any, timeout: float = 30.0) -> Any:
    """The first reply of `q` once its queryable is known behind the router (NoResponder until then)."""
    deadline = asyncio.get_running_loop().time() + timeout
    while True:
        try:
            return await bus.query(q, request, timeout=5)
        except NoResponder:
            if asyncio.get_running_loop().time() > deadline:
                raise
            await asyncio.sleep(0.1)


async def skill_outcome(statuses: Subscription[SkillStatus], goal_id: str, timeout: float) -> SkillStatus:
    """The terminal status of skill goal `goal_id` from the executor's status stream (TimeoutError after
    `timeout` seconds)."""

    async def loop() -> SkillStatus:
        while True:
            st = await statuses.recv()
            if st.goal_id == goal_id and st.state.terminal:
                return st

    return await asyncio.wait_for(loop(), timeout)


def arun(coro, timeout: float = 240.0):
    """Run a coroutine to completion from a sync test, with an overall timeout."""
    return asyncio.run(asyncio.wait_for(coro, timeout))


class BusCollector:
    """What a bus source yields, collected on a thread with its own bus and event loop while a sync test drives
    processes (a CLI, signals). `source(bus)` declares what to read and returns the coroutine function that gives
    the next item; the collector is ready once `ready(items)` holds (default: at once, the source declared)."""

    def __init__(self, endpoint: str, source: Callable[[Bus], Callable[[], Awaitable[Any]]],
                 ready: Callable[[list[Any]], bool] = lambda items: True) -> None:
        self.endpoint, self.source, self.ready = endpoint, source, ready
        self.items: list[Any] = []
        self._ready, self._done = threading.Event(), threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._collect()), daemon=True)

    async def _collect(self) -> None:
        async with await Bus.open(connect=[self.endpoint]) as bus:
            next_item = self.source(bus)
            while not self._done.is_set():
                if self.ready(self.items):
                    self._ready.set()
                with contextlib.suppress(TimeoutError):
                    self.items.append(await asyncio.wait_for(next_item(), 0.2))

    def wait_for(self, pred: Callable[[list[Any]], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not pred(self.items):
            assert time.monotonic() < deadline, f"timed out waiting for {what}; collected {self.items}"
            time.sleep(0.05)

    def __enter__(self) -> BusCollector:
        self._thread.start()
        assert self._ready.wait(30), "the collector's source never became ready"
        return self

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        self._thread.join(10)
