"""Base settings shared by every service: vehicle id, Zenoh endpoints, logging. Read from the environment."""

from __future__ import annotations

import logging
import os
import re
from typing import Annotated

from pydantic import AliasChoices, Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from shared.frames import Mount
from shared.keys import DEFAULT_VEHICLE_ID, Keys

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"


class ServiceSettings(BaseSettings):
    """Fields common to all services come from AERMANI_* variables; subclasses set their own env_prefix
    (AERMANI_<NAME>_) for their fields. Built in `main()` and passed down, never read at import time."""

    model_config = SettingsConfigDict(env_prefix="AERMANI_", extra="ignore", populate_by_name=True,
                                      use_attribute_docstrings=True)

    vehicle_id: str = Field(DEFAULT_VEHICLE_ID, validation_alias=AliasChoices("vehicle_id", "AERMANI_VEHICLE_ID"),
                            pattern=r"^[A-Za-z0-9_-]{1,32}$")
    """Vehicle id; the key prefix is aermani/v1/<vehicle_id>/."""
    zenoh_connect: Annotated[list[str], NoDecode] = Field([DEFAULT_ROUTER],
                                     validation_alias=AliasChoices("zenoh_connect", "AERMANI_ZENOH_CONNECT"))
    """Zenoh endpoints to connect to (JSON list or comma-separated), e.g. tcp/127.0.0.1:7447."""
    zenoh_mode: str = Field("client", validation_alias=AliasChoices("zenoh_mode", "AERMANI_ZENOH_MODE"))
    """Zenoh session mode: client (to a router), peer or router."""
    zenoh_certs: str = Field("", validation_alias=AliasChoices("zenoh_certs", "AERMANI_ZENOH_CERTS"))
    """Certificate directory (`aermani certs init`) for `tls/` endpoints in zenoh_connect: a secure router
    accepts only a session with a certificate of its deployment's CA."""
    zenoh_identity: str = Field(
        "client", validation_alias=AliasChoices("zenoh_identity", "AERMANI_ZENOH_IDENTITY"),
        pattern=r"^(client|ground|drone|[a-z][a-z0-9_]{0,31}@[A-Za-z0-9_-]{1,32})$")
    """Whose certificate a `tls/` session presents: client (observes, may abort), ground (commands), drone, or
    a service's own, `<service>@<vehicle>`, which `aermani up --secure` issues to each service it starts."""
    log_level: str = Field("INFO", validation_alias=AliasChoices("log_level", "AERMANI_LOG_LEVEL"))
    """Python log level."""
    crash_backoff_s: float = Field(0.0, ge=0.0, le=600.0,
                                   validation_alias=AliasChoices("crash_backoff_s", "AERMANI_CRASH_BACKOFF_S"))
    """After a crash (a bad setting included), wait before exiting: 0.5 s, doubling with each crash in a row up
    to this many seconds (a run of a minute or more starts over). 0 (default) exits at once, as `aermani up`
    wants (its supervisor backs off itself); compose sets 30, because podman restarts a container at once
    (Docker backs off itself, from 0.1 s). The count lives in the container's /tmp."""
    mount: Mount = Field(default_factory=Mount, validation_alias=AliasChoices("mount"))
    """Camera and gripper mounts on the body: ONE definition for every service (env AERMANI_MOUNT_*)."""

    @field_validator("zenoh_connect", mode="before")
    @classmethod
    def _endpoints(cls, v: object) -> object:
        return parse_endpoints(v) if isinstance(v, str) else v

    @property
    def keys(self) -> Keys:
        return Keys(self.vehicle_id)


_ORIGIN = re.compile(r"https?://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+)(:[0-9]{1,5})?")


def exact_origins(origins: list[str]) -> list[str]:
    """`origins` when each is an exact web origin, `scheme://host[:port]`: a server that checks a browser's
    `Origin` header compares it with these as they are, so a wildcard, a path or a trailing slash (which no
    browser sends) is refused here rather than silently never matching or matching too much."""
    for origin in origins:
        if not _ORIGIN.fullmatch(origin):
            raise ValueError(f"allowed origin {origin!r} is not an exact origin: write scheme://host[:port], "
                             "e.g. http://127.0.0.1:3000 (no wildcard, no path, no trailing slash)")
    return origins


def parse_endpoints(value: str) -> list[str]:
    value = value.strip()
    if value.startswith("["):
        import json

        return list(json.loads(value))
    return [v.strip() for v in value.split(",") if v.strip()]


def setup_logging(level: str = "INFO", name: str = "") -> None:
    fmt = f"%(asctime)s %(levelname)s {name + ' ' if name else ''}%(name)s: %(message)s"
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), format=fmt, force=True)


def env_endpoints() -> list[str]:
    raw = os.environ.get("AERMANI_ZENOH_CONNECT")
    return parse_endpoints(raw) if raw else [DEFAULT_ROUTER]
