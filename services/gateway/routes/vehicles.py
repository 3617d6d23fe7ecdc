"""/vehicles/{id}/camera.jpg and camera.mjpeg: the latest colour frame of a vehicle, once or as a stream."""

from __future__ import annotations

import asyncio
import time
from typing import Annotated

from fastapi import APIRouter, Path, Query
from fastapi.responses import Response, StreamingResponse

from services.gateway.deps import Authorized, FleetDep, SettingsDep
from services.gateway.errors import ApiError, responses
from services.gateway.fleet import Fleet, Frame, VehicleView
from services.gateway.models import DetectionsOut, SkillRunIn, SkillRunOut, SkillsOut
from shared.action import skill_client
from shared.errors import BusError
from shared.keys import Keys
from shared.messages import SkillRequest

router = APIRouter(prefix="/vehicles", tags=["vehicles"])

VehicleId = Annotated[str, Path(pattern=r"^[A-Za-z0-9_-]{1,32}$", examples=["am1"])]
BOUNDARY = "aermaniframe"


def _frame(fleet: Fleet, vehicle_id: str) -> Frame:
    v = fleet.vehicles.get(vehicle_id)
    if v is None:
        raise ApiError(404, f"unknown vehicle {vehicle_id!r}; GET /api/v1/health lists the vehicles")
    if v.frame is None:
        raise ApiError(503, f"no camera frame from {vehicle_id} yet; is the camera (or sim) running?")
    return v.frame


def _view(fleet: Fleet, vehicle_id: str) -> VehicleView:
    v = fleet.vehicles.get(vehicle_id)
    if v is None:
        raise ApiError(404, f"unknown vehicle {vehicle_id!r}; GET /api/v1/health lists the vehicles")
    return v


@router.get("/{vehicle_id}/skills", response_model=SkillsOut, dependencies=[Authorized],
            summary="The vehicle's skill library", responses=responses(401, 404, 422, 503))
async def skills(vehicle_id: VehicleId, fleet: FleetDep) -> SkillsOut:
    """What the executor can do: every skill with its Skill Library text and argument rule; `policy_visible`
    ones are what the model may choose."""
    _view(fleet, vehicle_id)
    try:
        lib = await fleet.bus.query(Keys(vehicle_id).skills, None, timeout=5.0)
    except BusError as exc:
        raise ApiError(503, f"the executor of {vehicle_id} did not answer: {exc}")
    return SkillsOut(vehicle_id=vehicle_id, skills=[s.model_dump(mode="json") for s in lib.skills])


@router.get("/{vehicle_id}/detections", response_model=DetectionsOut, dependencies=[Authorized],
            summary="What perception sees now", responses=responses(401, 404, 422, 503))
async def detections(vehicle_id: VehicleId, fleet: FleetDep) -> DetectionsOut:
    """The newest `perception/detections` of the vehicle: labels, 3D centroids, sizes, confidence."""
    v = _view(fleet, vehicle_id)
    if v.detections is None:
        raise ApiError(503, f"no detections from {vehicle_id} yet; is perception running?")
    return DetectionsOut(vehicle_id=vehicle_id, stamp_ns=v.detections.stamp_ns,
                         items=[d.model_dump(mode="json") for d in v.detections.items])


@router.post("/{vehicle_id}/skills", response_model=SkillRunOut, dependencies=[Authorized],
             summary="Run one skill (off unless AERMANI_GATEWAY_SKILL_API)",
             responses=responses(401, 403, 404, 409, 422, 503, 504))
async def run_skill(vehicle_id: VehicleId, body: SkillRunIn, fleet: FleetDep, settings: SettingsDep) -> SkillRunOut:
    """Run a single skill outside any task and wait for its result. The executor applies its preconditions
    and safety envelope exactly as for the policy. Disabled unless the gateway runs with
    `AERMANI_GATEWAY_SKILL_API=true`."""
    if not settings.skill_api:
        raise ApiError(403, "running single skills is disabled; start a task instead (or set "
                            "AERMANI_GATEWAY_SKILL_API=true on the gateway)")
    _view(fleet, vehicle_id)
    try:
        async with skill_client(fleet.bus, vehicle_id) as client:
            goal = await client.send_goal(SkillRequest(skill=body.skill, argument=body.argument), timeout=5.0)
            if not goal.accepted:
                raise ApiError(409, f"the executor refused {body.skill}: {goal.reason}")
            result = await goal.result(body.timeout_s)
    except BusError as exc:
        raise ApiError(503, f"the executor of {vehicle_id} did not answer: {exc}")
    if result is None:
        raise ApiError(504, f"{body.skill} did not end within {body.timeout_s:.0f} s")
    return SkillRunOut(vehicle_id=vehicle_id, skill=body.skill, state=result.state.value, message=result.message,
                       perceived=result.outcome.perceived)


@router.get("/{vehicle_id}/camera.jpg", dependencies=[Authorized], summary="Latest camera frame (JPEG)",
            response_class=Response, responses={200: {"content": {"image/jpeg": {}},
                                                       "description": "The newest JPEG."},
                                                **responses(401, 404, 422, 503)})
async def camera_jpg(vehicle_id: VehicleId, fleet: FleetDep) -> Response:
    stamp, jpeg = _frame(fleet, vehicle_id).jpeg()
    return Response(jpeg, media_type="image/jpeg",
                    headers={"Cache-Control": "no-store", "X-Frame-Stamp-Ns": str(stamp)})


@router.get("/{vehicle_id}/camera.mjpeg", dependencies=[Authorized], summary="Live camera (MJPEG)",
            response_class=StreamingResponse,
            responses={200: {"content": {f"multipart/x-mixed-replace; boundary={BOUNDARY}": {}},
                             "description": "One JPEG part per new frame, rate-capped."},
                       **responses(401, 404, 422, 503)})
async def camera_mjpeg(vehicle_id: VehicleId, fleet: FleetDep, settings: SettingsDep,
                       frames: Annotated[int | None, Query(ge=1, le=1_000_000,
                                                           description="Stop after this many frames.")] = None,
                       ) -> StreamingResponse:
    """Each new frame as a multipart part, at most `camera_max_fps` per second; endless unless `frames`."""
    _frame(fleet, vehicle_id)
    period = 1.0 / settings.camera_max_fps

    async def parts():
        sent, last_seq = 0, -1
        while frames is None or sent < frames:
            frame = fleet.vehicles[vehicle_id].frame
            if frame is None or frame.seq == last_seq:
                await fleet.changed.wait(5.0)
                if fleet.closing.is_set():
                    return
                continue
            t0 = time.monotonic()
            last_seq = frame.seq
            _, jpeg = frame.jpeg()
            yield (f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n\r\n".encode()
                   + jpeg + b"\r\n")
            sent += 1
            await asyncio.sleep(max(0.0, period - (time.monotonic() - t0)))

    return StreamingResponse(parts(), media_type=f"multipart/x-mixed-replace; boundary={BOUNDARY}",
                             headers={"Cache-Control": "no-store"})
