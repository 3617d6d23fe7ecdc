"""The asyncio wrapper over zenoh-python 1.x that every service uses; services never touch zenoh directly.

zenoh-python is synchronous and calls back on its own threads. A subscription's callback only copies the
sample's bytes into the subscription's bounded queue and, when a consumer is waiting and no wake-up is
already on its way, wakes the event loop with one `loop.call_soon_threadsafe`: a burst of samples costs
one hand-off, not one per sample. Decoding happens on the consumer side, so a malformed payload is logged,
counted and dropped without touching the subscriber. A payload that names a vehicle (`vehicle_id`) is also
checked against its key's vehicle (`aermani/v1/<vehicle_id>/...`): a state, step or status of another vehicle is
refused the same way (see `check_vehicle`), on subscriptions, requests and replies alike.

Queue policy: each subscription has one bounded queue. When it is full, `overflow="drop_oldest"`
(the default, right for sensor streams and state: the newest sample wins) discards the oldest queued
sample; `overflow="drop_newest"` discards the arriving one. Either way the discarded sample is counted
in `Subscription.dropped`, never silently lost. `overflow="latest"` is for latest-value consumers (the
newest vehicle state, depth frame or detections is all they read): it discards the oldest like
`drop_oldest`, but counts it in `Subscription.superseded`, since a value replaced by a newer one of the same
stream is what such a consumer asks for, not a lost message. Publishers use CongestionControl.BLOCK by default so the
network layer itself does not drop (`reliable=False` selects DROP + express, for frames where late is
worse than lost).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import math
import os
import threading
import time
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from typing import Any, Generic, Literal, TypeVar, overload

import zenoh
from pydantic import BaseModel, TypeAdapter, ValidationError
from pydantic_core import PydanticSerializationError

from shared.errors import BusError, DecodeError, NoResponder, NotFound, QueryTimeout, RemoteError
from shared.keys import (
    FLEET_ID,
    ROOT,
    BoundQuery,
    BoundToken,
    BoundTopic,
    Json,
    Protobuf,
    max_bytes_of,
    schema_name,
)
from shared.messages import SCHEMA_MINOR, SCHEMA_VERSION, Health
from shared.text import well_formed_tree

QUERY_CONCURRENCY = 64
"""Requests one queryable serves at once; beyond that a request gets a "busy" error reply at once."""
ZENOH_TIMEOUT = b"Timeout"
"""The payload of the error reply Zenoh itself gives a query whose deadline passed without an answer."""

log = logging.getLogger("aermani.bus")

T = TypeVar("T")
Req = TypeVar("Req")
Rep = TypeVar("Rep")
Overflow = Literal["drop_oldest", "drop_newest", "latest"]

_ENC_JSON = zenoh.Encoding.APPLICATION_JSON
_ENC_PROTOBUF = zenoh.Encoding.APPLICATION_PROTOBUF
_ENC_BYTES = zenoh.Encoding.ZENOH_BYTES

_zenoh_log_initialised = False


def _init_zenoh_log() -> None:
    global _zenoh_log_initialised
    if not _zenoh_log_initialised:
        with contextlib.suppress(Exception):
            zenoh.init_log_from_env_or("error")
        _zenoh_log_initialised = True


def zenoh_config(mode: str = "client", connect: list[str] | tuple[str, ...] = (),
                 listen: list[str] | tuple[str, ...] = (), multicast: bool = False,
                 connect_timeout_s: float | None = None, shared_memory: bool = True) -> zenoh.Config:
    """A Zenoh config with explicit endpoints and multicast scouting off by default.

    Clients wait for their router forever by default (services may start before it); a command-line tool
    passes `connect_timeout_s` to fail with a clear message instead. `shared_memory` (on; stated here rather
    than left to zenoh's default): between sessions on one host, zenoh's transport puts every message above
    3 KiB (frames, not the small messages) into a shared-memory pool and sends only a reference, through the
    router too; a link to another host, or a peer without it, gets the bytes as usual."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(multicast))
    cfg.insert_json5("transport/shared_memory/enabled", json.dumps(shared_memory))
    if connect:
        cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if listen:
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if mode == "client":
        timeout_ms = -1 if connect_timeout_s is None else int(connect_timeout_s * 1000)
        cfg.insert_json5("connect/timeout_ms", json.dumps(timeout_ms))
    return cfg


def tls_client_config(connect: list[str], certs: str | None = None, identity: str | None = None,
                      connect_timeout_s: float | None = None) -> zenoh.Config:
    """A client config for `tls/` endpoints with the certificate of `identity` in `certs` (defaults from
    AERMANI_ZENOH_CERTS / AERMANI_ZENOH_IDENTITY), or a BusError saying how to give one."""
    from shared.errors import ConfigError
    from shared.security import client_config

    certs = certs or os.environ.get("AERMANI_ZENOH_CERTS", "")
    identity = identity or os.environ.get("AERMANI_ZENOH_IDENTITY", "") or "client"
    if not certs:
        raise BusError(f"{connect} is a mutual-TLS router: it needs a client certificate. Pass "
                       "`aermani --client-certs DIR [--identity client|ground] ...` or set AERMANI_ZENOH_CERTS "
                       "(a directory from `aermani certs init`)")
    try:
        return client_config(certs, identity, connect, connect_timeout_s=connect_timeout_s)
    except ConfigError as exc:
        raise BusError(str(exc)) from exc


def _fail(fut: asyncio.Future[zenoh.Session], exc: BaseException) -> None:
    if not fut.done():
        fut.set_exception(exc)


def _deliver(fut: asyncio.Future[zenoh.Session], session: zenoh.Session) -> None:
    if fut.done():  # the waiter gave up (stop during the wait): nobody will close it otherwise
        session.close()  # type: ignore[no-untyped-call]
    else:
        fut.set_result(session)


async def _open_in_daemon_thread(cfg: zenoh.Config) -> zenoh.Session:
    """zenoh.open blocks while a client waits for its router. A daemon thread (not the loop's executor)
    lets a SIGTERM during that wait cancel us and exit: asyncio.run would otherwise join the thread."""
    loop = asyncio.get_running_loop()
    fut: asyncio.Future[zenoh.Session] = loop.create_future()

    def work() -> None:
        try:
            session = zenoh.open(cfg)
        except BaseException as exc:  # handed to the waiting coroutine
            if not loop.is_closed():
                loop.call_soon_threadsafe(_fail, fut, exc)
            return
        if loop.is_closed():
            session.close()  # type: ignore[no-untyped-call]
            return
        loop.call_soon_threadsafe(_deliver, fut, session)

    threading.Thread(target=work, name="zenoh-open", daemon=True).start()
    return await fut


# --------------------------------------------------------------------------- encoding


def schema_of(obj: Any) -> str:
    if isinstance(obj, BaseModel):
        fn = getattr(type(obj), "full_schema_name", None)
        return fn() if fn else f"aermani.{type(obj).__name__}"
    return ""


@functools.lru_cache(maxsize=256)
def _encoding(base: str, schema: str) -> zenoh.Encoding:
    """Encodings are immutable: build each (base, schema) once instead of per sample."""
    enc = {"json": _ENC_JSON, "protobuf": _ENC_PROTOBUF}[base]
    return enc.with_schema(schema) if schema else enc


def _json_null(value: Any) -> Any:
    """inf and nan as null, as pydantic's JSON writes them."""
    return None if isinstance(value, float) and not math.isfinite(value) else value


def _well_formed_json(obj: BaseModel) -> bytes:
    """JSON of a model holding a lone surrogate (half an emoji a model or an HTTP client sent as `\\ud83d`,
    which UTF-8 cannot encode): the surrogate replaced by U+FFFD, so a message is never lost to the text a peer
    put in it."""
    tree = well_formed_tree(obj.model_dump(mode="json"), _json_null)
    return json.dumps(tree, ensure_ascii=False, separators=(",", ":")).encode()


def encode(obj: Any, schema: str | None = None) -> tuple[bytes, zenoh.Encoding]:
    """Model -> JSON bytes with `application/json;aermani.<Model>`; protobuf message -> bytes with
    `application/protobuf;<full name>`; bytes pass through (not copied) with the given schema (protobuf if
    it names a foxglove type)."""
    if isinstance(obj, BaseModel):
        try:  # the serializer's bytes as they are (model_dump_json would decode them to str for us to re-encode)
            data = obj.__pydantic_serializer__.to_json(obj)
        except PydanticSerializationError:
            data = _well_formed_json(obj)
        return data, _encoding("json", schema or schema_of(obj))
    if hasattr(obj, "SerializeToString") and hasattr(obj, "DESCRIPTOR"):
        return obj.SerializeToString(), _encoding("protobuf", obj.DESCRIPTOR.full_name)
    if isinstance(obj, bytes | bytearray | memoryview):
        data = obj if isinstance(obj, bytes) else bytes(obj)
        if schema and schema.startswith("foxglove."):
            return data, _encoding("protobuf", schema)
        if schema:
            return data, _encoding("json", schema)
        return data, _ENC_BYTES
    if isinstance(obj, dict | list | str | int | float | bool) or obj is None:
        return json.dumps(obj).encode(), _ENC_JSON.with_schema(schema) if schema else _ENC_JSON
    raise TypeError(f"cannot encode {type(obj).__name__} for the bus")


_warned_minor: set[tuple[str, str]] = set()


def _is_raw(model: Any) -> bool:
    return model is None or isinstance(model, Protobuf)


class _Decoder(Generic[T]):
    """Bytes -> the declared type, with the versioning rule of `shared.messages`: a message of a newer minor
    version may carry fields this receiver does not know (they are dropped, logged once per field); a
    message of a newer major version is rejected with an error naming both versions."""

    def __init__(self, model: Any) -> None:
        self.model = model
        self.name = getattr(model, "__name__", str(model))
        self.json = isinstance(model, Json)
        self.adapter = None if _is_raw(model) or self.json else TypeAdapter(model)

    def __call__(self, data: bytes) -> T:
        if self.adapter is None:
            if self.json:
                try:
                    return json.loads(data) if data else None  # type: ignore[return-value]
                except ValueError as exc:
                    raise DecodeError(f"invalid JSON for {self.name}: {exc}") from exc
            return data  # type: ignore[return-value]
        try:
            value = self.adapter.validate_json(data)
        except ValidationError as exc:
            value = self._newer_minor(data, exc)
        major = getattr(value, "schema_version", SCHEMA_VERSION)
        if major > SCHEMA_VERSION:
            raise DecodeError(f"{self.name} of schema version {major}.{getattr(value, 'schema_minor', 0)} "
                              f"cannot be read by this receiver (version {SCHEMA_VERSION}.{SCHEMA_MINOR}); "
                              "upgrade aermani on this side")
        return value  # type: ignore[no-any-return]

    def _newer_minor(self, data: bytes, exc: ValidationError) -> Any:
        errors = exc.errors()
        try:
            doc = json.loads(data)
        except ValueError:
            doc = None
        if isinstance(doc, dict):
            major = doc.get("schema_version", SCHEMA_VERSION)
            minor = doc.get("schema_minor", 0)
            if isinstance(major, int) and major > SCHEMA_VERSION:
                raise DecodeError(f"{self.name} of schema version {major}.{minor} cannot be read by this "
                                  f"receiver (version {SCHEMA_VERSION}.{SCHEMA_MINOR}); upgrade aermani on "
                                  "this side") from exc
            extra = [e["loc"] for e in errors if e.get("type") == "extra_forbidden"]
            newer = isinstance(minor, int) and major == SCHEMA_VERSION and minor > SCHEMA_MINOR
            if newer and extra and len(extra) == len(errors):
                for loc in extra:
                    _drop_path(doc, loc)
                    field = ".".join(str(p) for p in loc)
                    if (self.name, field) not in _warned_minor:
                        _warned_minor.add((self.name, field))
                        log.info("%s from schema version %s.%s carries field %r unknown to version %s.%s: "
                                 "ignored", self.name, major, minor, field, SCHEMA_VERSION, SCHEMA_MINOR)
                try:
                    return self.adapter.validate_python(doc)  # type: ignore[union-attr]
                except ValidationError as again:
                    exc = again
                    errors = again.errors()
        loc = errors[0].get("loc", ()) if errors else ()
        msg = errors[0].get("msg", str(exc)) if errors else str(exc)
        where = ".".join(str(p) for p in loc) or "payload"
        raise DecodeError(f"invalid {self.name} at {where}: {msg}") from exc


def _drop_path(doc: Any, loc: tuple[Any, ...]) -> None:
    """Remove the value at `loc` (a pydantic error location; union tags are skipped) from a JSON document."""
    node = doc
    for i, part in enumerate(loc):
        last = i == len(loc) - 1
        if isinstance(node, dict) and part in node:
            if last:
                node.pop(part, None)
                return
            node = node[part]
        elif isinstance(node, list) and isinstance(part, int) and part < len(node):
            node = node[part]
        # else: a union member tag in the location path; stay on this node


def decoder(model: Any) -> Callable[[bytes], Any]:
    return _Decoder(model)


def key_vehicle(key: str) -> str | None:
    """The vehicle segment of an aermani key (`aermani/v1/am2/autopilot/state` -> "am2"; FLEET_ID for a fleet
    key), or None for a key outside `aermani/v1/`."""
    parts = str(key).split("/", 3)
    if len(parts) < 4 or f"{parts[0]}/{parts[1]}" != ROOT:
        return None
    return parts[2]


def check_vehicle(key: str, value: Any) -> None:
    """Raise DecodeError when `value` names a vehicle (`vehicle_id`) other than the one its key is under: a
    vehicle's state, step or task status published on another vehicle's key would be taken for that vehicle's.
    A fleet key (`aermani/v1/fleet/...`) carries what addresses every vehicle (the fleet abort, which names none):
    a payload naming one vehicle does not belong there and is refused too. Keys outside `aermani/v1/` and
    payloads without a vehicle id are not checked."""
    claimed = getattr(value, "vehicle_id", None)
    if not isinstance(claimed, str):
        return
    vehicle = key_vehicle(key)
    if vehicle is None or claimed == vehicle:
        return
    where = "a fleet-wide key" if vehicle == FLEET_ID else f"a key of vehicle {vehicle!r}"
    raise DecodeError(f"{type(value).__name__} of vehicle {claimed!r} on {where} ({key}): its vehicle_id must be "
                      "its key's vehicle")


def _accepted_types(decl_type: Any) -> tuple[type, ...]:
    """The classes `_check_type` accepts by isinstance alone, so a publish checks a value with one isinstance
    (a protobuf message object, checked by its descriptor, still goes through `_check_type`)."""
    if isinstance(decl_type, Protobuf):
        return (bytes, bytearray, memoryview)
    if isinstance(decl_type, Json):
        return (dict, list)
    if isinstance(decl_type, type):
        return (decl_type,)
    args: tuple[Any, ...] = getattr(decl_type, "__args__", ())
    inner = args[0] if args and getattr(decl_type, "__metadata__", None) else decl_type
    members = getattr(inner, "__args__", (inner,))
    return tuple(m for m in members if isinstance(m, type))


def _check_type(decl_type: Any, obj: Any, key: str) -> None:
    """Refuse to publish a value of another type than the key declares (a programming error)."""
    if isinstance(decl_type, Protobuf):
        ok = isinstance(obj, bytes | bytearray | memoryview) or (
            hasattr(obj, "DESCRIPTOR") and obj.DESCRIPTOR.full_name == decl_type.full_name)
    elif isinstance(decl_type, Json):
        ok = isinstance(obj, dict | list)
    elif isinstance(decl_type, type):
        ok = isinstance(obj, decl_type)
    else:  # a union (possibly Annotated)
        args: tuple[Any, ...] = getattr(decl_type, "__args__", ())
        inner = args[0] if args and getattr(decl_type, "__metadata__", None) else decl_type
        ok = isinstance(obj, tuple(getattr(inner, "__args__", (inner,))))
    if not ok:
        raise TypeError(f"{key} carries {getattr(decl_type, '__name__', decl_type)}, not {type(obj).__name__}")


@dataclass(frozen=True)
class Caller:
    """Who sent a query, as the querier's attachment claims it: its service name and Zenoh session id.
    Not authenticated by itself (the routers' access control decides who may query at all); logged so that
    every command can be traced to a session."""

    sender: str = "unknown"
    zid: str = ""

    @classmethod
    def from_attachment(cls, data: bytes | None) -> Caller:
        if not data:
            return cls("unknown (no attachment)")
        def clean(v: object) -> str:  # the text goes into logs: no newlines or control characters
            return "".join(c for c in str(v)[:64] if c.isprintable())

        try:
            obj = json.loads(data)
            return cls(clean(obj.get("sender", "unknown")), clean(obj.get("zid", "")))
        except (ValueError, AttributeError):
            return cls(f"unknown (attachment {bytes(data[:32])!r})")

    def __str__(self) -> str:
        return f"{self.sender} (zid {self.zid or '?'})"


# --------------------------------------------------------------------------- subscription


@dataclass
class Received(Generic[T]):
    """A decoded sample with its metadata."""

    key: str
    value: T
    payload: bytes
    encoding: str
    receive_ns: int


def _handler_failed(query: zenoh.Query, key: str, exc: Exception) -> None:
    """An exception in a queryable's handler becomes an error reply; NotFound is an answer (an unknown goal),
    anything else a failure, logged with its traceback."""
    if isinstance(exc, NotFound):
        query.reply_err(json.dumps({"error": str(exc)}).encode())
        return
    log.error("handler for %s failed", key, exc_info=exc)
    query.reply_err(json.dumps({"error": f"{type(exc).__name__}: {exc}"}).encode())


@dataclass(frozen=True)
class RawReply:
    """A queryable's reply sent as it is: bytes with an exact encoding and an attachment (another protocol's
    reply on the same router, e.g. a ROS 2 service response over rmw_zenoh)."""

    data: bytes
    encoding: str
    attachment: bytes | None = None


def _reply(query: zenoh.Query, key: str, result: Any) -> None:
    """A handler's return value as the query's reply: a RawReply verbatim, anything else encoded."""
    if isinstance(result, RawReply):
        query.reply(key, result.data, encoding=zenoh.Encoding(result.encoding), attachment=result.attachment)
    else:
        payload, enc = encode(result)
        query.reply(key, payload, encoding=enc)


class RateLimitedWarning:
    """A warning logged at most once per `period_s` per source, with the count of those it held back."""

    def __init__(self, period_s: float = 10.0) -> None:
        self.period_s = period_s
        self._last = -math.inf
        self._held = 0

    def __call__(self, msg: str, *args: Any) -> None:
        now = time.monotonic()
        if now - self._last < self.period_s:
            self._held += 1
            return
        if self._held:
            msg += f" ({self._held} more like it in the last {self.period_s:.0f} s)"
        self._held, self._last = 0, now
        log.warning(msg, *args)


def _expire(fut: asyncio.Future[bool]) -> None:
    if not fut.done():
        fut.set_result(False)


class Subscription(Generic[T]):
    """A bounded async queue of decoded samples from one key expression."""

    def __init__(self, bus: Bus, key: str, model: Any, maxsize: int, overflow: Overflow,
                 max_bytes: int | None = None) -> None:
        self.bus = bus
        self.key = key
        self._decode = decoder(model)
        self._maxsize = maxsize
        self._overflow = overflow
        self.max_bytes = max_bytes_of(model, max_bytes)
        self.dropped = 0
        """Samples lost to a full queue or hand-off (the consumer is too slow)."""
        self.superseded = 0
        """With `overflow="latest"`: older samples replaced by a newer one before the consumer read them."""
        self.malformed = 0
        self.oversize = 0
        """Samples larger than `max_bytes`, dropped before they were copied."""
        self.received = 0
        self._warn = RateLimitedWarning()
        self._sub: Any = None
        self._closed = False
        # The one bounded buffer between zenoh's threads and the consumer: the callback appends (applying the
        # overflow policy at once), the consumer pops on the loop. The loop is woken only when a consumer waits,
        # once per burst (no call_soon_threadsafe while one is already scheduled), never once per sample.
        self._items: deque[tuple[str, bytes, str, int]] = deque()
        self._lock = threading.Lock()
        self._waiters: list[asyncio.Future[bool]] = []
        self._wake_scheduled = False

    def _on_sample(self, sample: zenoh.Sample) -> None:  # runs on a zenoh thread
        payload = sample.payload
        size = len(payload)
        if size > self.max_bytes:
            self.oversize += 1
            self._warn("dropped a %d-byte sample on %s: larger than its %d-byte cap", size, sample.key_expr,
                       self.max_bytes)
            return
        item = (str(sample.key_expr), payload.to_bytes(), str(sample.encoding), time.time_ns())
        with self._lock:
            self.received += 1
            if len(self._items) >= self._maxsize:
                self._discard()
                if self._overflow == "drop_newest":
                    return
                self._items.popleft()
            self._items.append(item)
            if not self._waiters or self._wake_scheduled:
                return
            self._wake_scheduled = True
        self.bus._to_loop(self._wake)

    def _discard(self) -> None:
        if self._overflow == "latest":
            self.superseded += 1
        else:
            self.dropped += 1

    def _wake(self) -> None:  # runs on the loop
        with self._lock:
            self._wake_scheduled = False
            waiters, self._waiters = self._waiters, []
        for fut in waiters:
            if not fut.done():
                fut.set_result(True)

    def _pop(self) -> tuple[str, bytes, str, int] | None:  # runs on the loop
        with self._lock:
            return self._items.popleft() if self._items else None

    async def _wait(self, deadline: float | None) -> None:
        """Until a sample is queued (returns at once if one is). Raises TimeoutError after `deadline`."""
        loop = self.bus.loop
        fut: asyncio.Future[bool] = loop.create_future()
        with self._lock:
            if self._items:
                return
            self._waiters.append(fut)
        timer = None
        if deadline is not None:
            timer = loop.call_later(max(0.0, deadline - time.monotonic()), _expire, fut)
        try:
            if not await fut:
                raise TimeoutError(f"no sample on {self.key} in time")
        finally:
            if timer is not None:
                timer.cancel()
            with self._lock, contextlib.suppress(ValueError):
                self._waiters.remove(fut)

    def _value(self, key: str, data: bytes) -> T:
        """The sample decoded to its declared type and checked against its key's vehicle (DecodeError if not)."""
        value: T = self._decode(data)
        check_vehicle(key, value)
        return value

    async def recv_sample(self, timeout: float | None = None) -> Received[T]:
        """Next valid sample (malformed ones are logged and skipped). Raises TimeoutError."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            item = self._pop()
            if item is None:
                await self._wait(deadline)
                continue
            key, data, enc, rns = item
            try:
                value = self._value(key, data)
            except DecodeError as exc:
                self.malformed += 1
                self._warn("dropped malformed sample on %s: %s", key, exc)
                continue
            return Received(key, value, data, enc, rns)

    async def recv(self, timeout: float | None = None) -> T:
        return (await self.recv_sample(timeout)).value

    def recv_nowait(self) -> T | None:
        """The next valid queued sample, or None when the queue is empty (never waits)."""
        while (item := self._pop()) is not None:
            try:
                return self._value(item[0], item[1])
            except DecodeError as exc:
                self.malformed += 1
                self._warn("dropped malformed sample on %s: %s", item[0], exc)
        return None

    def latest_nowait(self) -> T | None:
        """Drain the queue and return the newest valid sample, or None."""
        newest = None
        while (value := self.recv_nowait()) is not None:
            newest = value
        return newest

    def __aiter__(self) -> AsyncIterator[T]:
        return self._iter()

    async def _iter(self) -> AsyncIterator[T]:
        while not self._closed:
            yield await self.recv()

    def qsize(self) -> int:
        return len(self._items)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self.bus._undeclare(self._sub)
            with contextlib.suppress(ValueError):
                self.bus._subscriptions.remove(self)


# --------------------------------------------------------------------------- the bus


@dataclass(frozen=True)
class _Route:
    """A declared topic as this bus publishes it: its key, schema, accepted types and default publisher."""

    decl: Any
    key: str
    schema: str | None
    types: tuple[type, ...]
    publisher: Any


class Bus:
    """One Zenoh session bound to one asyncio loop. Create with `await Bus.open(...)`."""

    def __init__(self, session: zenoh.Session, loop: asyncio.AbstractEventLoop) -> None:
        self.session = session
        self.loop = loop
        self._publishers: dict[tuple[str, bool], Any] = {}
        self._declared: list[Any] = []
        self._tasks: set[asyncio.Task[None]] = set()
        self._closed = False
        self._lock = threading.Lock()
        self._subscriptions: list[Subscription[Any]] = []
        self._watches: dict[int, Any] = {}  # id(queue) -> its liveliness subscriber, for unwatch_liveliness
        self._refused_queries = 0
        self._routes: dict[tuple[str, int], _Route] = {}
        self.name = ""
        """This service's name, sent with every query so queryables can log who asked (see Caller)."""

    # ---- lifecycle

    @classmethod
    async def open(cls, connect: list[str] | tuple[str, ...] = ("tcp/127.0.0.1:7447",), mode: str = "client",
                   listen: list[str] | tuple[str, ...] = (), config: zenoh.Config | None = None,
                   connect_timeout_s: float | None = None, certs: str | None = None,
                   identity: str | None = None) -> Bus:
        """A session on `connect`. A `tls/` endpoint (a secure deployment's router) needs a client certificate:
        `certs` (a directory from `aermani certs init`) and `identity` (ground, drone or client), by default
        AERMANI_ZENOH_CERTS and AERMANI_ZENOH_IDENTITY (client), which `aermani --client-certs` sets."""
        _init_zenoh_log()
        if config is None and any(e.startswith("tls/") for e in connect):
            config = tls_client_config(list(connect), certs, identity, connect_timeout_s)
        cfg = config or zenoh_config(mode=mode, connect=connect, listen=listen, connect_timeout_s=connect_timeout_s)
        try:
            session = await _open_in_daemon_thread(cfg)
        except Exception as exc:  # zenoh raises ZError
            raise BusError(f"could not open a Zenoh {mode} session (connect={list(connect)}, "
                           f"listen={list(listen)}): {exc}. Is the router running?") from exc
        return cls(session, asyncio.get_running_loop())

    async def close(self) -> None:
        """Undeclare everything, then close the session (in that order: avoids the known close hangs)."""
        if self._closed:
            return
        self._closed = True
        for t in list(self._tasks):
            t.cancel()
        for obj in reversed(self._declared):
            with contextlib.suppress(Exception):
                obj.undeclare()
        self._declared.clear()
        for pub in self._publishers.values():
            with contextlib.suppress(Exception):
                pub.undeclare()
        self._publishers.clear()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(asyncio.to_thread(self.session.close), 5.0)

    async def __aenter__(self) -> Bus:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def _undeclare(self, obj: Any) -> None:
        if obj is None:
            return
        with contextlib.suppress(Exception):
            obj.undeclare()
        with contextlib.suppress(ValueError):
            self._declared.remove(obj)

    def _to_loop(self, fn: Callable[..., Any], *args: Any) -> None:
        """Called on zenoh threads: hand over to the loop, ignore a loop that has closed."""
        if self._closed:
            return
        with contextlib.suppress(RuntimeError):
            self.loop.call_soon_threadsafe(fn, *args)

    # ---- pub/sub

    def _publisher(self, key: str, reliable: bool) -> Any:
        pub = self._publishers.get((key, reliable))
        if pub is None:
            pub = self.session.declare_publisher(
                key,
                congestion_control=zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP,
                express=not reliable,
            )
            self._publishers[(key, reliable)] = pub
        return pub

    def publish(self, target: BoundTopic[T] | str, obj: T, *, reliable: bool | None = None,
                attachment: bytes | None = None, schema: str | None = None) -> None:
        """Publish on a declared topic (its type and schema come from the declaration), or on a plain key
        expression (`schema` names the payload). Non-blocking in practice: BLOCK only waits when the
        transmission queue is full."""
        if self._closed:
            raise BusError(f"publish on {target} after the bus was closed")
        if isinstance(target, BoundTopic):
            route = self._routes.get((target, id(target.decl)))
            if route is None or route.decl is not target.decl:
                route = self._route(target)
            if not isinstance(obj, route.types):
                _check_type(target.decl.type, obj, target.key)
            schema = route.schema
            pub = route.publisher if reliable is None or reliable == target.decl.reliable else \
                self._publisher(route.key, reliable)
        else:
            pub = self._publisher(target, True if reliable is None else reliable)
        if isinstance(obj, Health) and "bus" not in obj.details:
            obj = self._with_bus_counters(obj)
        data, enc = encode(obj, schema)
        pub.put(data, encoding=enc, attachment=attachment)

    def _route(self, target: BoundTopic[Any]) -> _Route:
        """What a publish on a declared topic needs, resolved once per key and declaration."""
        if len(self._routes) > 4096:  # topics bound with ever new declarations: keep the cache bounded
            self._routes.clear()
        decl = target.decl
        route = _Route(decl, target.key, schema_name(decl.type), _accepted_types(decl.type),
                       self._publisher(target.key, decl.reliable))
        self._routes[(target.key, id(decl))] = route
        return route

    def _with_bus_counters(self, health: Any) -> Any:
        """A service's health carries its bus counters once anything was dropped, malformed, oversize or
        refused: those show without each service having to report them (superseded latest values alone do
        not count)."""
        if not self._refused_queries and not any(s.dropped or s.malformed or s.oversize
                                                 for s in self._subscriptions):
            return health
        stats = self.stats()
        return health.model_copy(update={"details": {**health.details, "bus": stats}})

    def has_subscribers(self, target: BoundTopic[Any]) -> bool:
        """Whether any subscriber (local or behind the router) matches the topic now, so a producer can skip
        expensive work nobody consumes (the simulator renders only while someone watches)."""
        status = self._publisher(target.key, target.decl.reliable).matching_status
        return bool(getattr(status, "matching", status))

    def publish_raw(self, key: str, data: bytes, encoding: str, *, reliable: bool = True,
                    attachment: bytes | None = None) -> None:
        """Publish bytes with an exact Zenoh encoding string (e.g. `application/json;aermani.ReasoningStep`),
        as recorded: replay republishes samples verbatim, which `publish` cannot do for every encoding."""
        if self._closed:
            raise BusError(f"publish on {key} after the bus was closed")
        self._publisher(key, reliable).put(bytes(data), encoding=zenoh.Encoding(encoding), attachment=attachment)

    # A BoundTopic / BoundQuery is also a `str`: with a union parameter mypy cannot infer the declared type
    # (T would be solved from the `str` arm), so each of these has one overload per kind of target.
    @overload
    def subscribe(self, target: BoundTopic[T], *, maxsize: int = 100,
                  overflow: Overflow = "drop_oldest") -> Subscription[T]: ...

    @overload
    def subscribe(self, target: str, *, maxsize: int = 100,
                  overflow: Overflow = "drop_oldest") -> Subscription[Any]: ...

    def subscribe(self, target: BoundTopic[T] | str, *, maxsize: int = 100,
                  overflow: Overflow = "drop_oldest") -> Subscription[T]:
        """Subscribe a declared topic (values decode to its declared type; protobuf topics give bytes) or a
        plain key expression (raw bytes), into a bounded queue."""
        key, model = (target.key, target.decl.type) if isinstance(target, BoundTopic) else (target, None)
        cap = target.decl.max_bytes if isinstance(target, BoundTopic) else None
        sub_obj: Subscription[T] = Subscription(self, key, model, maxsize, overflow, cap)
        sub_obj._sub = self.session.declare_subscriber(key, sub_obj._on_sample)
        self._declared.append(sub_obj._sub)
        self._subscriptions.append(sub_obj)
        return sub_obj

    def stats(self) -> dict[str, int]:
        """Counters: samples dropped (slow consumer), malformed and oversize over this bus's subscriptions,
        requests its queryables refused (busy, or larger than their cap), and samples superseded by newer ones
        on latest-value subscriptions (`overflow="latest"`: expected, not a loss)."""
        subs = list(self._subscriptions)
        return {"dropped": sum(s.dropped for s in subs), "malformed": sum(s.malformed for s in subs),
                "oversize": sum(s.oversize for s in subs), "refused_queries": self._refused_queries,
                "superseded": sum(s.superseded for s in subs)}

    # ---- query / reply

    @overload
    async def query(self, target: BoundQuery[Req, Rep], request: Req | None = None, *,
                    timeout: float = 5.0) -> Rep: ...

    @overload
    async def query(self, target: str, request: Any = None, *, timeout: float = 5.0) -> Any: ...

    async def query(self, target: BoundQuery[Req, Rep] | str, request: Req | Any = None, *,
                    timeout: float = 5.0) -> Rep:
        """Send a query to a declared queryable and return the first reply, decoded to its declared type (to a
        plain key expression: the reply's bytes). Raises NoResponder (nobody serves the key), QueryTimeout,
        RemoteError (error reply) or DecodeError (reply is malformed)."""
        key = target.key if isinstance(target, BoundQuery) else target
        schema = schema_name(target.decl.request) if isinstance(target, BoundQuery) and request is not None else None
        replies = await self.query_all(key, request, timeout=timeout, schema=schema, first_only=True)
        if not replies:
            raise NoResponder(f"no service answers {key}: is it running?")
        ok, data = replies[0]
        if not ok:
            text = data.decode(errors="replace")
            if data.strip() == ZENOH_TIMEOUT:  # Zenoh's own reply when the deadline passed; a service's error
                raise QueryTimeout(f"query {key} timed out after {timeout:.1f} s")  # text never counts as one
            raise RemoteError(f"{key} answered with an error: {text}", text)
        value = decoder(target.decl.reply if isinstance(target, BoundQuery) else None)(data)
        check_vehicle(key, value)
        return value  # type: ignore[no-any-return]

    async def query_all(self, key: str, request: Any = None, *, timeout: float = 5.0, schema: str | None = None,
                        first_only: bool = False) -> list[tuple[bool, bytes]]:
        """Every reply as (ok, bytes) until the query is finalized or times out."""
        fut: asyncio.Future[list[tuple[bool, bytes]]] = self.loop.create_future()
        replies: list[tuple[bool, bytes]] = []

        def add(item: tuple[bool, bytes]) -> None:
            replies.append(item)
            if first_only and not fut.done():
                fut.set_result(list(replies))

        def on_reply(reply: zenoh.Reply) -> None:
            res, err = reply.ok, reply.err
            if res is not None:
                item = (True, res.payload.to_bytes())
            else:
                item = (False, err.payload.to_bytes() if err is not None else b"no reply")
            self._to_loop(add, item)

        def finish() -> None:
            if not fut.done():
                fut.set_result(list(replies))

        def on_done() -> None:
            self._to_loop(finish)

        kwargs: dict[str, Any] = {"timeout": timeout, "attachment": self._caller_attachment()}
        if request is not None:
            data, enc = encode(request, schema)
            kwargs.update(payload=data, encoding=enc)
        self.session.get(key, zenoh.handlers.Callback(on_reply, on_done), **kwargs)
        try:
            return await asyncio.wait_for(fut, timeout + 1.0)
        except TimeoutError:
            raise QueryTimeout(f"query {key} timed out after {timeout:.1f} s")

    def _caller_attachment(self) -> bytes:
        with contextlib.suppress(Exception):
            return json.dumps({"sender": self.name or "anonymous", "zid": str(self.session.zid())}).encode()
        return b""

    def serve(self, target: BoundQuery[Req, Rep] | str, handler: Callable[..., Awaitable[Rep]], *,
              concurrent: bool = True, raw: bool = False, with_caller: bool = False,
              with_attachment: bool = False, complete: bool = False) -> Any:
        """Declare a queryable. `handler(request)` runs on the loop with the request decoded to its declared
        type (`raw=True`: the bytes, for a handler that answers a malformed request itself); its return
        value is the reply. A malformed request gets an error reply naming the problem and the handler is
        not called; an exception in the handler becomes an error reply, never a crash. With `with_caller`,
        the handler is called as `handler(request, caller)` with the querier's Caller; with `with_attachment`,
        as `handler(request, attachment)` with the query's attachment bytes (or None). A plain key expression
        (not a declaration) serves raw bytes; a handler that returns a `RawReply` has it sent verbatim.
        `complete`: the queryable answers for every key it covers (queries that target complete queryables
        only, as ROS 2's service clients over rmw_zenoh do, reach it)."""
        key = target.key if isinstance(target, BoundQuery) else target
        request_model = target.decl.request if isinstance(target, BoundQuery) and not raw else None
        decode = decoder(request_model)
        max_bytes = max_bytes_of(None if raw or not isinstance(target, BoundQuery) else target.decl.request)
        lock = asyncio.Lock()

        async def answer(query: zenoh.Query, data: bytes | None, attachment: bytes | None) -> None:
            try:
                try:
                    if request_model is None or isinstance(request_model, Json | Protobuf):
                        req = decode(data) if data and request_model is not None else data
                    elif not data:
                        raise DecodeError(f"empty request: {key} expects a JSON "
                                          f"{getattr(request_model, '__name__', 'request')}")
                    else:
                        req = decode(data)
                    check_vehicle(key, req)
                except DecodeError as exc:
                    log.warning("rejected malformed query on %s: %s", key, exc)
                    query.reply_err(json.dumps({"error": str(exc)}).encode())
                    return
                args: tuple[Any, ...] = (req,)
                if with_caller:
                    args = (req, Caller.from_attachment(attachment))
                elif with_attachment:
                    args = (req, attachment)
                try:
                    if concurrent:
                        result = await handler(*args)
                    else:
                        async with lock:
                            result = await handler(*args)
                except asyncio.CancelledError:
                    query.reply_err(b'{"error": "service is shutting down"}')
                    raise
                except Exception as exc:
                    _handler_failed(query, key, exc)
                    return
                _reply(query, key, result)
            finally:
                with contextlib.suppress(Exception):
                    query.drop()  # type: ignore[no-untyped-call]

        in_flight: set[asyncio.Task[None]] = set()
        warn = RateLimitedWarning()

        def refuse(query: zenoh.Query, why: str) -> None:
            self._refused_queries += 1
            warn("refused a query on %s: %s", key, why)
            with contextlib.suppress(Exception):
                query.reply_err(json.dumps({"error": why}).encode())
                query.drop()  # type: ignore[no-untyped-call]

        def start(query: zenoh.Query, data: bytes | None, attachment: bytes | None) -> None:
            if len(in_flight) >= QUERY_CONCURRENCY:
                refuse(query, f"busy: {len(in_flight)} requests on {key} in progress; try again")
                return
            task = self.loop.create_task(answer(query, data, attachment))
            self._tasks.add(task)
            in_flight.add(task)
            task.add_done_callback(self._tasks.discard)
            task.add_done_callback(in_flight.discard)

        def on_query(query: zenoh.Query) -> None:
            payload = query.payload
            if payload is not None and len(payload) > max_bytes:
                refuse(query, f"request of {len(payload)} bytes exceeds the {max_bytes}-byte cap of {key}")
                return
            attachment = query.attachment
            self._to_loop(start, query, payload.to_bytes() if payload is not None else None,
                          attachment.to_bytes() if attachment is not None else None)

        q = self.session.declare_queryable(key, on_query, complete=complete)
        self._declared.append(q)
        return q

    # ---- liveliness

    def declare_token(self, target: BoundToken | str) -> Any:
        token = self.session.liveliness().declare_token(str(target))
        self._declared.append(token)
        return token

    async def alive(self, pattern: str, timeout: float = 2.0) -> list[str]:
        """Keys of the liveliness tokens alive now that match `pattern`."""

        def get() -> list[str]:
            replies = self.session.liveliness().get(pattern, timeout=timeout)
            return sorted({str(r.ok.key_expr) for r in replies if r.ok is not None})

        return await asyncio.to_thread(get)

    def watch_liveliness(self, pattern: str, *, history: bool = True,
                         maxsize: int = 1000) -> asyncio.Queue[tuple[str, bool]]:
        """Queue of (key, alive) events: True when a token appears, False when it disappears."""
        queue: asyncio.Queue[tuple[str, bool]] = asyncio.Queue(maxsize=maxsize)

        def push(item: tuple[str, bool]) -> None:
            if queue.full():
                with contextlib.suppress(asyncio.QueueEmpty):
                    queue.get_nowait()
            queue.put_nowait(item)

        def on_sample(sample: zenoh.Sample) -> None:
            self._to_loop(push, (str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))

        sub = self.session.liveliness().declare_subscriber(pattern, on_sample, history=history)
        self._declared.append(sub)
        self._watches[id(queue)] = sub
        return queue

    def unwatch_liveliness(self, queue: asyncio.Queue[tuple[str, bool]]) -> None:
        """Stop the watch that feeds `queue` (its subscriber is undeclared; nothing more is queued)."""
        self._undeclare(self._watches.pop(id(queue), None))


class Latest(Generic[T]):
    """The one latest-value helper: the newest sample of a subscription with its local receive time, and
    "wait for one newer than X". `run()` keeps it up to date in the background; `transform` turns each
    sample into the stored value (samples it rejects with an AermaniError are logged and skipped)."""

    def __init__(self, sub: Subscription[Any], transform: Callable[[Any], T] | None = None) -> None:
        self.sub = sub
        self.transform = transform
        self.value: T | None = None
        self.receive_ns = 0
        self._changed = asyncio.Event()

    async def run(self) -> None:
        from shared.errors import AermaniError

        while True:
            rec = await self.sub.recv_sample()
            try:
                value = self.transform(rec.value) if self.transform else rec.value
            except AermaniError as exc:
                log.warning("dropped sample on %s: %s", rec.key, exc)
                continue
            self.put(value, rec.receive_ns)

    def put(self, value: T, receive_ns: int) -> None:
        self.value, self.receive_ns = value, receive_ns
        self._changed.set()
        self._changed = asyncio.Event()

    @property
    def age_s(self) -> float:
        return float("inf") if not self.receive_ns else (time.time_ns() - self.receive_ns) / 1e9

    async def newer_than(self, ns: int, timeout: float) -> bool:
        """Wait until a sample received after `ns` is here (True) or `timeout` passes (False)."""
        deadline = time.monotonic() + timeout
        while self.receive_ns <= ns:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._changed.wait(), remaining)
        return True

    async def wait(self, timeout: float) -> T:
        """The next sample received from now on. Raises TimeoutError."""
        if not await self.newer_than(time.time_ns(), timeout):
            raise TimeoutError(f"no new sample on {self.sub.key} within {timeout:.1f} s")
        assert self.value is not None
        return self.value


async def query_ready(bus: Bus, target: BoundQuery[Req, Rep], request: Req | None = None, *,
                      timeout: float = 10.0, ready_timeout: float = 30.0, first_delay: float = 0.2,
                      max_delay: float = 2.0) -> Rep:
    """The one "query until someone answers" helper: retries while nobody serves the key yet (start-up, or a
    supervised restart) with exponential backoff capped at `max_delay`, for at most `ready_timeout`
    seconds; then raises the last NoResponder/QueryTimeout. Error replies are not retried."""
    deadline = time.monotonic() + ready_timeout
    delay = first_delay
    while True:
        try:
            return await bus.query(target, request, timeout=timeout)
        except (NoResponder, QueryTimeout):
            if time.monotonic() + delay > deadline:
                raise
            await asyncio.sleep(delay)
            delay = min(max_delay, delay * 2)
