"""/vehicles/{id}/camera.jpg and camera.mjpeg: the latest colour frame of a vehicle, once or as a stream."""

from __future__ import annotations

import asyncio
import time
from typing import Annotated

from fastapi import APIRouter, Path, Query
from fastapi.responses import Response, StreamingResponse

from services.gateway.deps import Authorized, FleetDep, SettingsDep
from services.gateway.errors import ApiError, responses
from services.gateway.fleet import Fleet, Frame

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
                async with fleet.changed:
                    try:
                        await asyncio.wait_for(fleet.changed.wait(), 5.0)
                    except TimeoutError:
                        pass
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
