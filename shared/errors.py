"""The one error root of aermani; every error says what failed, with which input, and what to do."""

from __future__ import annotations

from typing import Any


class AermaniError(Exception):
    """Root of every error raised on purpose by aermani code."""


class ConfigError(AermaniError):
    """Settings are missing, inconsistent or unsafe; the message says which variable to set."""


class BusError(AermaniError):
    """A Zenoh operation failed (session, publish, query)."""


class QueryTimeout(BusError):
    """A query got no reply within its timeout."""


class NoResponder(BusError):
    """A query found no queryable for its key: the service that should answer is not running."""


class RemoteError(BusError):
    """The queryable answered with an error reply; `.payload` holds its text."""

    def __init__(self, message: str, payload: str = "") -> None:
        super().__init__(message)
        self.payload = payload


class NotFound(AermaniError):
    """A query names something its server does not have (an unknown goal): an error reply, no traceback."""


class ServerLost(BusError):
    """An action's server went away (its liveliness token disappeared) while a goal of it was running."""


class DecodeError(AermaniError):
    """A payload could not be decoded into the expected message type."""


class MavlinkError(AermaniError):
    """MAVLink link or command failure."""


class CameraError(AermaniError):
    """A camera source cannot be configured or opened (missing package, device, file)."""


class PerceptionError(AermaniError):
    """A perception backend could not start or answer."""


class SkillError(AermaniError):
    """A skill was rejected or failed; the message is written for the policy to read."""


class ModelError(AermaniError):
    """A VLM backend failed (transport, timeout, refusal) after its retry budget."""

    calls: tuple[Any, ...] = ()
    """The step's model calls (`ModelCall`s) made before the failure, set by the reasoner loop so the step
    record keeps them (IAR counts their invalid answers)."""
    kind: str = "server"
    """What failed: `refused` (the server answered 400/422 to this request), `schema` (it refused the answer
    schema), `server` (a 5xx after the retry budget) or `unreachable` (connection or timeout)."""


class InvalidAnswer(AermaniError):
    """A model answer that does not name a valid skill with valid arguments."""
