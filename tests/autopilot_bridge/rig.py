"""A real Bridge on a real MAVLink link, without the bus: started, heartbeating, and torn down in one place."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator

from services.autopilot_bridge.bridge import Bridge
from services.autopilot_bridge.link import MavlinkLink
from services.autopilot_bridge.settings import BridgeSettings


@contextlib.asynccontextmanager
async def running_bridge(settings: BridgeSettings, link: MavlinkLink) -> AsyncIterator[Bridge]:
    """The bridge listening on `link` and sending its heartbeat; on exit its tasks are cancelled and the link
    closed (the fakes on the other end are the caller's)."""
    bridge = Bridge(None, settings, link)
    stop = asyncio.Event()
    link.start(asyncio.get_running_loop(), bridge.on_message)
    hb = asyncio.create_task(bridge.heartbeat_loop(stop))
    try:
        yield bridge
    finally:
        stop.set()
        hb.cancel()
        for t in list(bridge._tasks):
            t.cancel()
        link.close()
