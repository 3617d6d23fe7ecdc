"""An abort always answers: hundreds of event streams opened and cancelled around it (clients that leave
mid-stream) never hold what the abort path waits on. Network-free on the gateway's side (the Fleet over a real
router, no HTTP), so every interleaving of cancellations runs many times."""

from __future__ import annotations

import asyncio
import random
from pathlib import Path

from services.gateway.fleet import Fleet
from services.gateway.store import Store
from shared.bus import Bus


async def test_abort_answers_while_streams_are_cancelled_around_it(router: str, tmp_path: Path) -> None:
    store = Store(str(tmp_path / "gateway.sqlite3"))
    await store.open()
    bus = await Bus.open(connect=[router])
    fleet = Fleet(bus, store)
    rng = random.Random(7)
    try:
        for round_ in range(300):
            # Streams wait for a change (some with a ping timeout that fires now); the change arrives and some
            # clients go away in the same moments, while an abort waits for acknowledgements.
            streams = [asyncio.create_task(fleet.wait_change(fleet.version, rng.choice([0.0005, 0.005, 5.0])))
                       for _ in range(rng.randint(2, 8))]
            abort = asyncio.create_task(fleet.abort(["am1"], "test", None, 0.02)) if round_ % 10 == 0 else None
            for _ in range(rng.randint(0, 3)):
                await asyncio.sleep(0)
            notify = asyncio.create_task(fleet._notify())
            for _ in range(rng.randint(0, 3)):
                await asyncio.sleep(0)
            for s in rng.sample(streams, 2):
                s.cancel()
            if abort is not None:
                # No vehicle runs here, so nothing acknowledges: the abort answers after its wait, always.
                assert await asyncio.wait_for(abort, 5.0) == {}
            for s in streams:
                s.cancel()
            await asyncio.gather(*streams, notify, return_exceptions=True)
        assert await asyncio.wait_for(fleet.abort(["am1"], "test", None, 0.05), 5.0) == {}
        # Streams still wake on a change after all that.
        since = fleet.version
        waiter = asyncio.create_task(fleet.wait_change(since, 5.0))
        await asyncio.sleep(0)
        await fleet._notify()
        await asyncio.wait_for(waiter, 2.0)
    finally:
        await bus.close()
        await store.close()
