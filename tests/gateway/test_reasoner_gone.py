"""The gateway when a reasoner's liveliness token vanishes: its running task is ended as an orphan, unless the
same reasoner process comes back within the grace (only the way to it broke: a router restart), which is still
running the task. Real router, real Fleet and Store, a reasoner played by a bus client with its token and
heartbeat."""

from __future__ import annotations

import asyncio
import contextlib
import time
from pathlib import Path

import pytest

from services.gateway.fleet import Fleet
from services.gateway.store import Store
from shared.bus import Bus
from shared.keys import Keys
from shared.messages import Heartbeat, TaskState, TaskStatus

pytestmark = pytest.mark.integration

VID = "am1"
KEYS = Keys(VID)


async def _until(pred, what: str, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not await pred():
        assert time.monotonic() < deadline, f"not seen in {timeout:.0f} s: {what}"
        await asyncio.sleep(0.05)


class Reasoner:
    """A reasoner as the gateway sees it: a liveliness token and a heartbeat with its pid."""

    def __init__(self, bus: Bus) -> None:
        self.bus, self.pid, self.token, self.beating = bus, 4242, None, None

    def up(self, pid: int) -> None:
        self.pid = pid
        self.token = self.bus.declare_token(KEYS.alive("reasoner"))
        self.beating = asyncio.create_task(self._beat())

    async def down(self) -> None:
        self.beating.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self.beating
        self.token.undeclare()

    async def _beat(self) -> None:
        while True:
            self.bus.publish(KEYS.heartbeat("reasoner"), Heartbeat(service="reasoner", pid=self.pid))
            await asyncio.sleep(0.1)


async def test_a_reasoner_back_as_the_same_process_keeps_its_task_a_new_one_ends_it(router: str,
                                                                                     tmp_path: Path) -> None:
    store = Store(str(tmp_path / "gateway.sqlite3"))
    await store.open()
    gw_bus = await Bus.open(connect=[router])
    r_bus = await Bus.open(connect=[router])
    fleet = Fleet(gw_bus, store)
    reasoner = Reasoner(r_bus)
    try:
        await fleet.start()
        reasoner.up(pid=1111)
        view = fleet.view(VID)

        async def beating(pid: int) -> bool:
            return view.reasoner_alive and view.reasoner_beat is not None and view.reasoner_beat[0] == pid

        await _until(lambda: beating(1111), "the reasoner alive and beating")
        r_bus.publish(KEYS.task_status, TaskStatus(vehicle_id=VID, task_id="task-gone01", command="pick it up",
                                                   state=TaskState.RUNNING))

        async def state() -> str | None:
            task = await store.get_task("task-gone01")
            return task["state"] if task else None

        async def running() -> bool:
            return await state() == "running"

        await _until(running, "the task stored as running")

        # The way to the reasoner breaks and comes back; the process is the same one: its task goes on.
        await reasoner.down()
        await _until(lambda: _async(not view.reasoner_alive), "the token gone")
        reasoner.up(pid=1111)
        await _until(lambda: _async(not fleet._gone), "the gateway deciding about the vanished reasoner")
        assert await state() == "running"

        # The reasoner dies and a new process takes its place: the task has nobody, it ends with the reason.
        await reasoner.down()
        await _until(lambda: _async(not view.reasoner_alive), "the token gone again")
        reasoner.up(pid=2222)

        async def ended() -> bool:
            return await state() == "failed"

        await _until(ended, "the orphaned task ended")
        task = await store.get_task("task-gone01")
        assert "the reasoner of am1 stopped while the task was running" in task["status"]["message"], task
    finally:
        with contextlib.suppress(Exception):
            await reasoner.down()
        await fleet.stop()
        await gw_bus.close()
        await r_bus.close()
        await store.close()


async def _async(value: bool) -> bool:
    return value
