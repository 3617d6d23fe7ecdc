"""/abort: stop every vehicle at once."""

from __future__ import annotations

from fastapi import APIRouter

from services.gateway.deps import Authorized, FleetDep, SettingsDep
from services.gateway.errors import ApiError, responses
from services.gateway.models import AbortIn, AbortOut, abort_summary

router = APIRouter(tags=["abort"])


@router.post("/abort", status_code=202, response_model=AbortOut, dependencies=[Authorized],
             summary="Abort on every vehicle (or one)", responses=responses(401, 404, 422, 503))
async def abort_all(fleet: FleetDep, settings: SettingsDep, body: AbortIn | None = None) -> AbortOut:
    """Publish an abort to every vehicle seen on the bus (or to `vehicle_id` only): executors hold, reasoners
    end their tasks."""
    req = body or AbortIn()
    vehicles = sorted(v.vehicle_id for v in fleet.vehicles.values() if any(v.services.values()) or v.state)
    if req.vehicle_id is not None:
        if req.vehicle_id not in vehicles:
            raise ApiError(404, f"vehicle {req.vehicle_id!r} is not on the bus; GET /api/v1/health lists them")
        vehicles = [req.vehicle_id]
    if not vehicles:
        raise ApiError(503, "no vehicle is on the bus: nothing to abort")
    reason = req.reason
    acked = await fleet.abort(vehicles, reason, None, settings.abort_ack_timeout_s,
                              fleet_wide=req.vehicle_id is None)
    return AbortOut(vehicles=vehicles, acknowledged=sorted(acked), messages=abort_summary(acked), services=acked)
