"""`Annotated` dependencies of the routes: settings, store, fleet, and the bearer-token check."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from services.gateway.errors import ApiError
from services.gateway.fleet import Fleet
from services.gateway.settings import GatewaySettings
from services.gateway.store import Store

_bearer = HTTPBearer(auto_error=False, description="Token from AERMANI_GATEWAY_TOKEN.")


def get_settings(request: Request) -> GatewaySettings:
    return request.app.state.settings


def get_store(request: Request) -> Store:
    return request.app.state.store


def get_fleet(request: Request) -> Fleet:
    return request.app.state.fleet


SettingsDep = Annotated[GatewaySettings, Depends(get_settings)]
StoreDep = Annotated[Store, Depends(get_store)]
FleetDep = Annotated[Fleet, Depends(get_fleet)]


def require_token(settings: SettingsDep,
                  creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    expected = settings.token_value()
    if expected is None:  # only possible on a loopback bind (check_safe)
        return
    if creds is None:
        raise ApiError(401, "missing bearer token: send `Authorization: Bearer <token>`",
                       headers={"WWW-Authenticate": "Bearer"})
    # Constant time, on bytes so non-ASCII input cannot raise.
    if not hmac.compare_digest(creds.credentials.encode(), expected.encode()):
        raise ApiError(401, "invalid bearer token", headers={"WWW-Authenticate": 'Bearer error="invalid_token"'})


Authorized = Depends(require_token)

UNAUTHORIZED = {401: {"description": "Missing or wrong bearer token."}}
