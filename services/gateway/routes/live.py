"""/live: the one endpoint without a token, for container health checks. Says only that the process serves."""

from __future__ import annotations

from fastapi import APIRouter

router = APIRouter(tags=["health"])


@router.get("/live", summary="Liveness (no token needed)")
async def live() -> dict[str, bool]:
    """200 while the HTTP server runs. Carries nothing else: fleet health is `/health`, behind the token."""
    return {"ok": True}
