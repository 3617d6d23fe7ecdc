"""An in-process test rig: router, the executor on its own client session, fakes and a caller on another."""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import dataclass

from aermani.launcher import free_port, open_router
from services.executor.service import Executor
from services.executor.settings import ExecutorSettings
from shared.bus import Bus, Subscription
from shared.errors import BusError
from shared.keys import Keys
from shared.messages import SkillAccept, SkillRequest, SkillState, SkillStatus, WorkingMemory
from tests.executor.fakes import FakeAutopilot, FakeDepth, FakePerception, ToyWorld, cancel_all
from tests.helpers import skill_outcome, wait_until


@dataclass
class Rig:
    bus: Bus
    executor: Executor
    vehicle: FakeAutopilot
    perception: FakePerception
    depth: FakeDepth
    world: ToyWorld
    keys: Keys
    statuses: Subscription[SkillStatus]
    memory: Subscription[WorkingMemory]

    async def request(self, skill: str, argument: str | None = None, task_id: str = "t1") -> SkillAccept:
        request = SkillRequest(skill=skill, argument=argument, task_id=task_id)
        return await self.bus.query(self.keys.run_skill, request, timeout=5.0)

    async def terminal(self, goal_id: str, timeout: float = 60.0) -> SkillStatus:
        return await skill_outcome(self.statuses, goal_id, timeout)

    async def run_skill(self, skill: str, argument: str | None = None, timeout: float = 60.0) -> SkillStatus:
        acc = await self.request(skill, argument)
        st = await self.terminal(acc.goal_id, timeout)
        if not acc.accepted:
            assert st.state == SkillState.REJECTED
        return st


@contextlib.asynccontextmanager
async def rig(airborne_at: float | None = 1.5, depth_m: float | None = 8.0, **settings_kw):
    port = free_port()
    router = open_router(port)
    endpoint = f"tcp/127.0.0.1:{port}"
    # The fakes, the router's client sessions and the executor share this one event loop: a stall of half a
    # second (the production limit) under a loaded machine would read as a stale state mid-skill. The tests of
    # staleness itself ask for the production limit.
    settings_kw.setdefault("state_max_age_s", 2.0)
    settings = ExecutorSettings(zenoh_connect=[endpoint], **settings_kw)
    keys = settings.keys
    ebus = await Bus.open(connect=[endpoint])
    bus = await Bus.open(connect=[endpoint])
    world = ToyWorld()
    vehicle = FakeAutopilot(bus, keys, world, airborne_at=airborne_at)
    perception = FakePerception(bus, keys, world, vehicle)
    perception.serve()
    depth = FakeDepth(bus, keys, depth_m or 8.0)
    depth.publishing = depth_m is not None
    executor = Executor(ebus, settings)
    stop = asyncio.Event()
    statuses = bus.subscribe(keys.skill_status, maxsize=1000, overflow="drop_newest")
    memory = bus.subscribe(keys.memory, maxsize=1000)
    tasks = [asyncio.create_task(vehicle.run()), asyncio.create_task(depth.run()),
             asyncio.create_task(perception.run()), asyncio.create_task(executor.run(stop))]
    try:
        await wait_until(lambda: executor.state.value is not None
                         and (depth_m is None or executor.clearance.depth is not None), 20.0, what="executor inputs")
        # The executor's queryables must be reachable from the caller's session before the test starts.
        for _ in range(100):
            with contextlib.suppress(BusError):
                await bus.query(keys.skills, None, timeout=1.0)
                break
            await asyncio.sleep(0.05)
        yield Rig(bus, executor, vehicle, perception, depth, world, keys, statuses, memory)
    finally:
        stop.set()
        await cancel_all(tasks)
        await bus.close()
        await ebus.close()
        router.close()
