"""The gateway process: uvicorn serving the app on the service's own loop and bus until `stop` is set."""

from __future__ import annotations

import asyncio
import contextlib
import logging

import uvicorn

from services.gateway.app import create_app
from services.gateway.settings import GatewaySettings
from shared.bus import Bus
from shared.errors import ConfigError

log = logging.getLogger("aermani.gateway")


class _Server(uvicorn.Server):
    # shared.service owns SIGINT/SIGTERM (they set `stop`); uvicorn must not replace those handlers.
    @contextlib.contextmanager
    def capture_signals(self):
        yield


async def run(bus: Bus, settings: GatewaySettings, stop: asyncio.Event) -> None:
    app = create_app(settings, bus)
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_config=None, lifespan="on",
                            timeout_graceful_shutdown=3, proxy_headers=False, server_header=False,
                            ssl_certfile=settings.tls_certfile, ssl_keyfile=settings.tls_keyfile)
    server = _Server(config)
    serving = asyncio.create_task(server.serve(), name="gateway.http")
    stopping = asyncio.create_task(stop.wait(), name="gateway.stop")
    log.info("gateway on %s://%s:%d (token %s)", "https" if settings.tls_certfile else "http", settings.host,
             settings.port,
             "required" if settings.token is not None else "not set: loopback only, no auth")
    try:
        await asyncio.wait({serving, stopping}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        stopping.cancel()
        fleet = getattr(app.state, "fleet", None)
        if fleet is not None:
            fleet.closing.set()  # ends the event streams so the graceful shutdown does not wait on them
            await fleet._notify()
        server.should_exit = True
        try:
            await serving
        except SystemExit as exc:  # uvicorn exits on startup failure (port taken...)
            raise ConfigError(f"the HTTP server could not start on {settings.host}:{settings.port} "
                              f"(exit {exc.code}); is the port free? See the log above.") from None
