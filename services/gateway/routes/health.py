"""/health: liveliness of every service per vehicle, link and offboard health, battery."""

from __future__ import annotations

import time

from fastapi import APIRouter

from services.gateway.deps import FleetDep, StoreDep
from services.gateway.fleet import VehicleView
from services.gateway.models import HealthOut, VehicleHealth

router = APIRouter(tags=["health"])


def vehicle_health(v: VehicleView, running: str | None) -> VehicleHealth:
    now = time.time_ns()
    st = v.state
    return VehicleHealth(
        vehicle_id=v.vehicle_id, services=dict(sorted(v.services.items())),
        link_ok=st.link_ok if st else None, offboard_ok=st.offboard_ok if st else None,
        armed=st.armed if st else None, mode=st.mode if st else None,
        battery_remaining=st.battery_remaining if st else None, battery_voltage=st.battery_voltage if st else None,
        state_age_s=(now - v.state_ns) / 1e9 if st else None, state=st,
        camera_age_s=(now - v.frame.receive_ns) / 1e9 if v.frame else None, running_task=running,
        segmenter=v.segmenter, realism=v.realism)


@router.get("/health", response_model=HealthOut, summary="Fleet and gateway health")
async def health(fleet: FleetDep, store: StoreDep) -> HealthOut:
    """Always 200 while the gateway runs; `ok` says whether it can do useful work."""
    db_ok = await store.ping()
    running = {t["vehicle_id"]: t["task_id"] for t in (await store.running_tasks() if db_ok else [])}
    vehicles = [vehicle_health(v, running.get(v.vehicle_id)) for _, v in sorted(fleet.vehicles.items())]
    return HealthOut(ok=db_ok and any(v.services.get("reasoner") for v in vehicles), database=db_ok,
                     vehicles=vehicles)
