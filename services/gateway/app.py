"""FastAPI app factory of the gateway: routers under /api/v1, the ground-station page at /, bus + SQLite
in the lifespan."""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles

from services.gateway import errors
from services.gateway.deps import Authorized
from services.gateway.docs import docs_page
from services.gateway.fleet import Fleet
from services.gateway.guard import RequestGuard
from services.gateway.routes import abort, approvals, health, live, tasks, vehicles
from services.gateway.settings import GatewaySettings, check_safe
from services.gateway.store import Store
from shared.bus import Bus

log = logging.getLogger("aermani.gateway")

STATIC = Path(__file__).parent / "static"
API = "/api/v1"

DESCRIPTION = """Start language-driven aerial manipulation tasks, follow the drone's reasoning (DRT/STE) step by
step, watch its camera, and stop it.

**Auth:** with AERMANI_GATEWAY_TOKEN set, every endpoint except `GET /api/v1/live` needs
`Authorization: Bearer <token>`. Without a token (loopback only) requests must address a loopback Host and
state-changing ones must be same-origin JSON. Errors are JSON: `{"error", "detail", "status"}`."""


def create_app(settings: GatewaySettings, bus: Bus | None = None) -> FastAPI:
    """The gateway app. With `bus`, the app uses that session (the service's); without, it opens its own."""
    check_safe(settings)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        own_bus = bus is None
        the_bus = bus or await Bus.open(connect=settings.zenoh_connect, mode=settings.zenoh_mode)
        store = Store(settings.db_path, settings.db_synchronous)
        await store.open()
        fleet = Fleet(the_bus, store)
        try:
            await fleet.start()
            app.state.settings, app.state.store, app.state.fleet = settings, store, fleet
            yield
        finally:
            await fleet.stop()
            await store.close()
            if own_bus:
                await the_bus.close()

    app = FastAPI(title="aermani gateway", version="1.0.0", description=DESCRIPTION, lifespan=lifespan,
                  openapi_url=f"{API}/openapi.json", docs_url=None, redoc_url=None)
    app.state.settings = settings
    errors.install(app)
    # Outermost: refusals and the body cap happen before any route (or CORS) sees the request.
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins, allow_methods=["GET", "POST"],
                           allow_headers=["Authorization", "Content-Type", "Last-Event-ID"])
    app.include_router(live.router, prefix=API)
    for r in (tasks.router, abort.router, health.router, vehicles.router, approvals.router):
        app.include_router(r, prefix=API, dependencies=[Authorized], responses=errors.responses(401))
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    app.add_middleware(RequestGuard, settings=settings)

    @app.get("/docs", include_in_schema=False)
    async def docs() -> HTMLResponse:
        # A plain page rendered from the OpenAPI document: no CDN, no script (the default Swagger UI loads
        # its JavaScript from a CDN, which the CSP forbids and an offline ground station cannot reach).
        return HTMLResponse(docs_page(app.openapi()), headers={"Cache-Control": "no-cache"})

    @app.get("/", include_in_schema=False)
    async def index() -> FileResponse:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})

    return app
