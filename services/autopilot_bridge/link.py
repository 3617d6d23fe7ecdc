"""The MAVLink link: a pymavlink connection, a reader thread that hands messages to asyncio, locked writes."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import logging
import os
import select
import struct
import threading
import time
import types
from collections.abc import Callable
from typing import Any

# PX4 speaks MAVLink 2; pymavlink picks the v2 dialect modules only when this is set before the import.
os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil  # noqa: E402

from services.autopilot_bridge import px4  # noqa: E402
from shared.errors import MavlinkError  # noqa: E402

log = logging.getLogger("aermani.autopilot_bridge.link")

mavutil.set_dialect("common")
mavlink = mavutil.mavlink


UDP_TCP_SCHEMES = ("udpin:", "udpout:", "udp:", "udpbcast:", "tcp:", "tcpin:")


def parse_connection(spec: str, baud: int = 921600) -> tuple[str, int]:
    """A connection setting -> (pymavlink device, baud). Accepted: `udpin:HOST:PORT` (and udpout:, udp:, tcp:,
    tcpin:), `serial:DEVICE[:BAUD]` (e.g. `serial:/dev/ttyACM0:921600`), or a bare device path (`/dev/ttyAMA0`,
    `COM3`) at `baud`. Anything else is a clear error, before any port is opened."""
    s = spec.strip()
    if not s:
        raise MavlinkError("empty MAVLink connection: use udpin:127.0.0.1:14540 or serial:/dev/ttyACM0:921600")
    if s.startswith(UDP_TCP_SCHEMES):
        return s, baud
    if s.startswith("serial:"):
        rest = s[len("serial:"):]
        device, sep, rate = rest.rpartition(":")
        if not sep or not rate.isdigit():
            device, rate = rest, ""  # `...-usb-0:1.2:1.0` (a by-path name): the ':' are the device's own
        if not device:
            raise MavlinkError(f"MAVLink connection {spec!r}: no serial device (e.g. serial:/dev/ttyACM0:921600)")
        if rate and not 0 < int(rate) <= 12_000_000:
            raise MavlinkError(f"MAVLink connection {spec!r}: baud rate {rate} out of range")
        return device, int(rate) if rate else baud
    if s.startswith("/dev/") or s.upper().startswith("COM"):
        return s, baud
    raise MavlinkError(f"unknown MAVLink connection {spec!r}: use udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, "
                       "serial:/dev/DEVICE[:BAUD] or a device path")



def _parse_datagram(parser: Any, data: bytes) -> list[Any]:
    """The MAVLink messages of one UDP datagram, from a reset parser state; a parser error or a truncated frame at
    the end comes back as a BAD_DATA message instead of raising."""
    parser.buf, parser.buf_index = bytearray(), 0
    parser.expected_length, parser.have_prefix_error = mavlink.HEADER_LEN_V1 + 2, False
    try:
        msgs = parser.parse_buffer(data) or []
    except Exception as exc:  # the parser must never kill the link
        msgs = [mavlink.MAVLink_bad_data(bytearray(data), f"parser error: {exc}")]
    if parser.buf_len() > 0:  # a truncated frame at the end of the datagram
        msgs.append(mavlink.MAVLink_bad_data(bytearray(parser.buf[parser.buf_index:]), "truncated"))
    return list(msgs)

SIGNING_EPOCH_S = 1420070400
"""MAVLink 2 signing timestamps count 10 us units from 2015-01-01 00:00 UTC."""
SIGNING_NEW_STREAM_S = 60.0
"""A stream not seen before is accepted when its timestamp is at most this far behind ours (MAVLink's rule)."""


def signing_timestamp(now: float | None = None) -> int:
    """Now in MAVLink 2 signing units (10 us since 2015), so a restarted bridge never goes back in time."""
    return int((max(time.time() if now is None else now, SIGNING_EPOCH_S) - SIGNING_EPOCH_S) * 100_000)


def _check_signature(self: Any, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
    """pymavlink's MAVLink.check_signature in the right order: the signature first, then the timestamp rules.

    pymavlink (2.4.50) stores a stream's timestamp before it compares signatures, so one forged frame with a
    far-future timestamp would make every real frame of that stream "old" and lock the autopilot out."""
    signing = self.signing
    h = hashlib.sha256()
    h.update(signing.secret_key)
    h.update(msgbuf[:-6])
    if not hmac.compare_digest(h.digest()[:6], bytes(msgbuf[-6:])):
        return False
    tlow, thigh = struct.unpack("<IH", bytes(msgbuf[-12:-6]))
    timestamp = tlow + (thigh << 32)
    stream = (msgbuf[-13], src_system, src_component)
    last = signing.stream_timestamps.get(stream)
    if last is not None and timestamp <= last:
        return False  # a replay, or frames out of order
    if last is None and timestamp + int(SIGNING_NEW_STREAM_S * 100_000) < signing.timestamp:
        return False  # a new stream from the past: a recording replayed later
    signing.stream_timestamps[stream] = timestamp
    signing.timestamp = max(signing.timestamp, timestamp)
    return True


def enable_signing(mav: Any, key: bytes, *, link_id: int = 0, sign_outgoing: bool = True) -> None:
    """MAVLink 2 signing on one pymavlink MAVLink object: sign what it packs, accept only frames signed with
    `key` (unsigned and MAVLink 1 frames come out as BAD_DATA 'Invalid signature' under robust parsing)."""
    mav.signing.secret_key = key
    mav.signing.link_id = link_id
    mav.signing.timestamp = signing_timestamp()
    mav.signing.sign_outgoing = sign_outgoing
    mav.signing.allow_unsigned_callback = None
    mav.check_signature = types.MethodType(_check_signature, mav)


class _PeerWriter:
    """Stands in for `mav.file`: on UDP server links, send only to the peer we locked onto.

    pymavlink's udpin replies to whoever sent the last datagram, so one stray packet would redirect our
    setpoints; once the autopilot's address is known, nothing else can."""

    def __init__(self, conn: Any) -> None:
        self.conn = conn
        self.peer: tuple[str, int] | None = None

    def write(self, buf: bytes) -> None:
        port = getattr(self.conn, "port", None)
        if self.peer is not None and port is not None and hasattr(port, "sendto"):
            port.sendto(buf, self.peer)
        else:
            self.conn.write(buf)


class MavlinkLink:
    """Owns the pymavlink connection. `start(loop, on_message)` runs the reader thread; `send(...)` is safe
    from any thread."""

    def __init__(self, connection: str, *, baud: int = 921600, source_system: int = 1,
                 source_component: int = px4.MAV_COMP_ID_ONBOARD_COMPUTER, signing_key: bytes | None = None) -> None:
        self.connection = connection
        self.signing_key = signing_key
        device, baud = parse_connection(connection, baud)
        try:
            if device.startswith(UDP_TCP_SCHEMES):
                self.conn = mavutil.mavlink_connection(device, baud=baud, source_system=source_system,
                                                       source_component=source_component, autoreconnect=True)
            else:
                # A serial device opened as one: pymavlink's mavlink_connection takes any name with a ':' for a
                # UDP address, and every /dev/serial/by-path/... name has several.
                self.conn = mavutil.mavserial(device, baud=baud, source_system=source_system,
                                              source_component=source_component, autoreconnect=True)
        except Exception as exc:
            raise MavlinkError(f"could not open MAVLink connection {connection!r}: {exc}. Check the port is "
                               "free (UDP) or the device exists and is readable (serial).") from exc
        self._writer = _PeerWriter(self.conn)
        self.conn.mav.file = self._writer
        self.conn.mav.robust_parsing = True  # garbage becomes BAD_DATA instead of an exception
        if signing_key is not None:
            enable_signing(self.conn.mav, signing_key)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.sent = 0
        self.send_errors = 0

    @property
    def mav(self) -> Any:
        return self.conn.mav

    @property
    def peer(self) -> tuple[str, int] | None:
        return self._writer.peer

    def lock_peer(self, addr: tuple[str, int] | None) -> None:
        """Send only to `addr` from now on (UDP); None restores pymavlink's behaviour."""
        self._writer.peer = addr

    @property
    def signing(self) -> bool:
        return self.signing_key is not None

    @property
    def is_udp(self) -> bool:
        return isinstance(self.conn, mavutil.mavudp)

    def _receive_parser(self) -> Any:
        """The UDP reader's own parser (datagram by datagram), checking signatures when signing is on."""
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        if self.signing_key is not None:
            enable_signing(parser, self.signing_key, sign_outgoing=False)
        return parser

    def _follow_timestamp(self, parser: Any) -> None:
        """With signing, what we send next is never older than what we accepted (MAVLink's timestamp rule)."""
        if self.signing_key is not None:
            with self._lock:
                self.conn.mav.signing.timestamp = max(self.conn.mav.signing.timestamp, parser.signing.timestamp)

    def start(self, loop: asyncio.AbstractEventLoop,
              on_message: Callable[[Any, tuple[str, int] | None, float], None]) -> None:
        """Run the reader thread; `on_message(msg, source_address, monotonic_time)` is called on `loop`."""

        def deliver(msg: Any, addr: tuple[str, int] | None) -> bool:
            try:
                loop.call_soon_threadsafe(on_message, msg, addr, time.monotonic())
                return True
            except RuntimeError:  # loop closed: we are shutting down
                return False

        def read_udp() -> None:
            # Datagram by datagram so every message carries the address it really came from (pymavlink's
            # own reader forgets it), with a fresh parser state so garbage cannot bleed into the next one.
            parser = self._receive_parser()
            sock = self.conn.port
            while not self._stop.is_set():
                try:
                    ready, _, _ = select.select([sock], [], [], 0.1)
                    if not ready:
                        continue
                    data, addr = sock.recvfrom(65535)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError as exc:
                    if self._stop.is_set():
                        return
                    log.warning("UDP read error on %s: %s", self.connection, exc)
                    time.sleep(0.1)
                    continue
                msgs = _parse_datagram(parser, data)
                self._follow_timestamp(parser)
                for m in msgs:
                    if not deliver(m, addr):
                        return

        def read_stream() -> None:
            while not self._stop.is_set():
                try:
                    msg = self.conn.recv_match(blocking=True, timeout=0.1)
                except Exception as exc:  # a broken serial port or a parser bug must not kill the thread
                    log.warning("MAVLink read error on %s: %s", self.connection, exc)
                    time.sleep(0.1)
                    continue
                if msg is not None and not deliver(msg, None):
                    return

        target = read_udp if self.is_udp else read_stream
        self._thread = threading.Thread(target=target, name="mavlink-reader", daemon=True)
        self._thread.start()

    def send(self, msg: Any) -> bool:
        """Send one MAVLink message; False (and logged by the caller) when the OS refused it."""
        try:
            with self._lock:
                self.conn.mav.send(msg)
            self.sent += 1
            return True
        except OSError as exc:
            self.send_errors += 1
            if self.send_errors in (1, 10, 100) or self.send_errors % 1000 == 0:
                log.warning("MAVLink send failed (%d so far): %s", self.send_errors, exc)
            return False

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        with contextlib.suppress(Exception):
            self.conn.close()
