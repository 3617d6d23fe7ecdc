"""The gateway's request guard (pure ASGI, in front of every route): browser-attack checks, a body size cap,
security headers.

Why each rule exists:
- Without a token (loopback only), a web page the operator visits could POST to 127.0.0.1 (cross-site
  request) or rebind its own DNS name to 127.0.0.1 and read the API (DNS rebinding). So in that mode every
  request must name a loopback Host, and a state-changing request must be JSON (a form or a "simple" fetch
  cannot send that type without a CORS preflight, which we never grant) and, when the browser says where it
  comes from (Origin, Sec-Fetch-Site), come from this very origin.
- With a token, the bearer header is what a cross-site page cannot forge; Origin must still match when sent
  (or be one of AERMANI_GATEWAY_CORS_ORIGINS).
- A body cap stops a client from making the gateway buffer megabytes (a task command is at most 500 chars).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any
from urllib.parse import urlsplit

from services.gateway.settings import GatewaySettings, is_loopback

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

log = logging.getLogger("aermani.gateway.guard")

SAFE_METHODS = {"GET", "HEAD", "OPTIONS"}
# Scripts, styles and images only from the gateway itself; camera frames are blob: URLs; no framing.
CSP = ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; connect-src 'self'; "
       "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'")


def _host_name(host_header: str) -> str:
    """`127.0.0.1:8080` -> 127.0.0.1, `[::1]:8080` -> ::1, `localhost` -> localhost."""
    h = host_header.strip().lower()
    if h.startswith("["):
        return h[1:h.find("]")] if "]" in h else h
    return h.rsplit(":", 1)[0] if h.count(":") == 1 else h


class RequestGuard:
    """ASGI middleware: bearer-token check, CORS origin allow-list, body size limit and security headers."""

    def __init__(self, app: ASGIApp, settings: GatewaySettings) -> None:
        self.app = app
        self.settings = settings
        self.no_token = settings.token is None
        self.max_body = settings.max_body_bytes
        self.allowed_origins = {o.rstrip("/").lower() for o in settings.cors_origins}
        self.headers = [(b"x-content-type-options", b"nosniff"), (b"x-frame-options", b"DENY"),
                        (b"referrer-policy", b"no-referrer"), (b"content-security-policy", CSP.encode()),
                        (b"cross-origin-opener-policy", b"same-origin"),
                        (b"cross-origin-resource-policy", b"same-origin"),
                        (b"permissions-policy", b"camera=(), microphone=(), geolocation=()")]
        if settings.tls_certfile:
            self.headers.append((b"strict-transport-security", b"max-age=31536000"))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        refusal = self.check(scope["method"], headers, scope.get("scheme", "http"))
        if refusal is not None:
            log.warning("refused %s %s (%d): %s", scope["method"], scope.get("path", "")[:200], *refusal)
            await self._error(send, *refusal)
            return
        length = headers.get("content-length")
        if length is not None and (not length.isdigit() or int(length) > self.max_body):
            await self._error(send, 413, f"request body over {self.max_body} bytes (Content-Length {length[:20]})")
            return

        if scope["method"] not in SAFE_METHODS:
            # Bodies are small (a task command is <= 500 characters): read the whole body here, counting, so
            # a chunked upload without Content-Length is capped too, then hand it on in one piece.
            chunks: list[bytes] = []
            size = 0
            while True:
                message = await receive()
                if message["type"] != "http.request":
                    return  # the client went away
                size += len(message.get("body", b""))
                if size > self.max_body:
                    await self._error(send, 413, f"request body over {self.max_body} bytes")
                    return
                chunks.append(message.get("body", b""))
                if not message.get("more_body", False):
                    break
            body = b"".join(chunks)
            delivered = False

            async def replay() -> Message:
                nonlocal delivered
                if not delivered:
                    delivered = True
                    return {"type": "http.request", "body": body, "more_body": False}
                return await receive()

            receive = replay

        async def with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                message.setdefault("headers", [])
                have = {k.lower() for k, _ in message["headers"]}
                message["headers"] = [*message["headers"], *((k, v) for k, v in self.headers if k not in have)]
            await send(message)

        await self.app(scope, receive, with_headers)

    def check(self, method: str, headers: dict[str, str], scheme: str) -> tuple[int, str] | None:
        """(status, reason) when the request must be refused, else None."""
        host = headers.get("host", "")
        if self.no_token and not is_loopback(_host_name(host)):
            return 403, (f"Host {host[:100]!r} is not a loopback name: without a token the gateway answers only "
                         "requests addressed to 127.0.0.1, [::1] or localhost (DNS rebinding guard)")
        origin = headers.get("origin")
        if origin is not None and origin.lower() != "null":
            if not self._same_origin(origin, host, scheme) and origin.rstrip("/").lower() not in self.allowed_origins:
                return 403, (f"cross-origin request from {origin[:100]!r} refused "
                             f"(Origin must match Host {host[:100]!r})")
        elif origin is not None and method not in SAFE_METHODS:
            return 403, "request from an opaque origin (Origin: null) refused"
        if method in SAFE_METHODS or not self.no_token:
            return None  # with a token, the bearer header is what a cross-site page cannot send
        if headers.get("sec-fetch-site", "same-origin") not in ("same-origin", "none"):
            return 403, f"cross-site request refused (Sec-Fetch-Site: {headers['sec-fetch-site'][:40]})"
        ctype = headers.get("content-type", "").split(";", 1)[0].strip().lower()
        if ctype != "application/json":
            return 415, (f"state-changing requests must send Content-Type: application/json (got "
                         f"{ctype[:60] or 'none'!r}); send a JSON body, `{{}}` when there is nothing to say")
        return None

    @staticmethod
    def _same_origin(origin: str, host: str, scheme: str) -> bool:
        parts = urlsplit(origin.strip())
        if parts.scheme not in ("http", "https") or not parts.netloc:
            return False
        # Origin omits default ports; Host may carry them.
        default = {"http": "80", "https": "443"}[parts.scheme]
        o_host = parts.netloc.lower()
        h = host.strip().lower()
        return parts.scheme == scheme and (o_host == h or f"{o_host}:{default}" == h or o_host == f"{h}:{default}")

    async def _error(self, send: Send, status: int, detail: str) -> None:
        from services.gateway.errors import _NAMES

        body = json.dumps({"error": _NAMES.get(status, "error"), "detail": detail, "status": status}).encode()
        await send({"type": "http.response.start", "status": status,
                    "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                                *self.headers]})
        await send({"type": "http.response.body", "body": body})
