"""Client side of the reasoner: submit a task (waiting for the service to serve) and follow it to the end."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

from shared.bus import Bus
from shared.errors import NoResponder, QueryTimeout
from shared.keys import Keys
from shared.messages import ReasoningStep, TaskAccept, TaskRequest, TaskStatus


async def submit_task(bus: Bus, keys: Keys, request: TaskRequest, timeout: float = 30.0) -> TaskAccept:
    """Send `reasoner/start_task`, retrying while nobody serves it yet (the liveliness token of a service
    appears before its queryables are declared)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return await bus.query(keys.start_task, request, TaskAccept, timeout=10.0)
        except (NoResponder, QueryTimeout):
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.3)


async def follow_task(bus: Bus, keys: Keys, request: TaskRequest, *, on_step: Callable[[ReasoningStep], None] =
                      lambda s: None, on_status: Callable[[TaskStatus], None] = lambda s: None,
                      timeout: float = 3600.0) -> tuple[TaskAccept, TaskStatus | None, list[ReasoningStep]]:
    """Submit `request` and stream its steps until the terminal status. Returns (accept, final, steps)."""
    steps_sub = bus.subscribe(keys.reasoning_step, ReasoningStep, maxsize=10_000)
    status_sub = bus.subscribe(keys.task_status, TaskStatus, maxsize=1000)
    steps: list[ReasoningStep] = []
    try:
        await asyncio.sleep(0.2)  # let the subscriptions reach the router before the first step
        accept = await submit_task(bus, keys, request)
        if not accept.accepted:
            return accept, None, steps

        async def drain_steps() -> None:
            while True:
                s = await steps_sub.recv()
                if s.task_id == request.task_id:
                    steps.append(s)
                    on_step(s)

        drainer = asyncio.create_task(drain_steps())
        try:
            async with asyncio.timeout(timeout):
                while True:
                    st = await status_sub.recv()
                    if st.task_id != request.task_id:
                        continue
                    on_status(st)
                    if st.state.terminal:
                        break
            await asyncio.sleep(0.3)  # the last step is published just before the status
        finally:
            drainer.cancel()
        return accept, st, steps
    finally:
        steps_sub.close()
        status_sub.close()
