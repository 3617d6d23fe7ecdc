"""The MCAP writer thread: takes samples from a queue, writes them into rotating, crash-recoverable files.

Writing (zstd, disk I/O) happens on this thread so the event loop never blocks. The file is opened
unbuffered: every finished chunk goes straight to the OS, so a SIGKILL loses only the chunk in progress
(`durable` counts the messages already in finished chunks). Write errors (disk full, unwritable path)
never raise out of here: they are reported in `stats()` and the writer retries a new file later.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any, BinaryIO, cast

from mcap.writer import Writer

from services.recorder.settings import RecorderSettings
from shared.mcaplog import (
    ChannelTable,
    compression_type,
    key_matches,
    publish_time_ns,
    vehicle_of,
)

log = logging.getLogger("aermani.recorder")

_STOP = object()
_ROTATE = object()
# Task events (flush_key_expr) that arrive while no file can be written (a full disk) are kept for the next
# file, up to this many; frames and the rest are counted in lost_on_error.
HELD_MAX = 10_000


class _File:
    """Unbuffered binary file that always writes everything it is given and knows its size."""

    def __init__(self, raw: BinaryIO) -> None:
        self.raw = raw
        self.pos = 0

    def write(self, data: bytes | memoryview) -> int:
        view = memoryview(data)
        while view:
            n = self.raw.write(view)
            if n is None or n <= 0:
                raise OSError("short write")
            view = view[n:]
        self.pos += len(data)
        return len(data)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        with contextlib.suppress(AttributeError):
            self.raw.flush()

    def close(self) -> None:
        self.raw.close()


def default_opener(path: Path) -> BinaryIO:
    return open(path, "wb", buffering=0)  # noqa: SIM115 - owned by the writer thread


class RecordWriter:
    """Thread that owns the MCAP files. `submit()` is safe from any thread and never blocks."""

    def __init__(self, settings: RecorderSettings, static_meta: dict[str, str] | None = None,
                 opener: Callable[[Path], BinaryIO] = default_opener) -> None:
        self.settings = settings
        self.static_meta = dict(static_meta or {})
        self.opener = opener
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._backlog_bytes = 0
        self._max_backlog = int(settings.max_backlog_mb * (1 << 20))
        self._thread = threading.Thread(target=self._main, name="recorder-writer", daemon=False)
        # State of the current file (writer thread only).
        self._writer: Writer | None = None
        self._file: _File | None = None
        self._table: ChannelTable | None = None
        self._opened_at = 0.0
        self._file_index = 0
        self._retry_at = 0.0
        self._file_durable = 0
        self._drain_deadline = 0.0
        self.dropped_at_stop = 0
        self._pending = 0
        self._fox_server: Any = None
        self._flush_keys: dict[str, bool] = {}
        self._held: deque[tuple[str, bytes, str, int]] = deque()
        # Figures for health (read from any thread; ints are updated atomically enough for reporting).
        self.submitted = 0
        self.written = 0
        self.durable = 0
        self.dropped_backlog = 0
        self.lost_on_error = 0
        self.bytes_written = 0
        self.path: str = ""
        self.files: list[str] = []
        self.vehicles: set[str] = set()
        self.channels = 0
        self.error = ""
        self.errors = 0
        self.file_messages = 0
        self.foxglove_url = ""

    # ---- any thread

    def start(self) -> None:
        self._thread.start()

    def submit(self, key: str, payload: bytes, encoding: str, receive_ns: int) -> bool:
        """Queue one sample; False (counted) when the backlog is over its limit."""
        n = len(payload)
        with self._lock:
            if self._backlog_bytes + n > self._max_backlog:
                self.dropped_backlog += 1
                return False
            self._backlog_bytes += n
            self.submitted += 1
        self._queue.put((key, payload, encoding, receive_ns))
        return True

    def rotate(self) -> None:
        """Ask for a new file now."""
        self._queue.put(_ROTATE)

    def stop(self, drain_s: float | None = None, timeout: float | None = 60.0) -> None:
        """Write what is queued (for at most `drain_s` seconds; what is left then is counted in
        `dropped_at_stop`), finish the file, end the thread. Bounded, so a SIGTERM always ends with a valid
        file within the stop grace of a container."""
        if self._thread.is_alive():
            if drain_s is not None:
                self._drain_deadline = time.monotonic() + drain_s
            self._queue.put(_STOP)
            self._thread.join(timeout)

    @property
    def backlog_bytes(self) -> int:
        return self._backlog_bytes

    @property
    def ok(self) -> bool:
        return not self.error

    def stats(self) -> dict[str, Any]:
        return {
            "path": self.path, "files": list(self.files), "received": self.submitted, "written": self.written,
            "durable": self.durable, "file_messages": self.file_messages, "dropped": self.dropped_backlog,
            "lost_on_error": self.lost_on_error, "bytes": self.bytes_written, "channels": self.channels,
            "vehicles": sorted(self.vehicles), "backlog_bytes": self._backlog_bytes, "error": self.error,
            "errors": self.errors, "foxglove": self.foxglove_url, "dropped_at_stop": self.dropped_at_stop,
            "held": len(self._held),
        }

    # ---- writer thread

    def _main(self) -> None:
        if self.settings.foxglove:
            self._start_foxglove()
        self._open()
        while True:
            try:
                item = self._queue.get(timeout=0.2)
            except queue.Empty:
                item = None
            if item is _STOP:
                break
            if self._drain_deadline and time.monotonic() > self._drain_deadline:
                self._drop_rest(item)
                break
            if item is _ROTATE:
                self._rotate("requested")
                continue
            if item is not None:
                key, payload, encoding, receive_ns = item
                with self._lock:
                    self._backlog_bytes -= len(payload)
                self._write(key, payload, encoding, receive_ns)
            self._maybe_rotate()
        self._close(final=True)
        if self._held:  # the disk stayed full to the end: the kept task events go unwritten after all
            log.warning("stop: %d task events kept through a write error could not be written", len(self._held))
            self.lost_on_error += len(self._held)
            self._held.clear()
        if self._fox_server is not None:
            with contextlib.suppress(Exception):
                self._fox_server.stop()

    def _drop_rest(self, item: Any) -> None:
        """The drain ran out of time: count `item` and what is still queued, and leave them."""
        while True:
            if isinstance(item, tuple):
                self.dropped_at_stop += 1
                with self._lock:
                    self._backlog_bytes -= len(item[1])
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
        log.warning("stop: %d queued samples not written (drain limit reached)", self.dropped_at_stop)

    def _next_path(self) -> Path:
        out = Path(self.settings.out_dir)
        stamp = time.strftime("%Y%m%d-%H%M%S")
        while True:
            self._file_index += 1
            path = out / f"{self.settings.file_prefix}-{stamp}-{self._file_index:03d}.mcap"
            if not path.exists():
                return path

    def _open(self) -> bool:
        try:
            out = Path(self.settings.out_dir)
            out.mkdir(parents=True, exist_ok=True)
            path = self._next_path()
            self._file = _File(self.opener(path))
            self.path, self._file_durable = str(path), 0  # from here a failure concerns this file
            # _File has the write/tell/flush mcap's Writer uses; its annotation only names real file types.
            self._writer = Writer(cast(IO[Any], self._file), chunk_size=self.settings.chunk_size,
                                  compression=compression_type(self.settings.compression))
            self._writer.start(profile="", library="aermani-recorder")
            self._writer.add_metadata("aermani", {**self.static_meta, "file_index": str(self._file_index),
                                                  "opened_ns": str(time.time_ns())})
            self._table = ChannelTable(self._writer)
            self.files.append(str(path))
            self._opened_at = time.monotonic()
            self._pending = 0
            self._file_durable = 0
            self.file_messages = 0
            self.channels = 0
            if self.error:
                log.info("recording again into %s after: %s", path, self.error)
            self.error = ""
            log.info("recording into %s", path)
            self._write_held()
            return True
        except Exception as exc:
            self._fail(exc, "cannot open a recording in " + self.settings.out_dir)
            return False

    def _fail(self, exc: BaseException, what: str) -> None:
        self.errors += 1
        self.error = f"{what}: {type(exc).__name__}: {exc}"
        log.error("%s; retrying in %.0f s", self.error, self.settings.retry_s)
        # Messages of the chunk in progress are gone with the broken file: they were never written.
        self.lost_on_error += self._pending
        self.written -= self._pending
        self._pending = 0
        if self._file is not None:
            with contextlib.suppress(Exception):
                self._file.close()
            if self._file_durable == 0 and self.path:
                # Nothing of this file reached the disk (a retry on a still-full disk): remove it, so a
                # disk-full episode leaves one new file when space returns, not one per retry.
                with contextlib.suppress(OSError):
                    Path(self.path).unlink()
                with contextlib.suppress(ValueError):
                    self.files.remove(self.path)
                log.info("removed %s: nothing in it reached the disk", self.path)
        self._file = None
        self._writer = None
        self._table = None
        self._retry_at = time.monotonic() + self.settings.retry_s

    def _hold(self, key: str, payload: bytes, encoding: str, receive_ns: int) -> bool:
        """Keep a task event that cannot be written now for the next file (False: not one, or no room)."""
        if not self._flushes(key) or len(self._held) >= HELD_MAX:
            return False
        self._held.append((key, payload, encoding, receive_ns))
        return True

    def _write_held(self) -> None:
        """The task events kept through a write error go first into the new file, in their order."""
        if self._held:
            held, self._held = self._held, deque()
            log.info("writing %d task events kept while no file could be written", len(held))
            for item in held:
                self._write(*item, live=False)

    def _write(self, key: str, payload: bytes, encoding: str, receive_ns: int, live: bool = True) -> None:
        vid = vehicle_of(key)
        if vid:
            self.vehicles.add(vid)
        if live:
            self._live(key, payload, encoding, receive_ns)
        if self._writer is None and (time.monotonic() < self._retry_at or not self._open()):
            if not self._hold(key, payload, encoding, receive_ns):
                self.lost_on_error += 1
            return
        assert self._writer is not None and self._table is not None and self._file is not None
        counted = False
        try:
            cid = self._table.channel_id(key, encoding)
            self.channels = len(self._table.channels)
            before = self._file.tell()
            self._writer.add_message(cid, receive_ns, payload, publish_time_ns(encoding, payload, receive_ns),
                                     self._table.next_sequence(cid))
            self.written += 1
            self.file_messages += 1
            self._pending += 1
            counted = True
            if self._flushes(key):
                self._writer.flush()  # a task event: its chunk goes to the disk now
            after = self._file.tell()
            if after != before:  # a chunk was finished: everything added so far is on disk
                self.durable += self._pending
                self._file_durable += self._pending
                self._pending = 0
                self.bytes_written += after - before
        except Exception as exc:
            self._fail(exc, f"cannot write to {self.path}")  # counts the chunk's pending messages as lost
            if not counted:
                self.lost_on_error += 1  # this message went down with its chunk
            if self._hold(key, payload, encoding, receive_ns):
                self.lost_on_error -= 1  # a task event: kept for the next file instead

    def _flushes(self, key: str) -> bool:
        hit = self._flush_keys.get(key)
        if hit is None:
            expr = self.settings.flush_key_expr
            hit = self._flush_keys[key] = bool(expr) and key_matches(expr, key)
        return hit

    def _maybe_rotate(self) -> None:
        if self._writer is None:
            if self._retry_at and time.monotonic() >= self._retry_at and self._queue.empty():
                self._retry_at = 0.0
                self._open()
            return
        s = self.settings
        if s.rotate_mb and self._file is not None and self._file.tell() >= s.rotate_mb * (1 << 20):
            self._rotate("size")
        elif s.rotate_s and time.monotonic() - self._opened_at >= s.rotate_s:
            self._rotate("time")

    def _rotate(self, reason: str) -> None:
        log.info("rotating %s (%s)", self.path, reason)
        self._close(final=False)
        self._open()

    def _close(self, final: bool) -> None:
        if self._writer is None or self._file is None:
            return
        try:
            self._writer.add_metadata("aermani.session", {
                "vehicles": ",".join(sorted(self.vehicles)), "messages": str(self.file_messages),
                "dropped": str(self.dropped_backlog), "lost_on_error": str(self.lost_on_error),
                "closed_ns": str(time.time_ns()), "final": str(final).lower(),
            })
            before = self._file.tell()
            self._writer.finish()
            self.bytes_written += self._file.tell() - before
            self.durable += self._pending
            self._pending = 0
            with contextlib.suppress(Exception):
                os.fsync(self._file.raw.fileno())
            self._file.close()
            log.info("finished %s (%d messages)", self.path, self.file_messages)
        except Exception as exc:
            self._fail(exc, f"cannot finish {self.path}")
        finally:
            self._writer = None
            self._file = None
            self._table = None

    # ---- optional live view in the Foxglove app

    def _start_foxglove(self) -> None:
        try:
            from services.recorder.live import LiveServer

            s = self.settings
            token = s.foxglove_token.get_secret_value() if s.foxglove_token is not None else None
            self._fox_server = LiveServer(s.foxglove_host, s.foxglove_port, token=token,
                                          allowed_origins=list(s.foxglove_allowed_origins))
            self.foxglove_url = f"ws://{s.foxglove_host}:{self._fox_server.port}"
            log.info("Foxglove live server on %s (%s)", self.foxglove_url,
                     "token required" if token else "no token: loopback only")
        except Exception as exc:
            log.error("Foxglove live server not started: %s", exc)
            self._fox_server = None

    def _live(self, key: str, payload: bytes, encoding: str, receive_ns: int) -> None:
        if self._fox_server is None:
            return
        try:
            self._fox_server.log(key, encoding, payload, receive_ns)
        except Exception as exc:  # the live view must never stop the recording
            log.warning("Foxglove live view disabled: %s", exc)
            with contextlib.suppress(Exception):
                self._fox_server.stop()
            self._fox_server = None
