"""JSON error bodies for every failure: our own, Starlette's (404/405) and request validation (422)."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from shared.text import well_formed

log = logging.getLogger("aermani.gateway")

_NAMES = {400: "bad_request", 401: "unauthorized", 403: "forbidden", 404: "not_found", 405: "method_not_allowed",
          406: "not_acceptable", 409: "conflict", 413: "too_large", 415: "unsupported_media_type",
          422: "validation_error", 429: "too_many_requests", 500: "internal_error", 502: "bad_gateway",
          503: "unavailable", 504: "timeout"}


class ApiError(Exception):
    """Raised by routes; becomes `{"error", "detail", "status"}` with its status code."""

    def __init__(self, status: int, detail: str, error: str | None = None,
                 headers: dict[str, str] | None = None) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.error = error or _NAMES.get(status, "error")
        self.headers = headers


def error_response(status: int, detail: str, error: str | None = None, headers: dict[str, str] | None = None,
                   fields: list[dict[str, Any]] | None = None) -> JSONResponse:
    # well_formed: a detail may quote what a client sent, and a lone surrogate in it would fail the response.
    body: dict[str, Any] = {"error": error or _NAMES.get(status, "error"), "detail": well_formed(detail),
                            "status": status}
    if fields is not None:
        body["fields"] = fields
    return JSONResponse(body, status_code=status, headers=headers)


def _field_errors(exc: RequestValidationError) -> list[dict[str, Any]]:
    # Only location, message and type: echoing the input could reflect huge or sensitive values.
    return [{"loc": [str(p) for p in e.get("loc", ())], "msg": str(e.get("msg", "")), "type": str(e.get("type", ""))}
            for e in exc.errors()]


def install(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api(_: Request, exc: ApiError) -> JSONResponse:
        return error_response(exc.status, exc.detail, exc.error, exc.headers)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        if exc.status_code == 404 and detail == "Not Found":
            detail = f"no such resource: {request.method} {request.url.path}; see /docs for the API"
        elif exc.status_code == 405:
            detail = f"{request.method} is not allowed on {request.url.path}; see /docs for the API"
        return error_response(exc.status_code, detail, headers=getattr(exc, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, exc: RequestValidationError) -> JSONResponse:
        fields = _field_errors(exc)
        first = fields[0] if fields else {"loc": [], "msg": "invalid request"}
        where = ".".join(first["loc"]) or "request"
        more = f" (and {len(fields) - 1} more)" if len(fields) > 1 else ""
        return error_response(422, f"invalid {where}: {first['msg']}{more}", fields=fields)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return error_response(500, f"internal error ({type(exc).__name__}); the gateway log has the details")


_DESCRIPTIONS = {401: "Missing or wrong bearer token.", 404: "No such task or vehicle.",
                 409: "Conflict with the current state (a task already runs, or it has ended).",
                 422: "The request is invalid; `detail` and `fields` say what.",
                 502: "The reasoner answered with an error.", 503: "No service on the bus can answer.",
                 504: "The reasoner did not answer in time."}


def responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses=` entry documenting the JSON error body for each status code."""
    from services.gateway.models import ErrorBody

    return {c: {"model": ErrorBody, "description": _DESCRIPTIONS.get(c, _NAMES.get(c, "error"))} for c in codes}
