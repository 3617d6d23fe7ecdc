"""The asyncio wrapper over zenoh-python 1.x that every service uses; services never touch zenoh directly.

zenoh-python is synchronous and calls back on its own threads. Every callback here only hands the raw
sample to the event loop with `loop.call_soon_threadsafe` (tiny, GIL-friendly); decoding happens on the
consumer side, so a malformed payload is logged, counted and dropped without touching the subscriber.

Queue policy: each subscription has a bounded asyncio queue. When it is full, `overflow="drop_oldest"`
(the default, right for sensor streams and state: the newest sample wins) discards the oldest queued
sample; `overflow="drop_newest"` discards the arriving one. Either way the discarded sample is counted
in `Subscription.dropped`, never silently lost. Publishers use CongestionControl.BLOCK by default so the
network layer itself does not drop (`reliable=False` selects DROP + express, for frames where late is
worse than lost).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import threading
import time
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from typing import Any, Generic, Literal, TypeVar

import zenoh
from pydantic import BaseModel, TypeAdapter, ValidationError

from shared.errors import BusError, DecodeError, NoResponder, QueryTimeout, RemoteError

log = logging.getLogger("aermani.bus")

T = TypeVar("T")
Overflow = Literal["drop_oldest", "drop_newest"]

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
                 connect_timeout_s: float | None = None) -> zenoh.Config:
    """A Zenoh config with explicit endpoints and multicast scouting off by default.

    Clients wait for their router forever by default (services may start before it); a command-line tool
    passes `connect_timeout_s` to fail with a clear message instead."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(multicast))
    if connect:
        cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if listen:
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if mode == "client":
        timeout_ms = -1 if connect_timeout_s is None else int(connect_timeout_s * 1000)
        cfg.insert_json5("connect/timeout_ms", json.dumps(timeout_ms))
    return cfg


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
                loop.call_soon_threadsafe(lambda e=exc: fut.done() or fut.set_exception(e))
            return
        if loop.is_closed():
            session.close()
            return
        loop.call_soon_threadsafe(lambda: fut.set_result(session) if not fut.done() else session.close())

    threading.Thread(target=work, name="zenoh-open", daemon=True).start()
    return await fut


# --------------------------------------------------------------------------- encoding


def schema_of(obj: Any) -> str:
    if isinstance(obj, BaseModel):
        fn = getattr(type(obj), "full_schema_name", None)
        return fn() if fn else f"aermani.{type(obj).__name__}"
    return ""


def encode(obj: Any, schema: str | None = None) -> tuple[bytes, zenoh.Encoding]:
    """Model -> JSON bytes with `application/json;aermani.<Model>`; protobuf message -> bytes with
    `application/protobuf;<full name>`; bytes pass through with the given schema (protobuf if it names
    a foxglove type)."""
    if isinstance(obj, BaseModel):
        return obj.model_dump_json().encode(), _ENC_JSON.with_schema(schema or schema_of(obj))
    if hasattr(obj, "SerializeToString") and hasattr(obj, "DESCRIPTOR"):
        return obj.SerializeToString(), _ENC_PROTOBUF.with_schema(obj.DESCRIPTOR.full_name)
    if isinstance(obj, bytes | bytearray | memoryview):
        if schema and schema.startswith("foxglove."):
            return bytes(obj), _ENC_PROTOBUF.with_schema(schema)
        if schema:
            return bytes(obj), _ENC_JSON.with_schema(schema)
        return bytes(obj), _ENC_BYTES
    if isinstance(obj, dict | list | str | int | float | bool) or obj is None:
        return json.dumps(obj).encode(), _ENC_JSON.with_schema(schema) if schema else _ENC_JSON
    raise TypeError(f"cannot encode {type(obj).__name__} for the bus")


class _Decoder(Generic[T]):
    def __init__(self, model: type[T] | Any | None) -> None:
        self.model = model
        self.adapter = TypeAdapter(model) if model is not None else None

    def __call__(self, data: bytes) -> T:
        if self.adapter is None:
            return data  # type: ignore[return-value]
        try:
            return self.adapter.validate_json(data)
        except ValidationError as exc:
            first = exc.errors()[0] if exc.errors() else {}
            where = ".".join(str(p) for p in first.get("loc", ())) or "payload"
            raise DecodeError(f"invalid {getattr(self.model, '__name__', self.model)} at {where}: "
                              f"{first.get('msg', exc)}") from exc


def decoder(model: type[T] | Any | None) -> Callable[[bytes], T]:
    return _Decoder(model)


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


class Subscription(Generic[T]):
    """A bounded async queue of decoded samples from one key expression."""

    def __init__(self, bus: Bus, key: str, model: Any, maxsize: int, overflow: Overflow) -> None:
        self.bus = bus
        self.key = key
        self._decode = decoder(model)
        self._queue: asyncio.Queue[tuple[str, bytes, str, int]] = asyncio.Queue(maxsize=maxsize)
        self._overflow = overflow
        self.dropped = 0
        self.malformed = 0
        self.received = 0
        self._sub: Any = None
        self._closed = False
        # Hand-over from zenoh's thread: samples gather here and one loop callback drains them, so a burst
        # costs one loop wake-up instead of one per sample.
        self._pending: deque[tuple[str, bytes, str, int]] = deque()
        self._pending_lock = threading.Lock()
        self._drain_scheduled = False

    def _from_zenoh(self, item: tuple[str, bytes, str, int]) -> None:  # runs on a zenoh thread
        with self._pending_lock:
            self._pending.append(item)
            if self._drain_scheduled:
                return
            self._drain_scheduled = True
        self.bus._to_loop(self._drain)

    def _drain(self) -> None:  # runs on the loop
        with self._pending_lock:
            items = list(self._pending)
            self._pending.clear()
            self._drain_scheduled = False
        for item in items:
            self._push(item)

    def _push(self, item: tuple[str, bytes, str, int]) -> None:  # runs on the loop
        self.received += 1
        if self._queue.full():
            self.dropped += 1
            if self._overflow == "drop_newest":
                return
            with contextlib.suppress(asyncio.QueueEmpty):
                self._queue.get_nowait()
        self._queue.put_nowait(item)

    async def recv_sample(self, timeout: float | None = None) -> Received[T]:
        """Next valid sample (malformed ones are logged and skipped). Raises TimeoutError."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            key, data, enc, rns = await asyncio.wait_for(self._queue.get(), remaining)
            try:
                value = self._decode(data)
            except DecodeError as exc:
                self.malformed += 1
                log.warning("dropped malformed sample on %s: %s", key, exc)
                continue
            return Received(key, value, data, enc, rns)

    async def recv(self, timeout: float | None = None) -> T:
        return (await self.recv_sample(timeout)).value

    def latest_nowait(self) -> T | None:
        """Drain the queue and return the newest valid sample, or None."""
        newest = None
        while True:
            try:
                key, data, _enc, _rns = self._queue.get_nowait()
            except asyncio.QueueEmpty:
                return newest
            try:
                newest = self._decode(data)
            except DecodeError as exc:
                self.malformed += 1
                log.warning("dropped malformed sample on %s: %s", key, exc)

    def __aiter__(self) -> AsyncIterator[T]:
        return self._iter()

    async def _iter(self) -> AsyncIterator[T]:
        while not self._closed:
            yield await self.recv()

    def qsize(self) -> int:
        return self._queue.qsize()

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self.bus._undeclare(self._sub)


# --------------------------------------------------------------------------- the bus


class Bus:
    """One Zenoh session bound to one asyncio loop. Create with `await Bus.open(...)`."""

    def __init__(self, session: zenoh.Session, loop: asyncio.AbstractEventLoop) -> None:
        self.session = session
        self.loop = loop
        self._publishers: dict[tuple[str, bool], Any] = {}
        self._declared: list[Any] = []
        self._tasks: set[asyncio.Task] = set()
        self._closed = False
        self._lock = threading.Lock()
        self.name = ""
        """This service's name, sent with every query so queryables can log who asked (see Caller)."""

    # ---- lifecycle

    @classmethod
    async def open(cls, connect: list[str] | tuple[str, ...] = ("tcp/127.0.0.1:7447",), mode: str = "client",
                   listen: list[str] | tuple[str, ...] = (), config: zenoh.Config | None = None,
                   connect_timeout_s: float | None = None) -> Bus:
        _init_zenoh_log()
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

    def publish(self, key: str, obj: Any, *, schema: str | None = None, reliable: bool = True,
                attachment: bytes | None = None) -> None:
        """Publish a model, a protobuf message, or bytes (with a schema name). Non-blocking in practice:
        BLOCK only waits when the transmission queue is full."""
        if self._closed:
            raise BusError(f"publish on {key} after the bus was closed")
        data, enc = encode(obj, schema)
        self._publisher(key, reliable).put(data, encoding=enc, attachment=attachment)

    def has_subscribers(self, key: str, *, reliable: bool = True) -> bool:
        """Whether any subscriber (local or behind the router) matches `key` now, so a producer can skip
        expensive work nobody consumes (the simulator renders only while someone watches)."""
        status = self._publisher(key, reliable).matching_status
        return bool(getattr(status, "matching", status))

    def publish_raw(self, key: str, data: bytes, encoding: str, *, reliable: bool = True,
                    attachment: bytes | None = None) -> None:
        """Publish bytes with an exact Zenoh encoding string (e.g. `application/json;aermani.ReasoningStep`),
        as recorded: replay republishes samples verbatim, which `publish` cannot do for every encoding."""
        if self._closed:
            raise BusError(f"publish on {key} after the bus was closed")
        self._publisher(key, reliable).put(bytes(data), encoding=zenoh.Encoding(encoding), attachment=attachment)

    def subscribe(self, key: str, model: type[T] | Any | None = None, *, maxsize: int = 100,
                  overflow: Overflow = "drop_oldest") -> Subscription[T]:
        """Subscribe `key` (a key expression) into a bounded queue; values decode to `model`
        (a pydantic model or union; None gives raw bytes)."""
        sub_obj: Subscription[T] = Subscription(self, key, model, maxsize, overflow)

        def on_sample(sample: zenoh.Sample) -> None:
            sub_obj._from_zenoh((str(sample.key_expr), sample.payload.to_bytes(), str(sample.encoding),
                                 time.time_ns()))

        sub_obj._sub = self.session.declare_subscriber(key, on_sample)
        self._declared.append(sub_obj._sub)
        return sub_obj

    # ---- query / reply

    async def query(self, key: str, request: Any = None, response_model: type[T] | Any | None = None, *,
                    timeout: float = 5.0, schema: str | None = None) -> T:
        """Send a query and return the first reply, decoded. Raises NoResponder (nobody serves the key),
        QueryTimeout, RemoteError (error reply) or DecodeError (reply is malformed)."""
        replies = await self.query_all(key, request, timeout=timeout, schema=schema, first_only=True)
        if not replies:
            raise NoResponder(f"no service answers {key}: is it running?")
        ok, data = replies[0]
        if not ok:
            text = data.decode(errors="replace")
            if "timeout" in text.lower():
                raise QueryTimeout(f"query {key} timed out after {timeout:.1f} s")
            raise RemoteError(f"{key} answered with an error: {text}", text)
        return decoder(response_model)(data)

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
            res = reply.ok
            item = (True, res.payload.to_bytes()) if res is not None else (False, reply.err.payload.to_bytes())
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

    def serve(self, key: str, handler: Callable[..., Awaitable[Any]], request_model: type | Any | None = None,
              *, concurrent: bool = True, with_caller: bool = False) -> Any:
        """Declare a queryable on `key`. `handler(request)` runs on the loop; its return value (model,
        protobuf, bytes) is the reply. A malformed request gets an error reply naming the problem and the
        handler is not called; an exception in the handler becomes an error reply, never a crash.
        With `with_caller`, the handler is called as `handler(request, caller)` with the querier's Caller."""
        decode = decoder(request_model)
        lock = asyncio.Lock()

        async def answer(query: zenoh.Query, data: bytes | None, attachment: bytes | None) -> None:
            try:
                try:
                    if request_model is None:
                        req = data
                    elif not data:
                        raise DecodeError(f"empty request: {key} expects a JSON "
                                          f"{getattr(request_model, '__name__', 'request')}")
                    else:
                        req = decode(data)
                except DecodeError as exc:
                    log.warning("rejected malformed query on %s: %s", key, exc)
                    query.reply_err(json.dumps({"error": str(exc)}).encode())
                    return
                args = (req, Caller.from_attachment(attachment)) if with_caller else (req,)
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
                    log.exception("handler for %s failed", key)
                    query.reply_err(json.dumps({"error": f"{type(exc).__name__}: {exc}"}).encode())
                    return
                payload, enc = encode(result)
                query.reply(key, payload, encoding=enc)
            finally:
                with contextlib.suppress(Exception):
                    query.drop()

        def start(query: zenoh.Query, data: bytes | None, attachment: bytes | None) -> None:
            task = self.loop.create_task(answer(query, data, attachment))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

        def on_query(query: zenoh.Query) -> None:
            payload = query.payload
            attachment = query.attachment
            self._to_loop(start, query, payload.to_bytes() if payload is not None else None,
                          attachment.to_bytes() if attachment is not None else None)

        q = self.session.declare_queryable(key, on_query)
        self._declared.append(q)
        return q

    # ---- liveliness

    def declare_token(self, key: str) -> Any:
        token = self.session.liveliness().declare_token(key)
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
        return queue


class Latest(Generic[T]):
    """Keeps the newest value of a subscription up to date in the background: `latest.value`, `latest.age_s`."""

    def __init__(self, sub: Subscription[T]) -> None:
        self.sub = sub
        self.value: T | None = None
        self.receive_ns = 0
        self.updated = asyncio.Event()

    async def run(self) -> None:
        while True:
            rec = await self.sub.recv_sample()
            self.value = rec.value
            self.receive_ns = rec.receive_ns
            self.updated.set()

    @property
    def age_s(self) -> float:
        return float("inf") if not self.receive_ns else (time.time_ns() - self.receive_ns) / 1e9

    async def wait(self, timeout: float) -> T:
        """Wait for a value newer than now."""
        self.updated.clear()
        await asyncio.wait_for(self.updated.wait(), timeout)
        assert self.value is not None
        return self.value
