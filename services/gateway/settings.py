"""Settings of the gateway (env AERMANI_GATEWAY_*), with the safety check that refuses unsafe binds."""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Annotated, Literal

from pydantic import AliasChoices, Field, SecretStr, field_validator
from pydantic_settings import NoDecode, SettingsConfigDict

from shared.errors import ConfigError
from shared.settings import ServiceSettings


class GatewaySettings(ServiceSettings):
    """Gateway configuration (AERMANI_GATEWAY_*): bind address, token, CORS, limits and database path."""

    model_config = SettingsConfigDict(env_prefix="AERMANI_GATEWAY_", extra="ignore", populate_by_name=True,
                                      use_attribute_docstrings=True)

    host: str = "127.0.0.1"
    """Address the HTTP server binds; anything but loopback requires a token."""
    port: int = Field(8080, ge=0, le=65535)
    """HTTP port (0 picks a free one, for tests)."""
    db_path: str = "runs/gateway.sqlite3"
    """SQLite file that keeps tasks, steps and skill statuses across restarts (`:memory:` for none)."""
    db_synchronous: Literal["NORMAL", "FULL"] = "NORMAL"
    """SQLite durability: NORMAL keeps every committed write across a killed gateway; FULL also across an OS
    crash or power loss (one fsync per write)."""
    token: SecretStr | None = Field(None, validation_alias=AliasChoices("token", "AERMANI_GATEWAY_TOKEN"))
    """Bearer token required by every /api/v1 endpoint except the liveness check /api/v1/live. Optional only
    on a loopback bind (then browser requests are checked for Host, Origin and JSON instead). Never logged or
    returned."""
    cors_origins: Annotated[list[str], NoDecode] = []
    """Origins allowed by CORS (JSON list or comma-separated); empty keeps CORS closed."""
    start_timeout_s: float = Field(10.0, gt=0)
    """How long to wait for the reasoner to accept or refuse a task."""
    abort_ack_timeout_s: float = Field(2.0, ge=0)
    """How long an abort request waits for the executor's acknowledgement before answering anyway."""
    camera_max_fps: float = Field(10.0, gt=0, le=60)
    """Frame rate cap of the MJPEG stream."""
    sse_ping_s: float = Field(15.0, gt=0)
    """Keep-alive comment interval on the event stream, seconds."""
    page_size_max: int = Field(100, ge=1, le=1000)
    """Largest page GET /tasks returns."""
    skill_api: bool = False
    """Allow POST /vehicles/{id}/skills (run one skill outside a task, through the executor's envelope).
    Off by default: operators and agents drive tasks, not single motions."""
    max_body_bytes: int = Field(65536, ge=1024, le=16 * 1024 * 1024)
    """Largest request body accepted; bigger ones get 413 before they are read."""
    tls_certfile: str | None = None
    """PEM certificate (chain) for HTTPS; with tls_keyfile the gateway serves https:// only."""
    tls_keyfile: str | None = None
    """PEM private key of tls_certfile."""

    @field_validator("cors_origins", mode="before")
    @classmethod
    def _origins(cls, v: object) -> object:
        if isinstance(v, str):
            v = v.strip()
            if v.startswith("["):
                import json

                return list(json.loads(v))
            return [o.strip() for o in v.split(",") if o.strip()]
        return v

    @field_validator("token", mode="before")
    @classmethod
    def _empty_token(cls, v: object) -> object:
        return None if isinstance(v, str) and not v.strip() else v

    def token_value(self) -> str | None:
        return self.token.get_secret_value() if self.token is not None else None


def is_loopback(host: str) -> bool:
    if host in ("localhost", "ip6-localhost"):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_safe(settings: GatewaySettings) -> None:
    """Refuse a bind that anyone on the network could reach without a token."""
    if not is_loopback(settings.host) and settings.token is None:
        raise ConfigError(
            f"refusing to serve on {settings.host}:{settings.port} without a token: anyone on the network could "
            "start tasks and abort the vehicle. Set AERMANI_GATEWAY_TOKEN (e.g. `openssl rand -hex 32`) or bind "
            "AERMANI_GATEWAY_HOST=127.0.0.1.")
    if settings.token is not None and len(settings.token.get_secret_value()) < 8:
        raise ConfigError("AERMANI_GATEWAY_TOKEN is shorter than 8 characters; use a long random token.")
    if bool(settings.tls_certfile) != bool(settings.tls_keyfile):
        raise ConfigError("set both AERMANI_GATEWAY_TLS_CERTFILE and AERMANI_GATEWAY_TLS_KEYFILE, or neither")
    for path in (settings.tls_certfile, settings.tls_keyfile):
        if path and not Path(path).is_file():
            raise ConfigError(f"TLS file {path} does not exist (AERMANI_GATEWAY_TLS_CERTFILE/_KEYFILE)")
