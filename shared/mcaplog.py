"""MCAP conventions of aermani logs: channel schemas from Zenoh encodings, stamps, reading and recovery.

One MCAP channel per (Zenoh key, Zenoh encoding); the channel's metadata keeps the exact Zenoh encoding
string so replay can republish a sample verbatim. Schemas: `protobuf` FileDescriptorSets for Foxglove
types (the Foxglove app and any protobuf reader decode them), `jsonschema` of the pydantic model for
aermani JSON messages, none for anything else.

This module is also the reading helper other services use (the reasoner's `replay` backend): see
`iter_samples`, `read_messages` and `reasoning_steps`.
"""

from __future__ import annotations

import functools
import json
import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
from pydantic import BaseModel

from shared.bus import decoder
from shared.errors import AermaniError
from shared.keys import REASONER_STEP, REASONER_TASK_STATUS, BoundTopic, Topic
from shared.messages import MESSAGES_BY_SCHEMA, ReasoningStep, TaskStatus
from shared.sensors import PROTO_TYPES, stamp_to_ns

log = logging.getLogger("aermani.recorder")

T = TypeVar("T", bound=BaseModel)

ZENOH_ENCODING_META = "zenoh_encoding"
PROTOBUF = "protobuf"
JSON = "json"
JSONSCHEMA = "jsonschema"
RAW_ENCODING = "application/octet-stream"  # MCAP message encoding of schemaless binary samples


@dataclass(frozen=True)
class ChannelSpec:
    """How one Zenoh encoding maps onto an MCAP schema and channel."""

    message_encoding: str
    schema_name: str = ""
    schema_encoding: str = ""
    schema_data: bytes = b""

    @property
    def has_schema(self) -> bool:
        return bool(self.schema_name)


def split_encoding(encoding: str) -> tuple[str, str]:
    """`application/json;aermani.VehicleState` -> ("application/json", "aermani.VehicleState")."""
    mime, _, schema = str(encoding).partition(";")
    return mime.strip(), schema.strip()


@functools.lru_cache(maxsize=256)
def channel_spec(encoding: str) -> ChannelSpec:
    """MCAP schema and message encoding for a Zenoh encoding string."""
    mime, schema = split_encoding(encoding)
    if mime == "application/protobuf" and schema in PROTO_TYPES:
        from mcap_protobuf.schema import build_file_descriptor_set

        fds = build_file_descriptor_set(PROTO_TYPES[schema]).SerializeToString()
        return ChannelSpec(PROTOBUF, schema, PROTOBUF, fds)
    if mime == "application/json":
        model = MESSAGES_BY_SCHEMA.get(schema)
        if model is not None:
            return ChannelSpec(JSON, schema, JSONSCHEMA, json.dumps(model.model_json_schema()).encode())
        return ChannelSpec(JSON)
    if mime == "application/protobuf":
        # A protobuf type we have no descriptor for: keep the bytes, schemaless.
        return ChannelSpec(PROTOBUF)
    if mime.startswith("text/"):
        return ChannelSpec("text")
    return ChannelSpec(RAW_ENCODING)


def publish_time_ns(encoding: str, payload: bytes, receive_ns: int) -> int:
    """The message's own stamp: `stamp_ns` of JSON messages, the header `timestamp` of Foxglove protobuf
    messages (first transform of FrameTransforms); the receive time when there is none."""
    mime, schema = split_encoding(encoding)
    try:
        if mime == "application/json":
            obj = json.loads(payload)
            if isinstance(obj, dict):
                stamp = obj.get("stamp_ns")
                if isinstance(stamp, int) and stamp > 0:
                    return stamp
        elif mime == "application/protobuf" and schema in PROTO_TYPES:
            msg = PROTO_TYPES[schema]()
            msg.ParseFromString(payload)
            if schema == "foxglove.FrameTransforms":
                if msg.transforms:
                    ns = stamp_to_ns(msg.transforms[0].timestamp)
                    return ns if ns > 0 else receive_ns
            elif msg.HasField("timestamp"):
                ns = stamp_to_ns(msg.timestamp)
                return ns if ns > 0 else receive_ns
    except Exception:  # a malformed payload is still recorded verbatim, stamped at receive time
        pass
    return receive_ns


def vehicle_of(key: str) -> str | None:
    """`aermani/v1/am1/camera/color` -> "am1"."""
    parts = key.split("/")
    return parts[2] if len(parts) > 3 and parts[0] == "aermani" else None


def log_vehicles(path: str | Path) -> set[str]:
    """The vehicle ids a log holds samples for: from its summary's channels, or (an unfinished log) from its
    samples."""
    try:
        with Path(path).open("rb") as f:
            summary = make_reader(f).get_summary()
        if summary is not None:
            return {v for c in summary.channels.values() if (v := vehicle_of(c.topic)) is not None}
    except (McapError, ValueError, KeyError, EOFError, AssertionError):
        pass
    return {v for s in salvage(path).samples if (v := vehicle_of(s.key)) is not None}


# --------------------------------------------------------------------------- key expressions


def key_matches(pattern: str, key: str) -> bool:
    """Zenoh key-expression match of a concrete key: `*` one chunk, `**` zero or more chunks,
    `$*` inside a chunk. Done here so readers need no Zenoh session."""
    return _match(pattern.split("/"), key.split("/"))


def _match(pat: list[str], parts: list[str]) -> bool:
    if not pat:
        return not parts
    head, rest = pat[0], pat[1:]
    if head == "**":
        return any(_match(rest, parts[i:]) for i in range(len(parts) + 1))
    if not parts:
        return False
    return _chunk_matches(head, parts[0]) and _match(rest, parts[1:])


def _chunk_matches(pat: str, chunk: str) -> bool:
    if pat == "*":
        return True
    if "$*" not in pat:
        return pat == chunk
    import fnmatch

    return fnmatch.fnmatchcase(chunk, pat.replace("$*", "*"))


# --------------------------------------------------------------------------- writing


def compression_type(name: str) -> CompressionType:
    return {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[name.lower()]


class ChannelTable:
    """Registers schemas and channels on one MCAP writer on first use of a (key, encoding)."""

    def __init__(self, writer: Writer) -> None:
        self.writer = writer
        self._schemas: dict[str, int] = {}
        self.channels: dict[tuple[str, str], int] = {}
        self.sequence: dict[int, int] = {}

    def channel_id(self, key: str, encoding: str) -> int:
        cid = self.channels.get((key, encoding))
        if cid is not None:
            return cid
        spec = channel_spec(encoding)
        schema_id = 0
        if spec.has_schema:
            schema_id = self._schemas.get(spec.schema_name, 0)
            if not schema_id:
                schema_id = self.writer.register_schema(spec.schema_name, spec.schema_encoding, spec.schema_data)
                self._schemas[spec.schema_name] = schema_id
        cid = self.writer.register_channel(key, spec.message_encoding, schema_id,
                                           {ZENOH_ENCODING_META: str(encoding)})
        self.channels[(key, encoding)] = cid
        self.sequence[cid] = 0
        return cid

    def next_sequence(self, cid: int) -> int:
        self.sequence[cid] += 1
        return self.sequence[cid]


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class LoggedSample:
    """One recorded Zenoh sample."""

    key: str
    payload: bytes
    encoding: str
    log_time_ns: int
    publish_time_ns: int
    schema_name: str = ""


def _encoding_of(schema: Schema | None, channel: Channel) -> str:
    enc = channel.metadata.get(ZENOH_ENCODING_META)
    if enc:
        return enc
    # A log written by another tool: derive the Zenoh encoding from the MCAP one.
    if channel.message_encoding == PROTOBUF and schema is not None:
        return f"application/protobuf;{schema.name}"
    if channel.message_encoding == JSON:
        return f"application/json;{schema.name}" if schema is not None and schema.name else "application/json"
    return "zenoh/bytes"


def _sample(schema: Schema | None, channel: Channel, message: Message) -> LoggedSample:
    return LoggedSample(channel.topic, bytes(message.data), _encoding_of(schema, channel), message.log_time,
                        message.publish_time, schema.name if schema is not None else "")


def iter_samples(path: str | Path, keys: str | None = None, start_ns: int | None = None,
                 end_ns: int | None = None) -> Iterator[LoggedSample]:
    """Samples of a log in log-time order, optionally only keys matching `keys` (a key expression) and
    log times in [start_ns, end_ns). An unfinished log (crash) is read up to its last complete chunk."""
    path = Path(path)
    yielded = 0
    try:
        with path.open("rb") as f:
            reader = make_reader(f)
            reader.get_summary()  # raises on a log without summary: use the streaming path below
            topics = None
            if keys:
                summary = reader.get_summary()
                topics = [c.topic for c in summary.channels.values() if key_matches(keys, c.topic)] if summary else None
                if topics is not None and not topics:
                    return
            for schema, channel, message in reader.iter_messages(topics=topics, starting_at=start_ns,
                                                                 ending_before=end_ns, log_time_order=True):
                yielded += 1
                yield _sample(schema, channel, message)
            return
    except (McapError, ValueError, KeyError, EOFError, AssertionError) as exc:
        if yielded:
            raise
        log.info("%s has no usable index (%s); reading it sequentially", path, exc)
    samples = [s for s in salvage(path).samples
               if (not keys or key_matches(keys, s.key))
               and (start_ns is None or s.log_time_ns >= start_ns) and (end_ns is None or s.log_time_ns < end_ns)]
    samples.sort(key=lambda s: s.log_time_ns)
    yield from samples


def read_messages(path: str | Path, model: type[T], keys: str | None = None) -> list[tuple[LoggedSample, T]]:
    """Every sample of a log whose schema is `model`, decoded (malformed ones are skipped)."""
    full_schema_name = getattr(model, "full_schema_name", None)  # protobuf classes have it, pydantic models not
    name = full_schema_name() if full_schema_name is not None else f"aermani.{model.__name__}"
    out = []
    for s in iter_samples(path, keys):
        if s.schema_name == name or s.encoding.endswith(";" + name):
            try:
                out.append((s, model.model_validate_json(s.payload)))
            except ValueError as exc:
                log.warning("skipped malformed %s on %s: %s", name, s.key, exc)
    return out


def read_topic(path: str | Path, topic: BoundTopic[T]) -> list[tuple[LoggedSample, T]]:
    """Every sample recorded on a declared topic (one vehicle's, or the fleet's), decoded to its declared
    type (malformed ones are skipped)."""
    decode = decoder(topic.decl.type)
    out = []
    for s in iter_samples(path, topic.key):
        try:
            out.append((s, decode(s.payload)))
        except AermaniError as exc:
            log.warning("skipped malformed sample on %s: %s", s.key, exc)
    return out


def topic_of(vehicle_id: str | None, decl: Topic[T]) -> BoundTopic[T]:
    """`decl` on one vehicle, or on every vehicle when `vehicle_id` is None or '*'."""
    return decl.fleet() if vehicle_id in (None, "*") else decl.bind(vehicle_id)


def reasoning_steps(path: str | Path, vehicle_id: str | None = None,
                    task_id: str | None = None) -> list[ReasoningStep]:
    """The recorded reasoning steps (last version of each (task, step)), in recording order. This is what
    the reasoner's replay backend reads its answers from."""
    latest: dict[tuple[str, int], ReasoningStep] = {}
    for _, step in read_topic(path, topic_of(vehicle_id, REASONER_STEP)):
        if task_id is None or step.task_id == task_id:
            latest[(step.task_id, step.step)] = step
    return list(latest.values())


class McapReplaySource:
    """Answers for the reasoner's `replay` backend from an MCAP log: every model call's raw answer (invalid
    ones included) of the recorded reasoning steps, in order. Implements the reasoner's ReplaySource."""

    def __init__(self, path: str | Path, vehicle_id: str | None = None, task_id: str | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"replay log {self.path} does not exist")
        self.vehicle_id = vehicle_id
        self.task_id = task_id

    def answers(self) -> Iterator[str]:
        for step in reasoning_steps(self.path, self.vehicle_id, self.task_id):
            for call in step.calls:
                yield call.raw_answer


def task_statuses(path: str | Path, vehicle_id: str | None = None) -> dict[str, TaskStatus]:
    """The last recorded status of each task."""
    return {st.task_id: st for _, st in read_topic(path, topic_of(vehicle_id, REASONER_TASK_STATUS))}


def metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """The metadata records of a log by name (later records of a name update earlier ones)."""
    out: dict[str, dict[str, str]] = {}
    try:
        with Path(path).open("rb") as f:
            for rec in make_reader(f).iter_metadata():
                out.setdefault(rec.name, {}).update(rec.metadata)
            return out
    except (McapError, ValueError, KeyError, EOFError, AssertionError):
        for rec in salvage(path).metadata:
            out.setdefault(rec.name, {}).update(rec.metadata)
        return out


# --------------------------------------------------------------------------- recovery


@dataclass
class Salvage:
    """What could be read from a damaged or unfinished MCAP file: samples, schemas, channels and metadata."""

    samples: list[LoggedSample]
    schemas: dict[int, Schema]
    channels: dict[int, Channel]
    metadata: list[Metadata]
    chunks: int
    complete: bool
    """True when the file ended with its footer (nothing was lost)."""
    error: str = ""
    raw: list[tuple[int, Message]] | None = None
    messages: int = 0
    """Messages kept (= len(samples) for `salvage`; `recover` streams them and keeps none)."""


@dataclass
class _Scan:
    """What streaming through a (possibly truncated) log found so far."""

    chunks: int = 0
    complete: bool = False
    error: str = ""


def _scan(path: str | Path, scan: _Scan) -> Iterator[Any]:
    """Yield the records of a (possibly truncated) log in file order: schemas, channels, messages, metadata;
    stop at the first incomplete or corrupt record. A chunk's records are yielded only once the whole chunk
    has been read and its CRC checked, so this keeps exactly the complete chunks, holding one at a time."""
    from mcap.records import Chunk, Footer

    with Path(path).open("rb") as f:
        reader = StreamReader(f, emit_chunks=True, record_size_limit=1 << 31)
        try:
            for record in reader.records:
                if isinstance(record, Chunk):
                    inner = list(_chunk_records(record))
                    scan.chunks += 1
                    yield from inner
                elif isinstance(record, Footer):
                    scan.complete = True
                else:
                    yield record
        except Exception as exc:  # truncated or corrupt tail: keep what was complete
            scan.error = f"{type(exc).__name__}: {exc}"


def salvage(path: str | Path) -> Salvage:
    """Read a (possibly truncated) log into memory record by record, up to its last complete chunk (for
    reading; `recover` streams instead)."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    meta: list[Metadata] = []
    raw: list[tuple[int, Message]] = []
    scan = _Scan()
    for record in _scan(path, scan):
        if isinstance(record, Metadata):
            meta.append(record)
        else:
            _take(record, schemas, channels, raw)
    samples = [_sample(schemas.get(channels[cid].schema_id), channels[cid], m) for cid, m in raw if cid in channels]
    return Salvage(samples, schemas, channels, meta, scan.chunks, scan.complete, scan.error, raw, len(samples))


def _chunk_records(chunk: Any) -> Iterable[Any]:
    from mcap.stream_reader import breakup_chunk

    return breakup_chunk(chunk, validate_crc=True)


def _take(record: Any, schemas: dict[int, Schema], channels: dict[int, Channel],
          raw: list[tuple[int, Message]]) -> None:
    if isinstance(record, Schema):
        schemas[record.id] = record
    elif isinstance(record, Channel):
        channels[record.id] = record
    elif isinstance(record, Message):
        raw.append((record.channel_id, record))


def recover(src: str | Path, dst: str | Path, *, chunk_size: int = 1 << 20) -> Salvage:
    """Write every message of the complete chunks of `src` (e.g. after a SIGKILL) into a finished log
    `dst`, with the same channels, schemas, metadata and times. Streams: memory stays at about one chunk
    whatever the log's size. The returned Salvage carries the counts, not the samples."""
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    scan = _Scan()
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    messages = 0
    with dst.open("wb") as f:
        writer = Writer(f, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        writer.start(profile="", library="aermani-recover")
        for record in _scan(src, scan):
            if isinstance(record, Schema) and record.id not in schema_ids:
                schemas[record.id] = record
                schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
            elif isinstance(record, Channel) and record.id not in channel_ids:
                channels[record.id] = record
                channel_ids[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schema_ids.get(record.schema_id, 0), dict(record.metadata))
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, dict(record.metadata))
            elif isinstance(record, Message) and record.channel_id in channel_ids:
                writer.add_message(channel_ids[record.channel_id], record.log_time, record.data, record.publish_time,
                                   record.sequence)
                messages += 1
        writer.add_metadata("aermani.recovered", {"source": str(src), "messages": str(messages),
                                                  "chunks": str(scan.chunks), "error": scan.error})
        writer.finish()  # type: ignore[no-untyped-call]  # mcap.writer.Writer.finish has no annotations
    return Salvage([], schemas, channels, [], scan.chunks, scan.complete, scan.error, None, messages)
