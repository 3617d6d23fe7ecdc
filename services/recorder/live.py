"""The recorder's live view for the Foxglove app: the Foxglove WebSocket protocol (v1, subscribe and stream)
with the handshake checks foxglove-sdk's server lacks. Its `start_server` (0.30) takes no Origin check and no
credential, so any web page the operator opened could read the camera and the vehicle's state; this server
refuses a handshake whose `Origin` is not listed exactly (`null` included) and, with a token, one that does not
carry it (`?token=` in the URL, since a browser's WebSocket cannot send headers, or `Authorization: Bearer`).

It runs on its own threads: the writer thread hands it samples through `log`, which never blocks (each client
has a bounded queue; a slow client loses messages, counted, and never stalls the recording)."""

from __future__ import annotations

import base64
import hmac
import json
import logging
import queue
import struct
import threading
import time
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qs, urlsplit

from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response
from websockets.sync.server import ServerConnection, serve

from shared.mcaplog import channel_spec

log = logging.getLogger("aermani.recorder.live")

SUBPROTOCOL = "foxglove.websocket.v1"
MESSAGE_DATA = 0x01  # binary opcode of a message on a subscription
_STOP = object()


@dataclass(frozen=True)
class Channel:
    """One advertised channel: a key with one encoding."""

    id: int
    topic: str
    encoding: str
    schema_name: str
    schema: str
    schema_encoding: str

    def advert(self) -> dict[str, Any]:
        return {"id": self.id, "topic": self.topic, "encoding": self.encoding, "schemaName": self.schema_name,
                "schema": self.schema, "schemaEncoding": self.schema_encoding}


def _channel(cid: int, key: str, encoding: str) -> Channel:
    spec = channel_spec(encoding)
    if not spec.has_schema:
        return Channel(cid, key, spec.message_encoding, "", "", "")
    # Foxglove takes a protobuf schema (a FileDescriptorSet) base64-encoded and a JSON schema as text.
    data = spec.schema_data
    schema = base64.b64encode(data).decode() if spec.schema_encoding == "protobuf" else data.decode()
    return Channel(cid, key, spec.message_encoding, spec.schema_name, schema, spec.schema_encoding)


class _Client:
    def __init__(self, conn: ServerConnection, backlog: int) -> None:
        self.conn = conn
        self.subs: dict[int, int] = {}
        """Subscription id by channel id (the client chooses the ids)."""
        self.out: queue.Queue[Any] = queue.Queue(maxsize=backlog)
        self.dropped = 0

    def put(self, item: Any) -> None:
        try:
            self.out.put_nowait(item)
        except queue.Full:
            self.dropped += 1


class LiveServer:
    """Serve every sample given to `log` to Foxglove clients that passed the handshake checks."""

    def __init__(self, host: str, port: int, *, token: str | None, allowed_origins: list[str],
                 backlog: int = 256, name: str = "aermani recorder") -> None:
        self.token = token.encode() if token is not None else None
        self.allowed = set(allowed_origins)
        self.backlog = backlog
        self.name = name
        self.session = str(time.time_ns())
        self.refused = 0
        self._lock = threading.Lock()
        self._channels: dict[tuple[str, str], Channel] = {}
        self._clients: set[_Client] = set()
        self._server = serve(self._handle, host, port, subprotocols=[SUBPROTOCOL],  # type: ignore[list-item]
                             process_request=self._check, compression=None, max_size=65536)
        self.port = int(self._server.socket.getsockname()[1])
        self._thread = threading.Thread(target=self._server.serve_forever, name="foxglove-live", daemon=True)
        self._thread.start()

    # ---- handshake

    def _check(self, conn: ServerConnection, request: Request) -> Response | None:
        origin = request.headers.get("Origin")
        if origin is not None and origin not in self.allowed:
            self.refused += 1
            log.warning("Foxglove live view: refused a connection from origin %r (not in "
                        "AERMANI_RECORDER_FOXGLOVE_ALLOWED_ORIGINS)", origin[:100])
            return conn.respond(403, f"origin {origin[:100]!r} is not allowed: "
                                     "AERMANI_RECORDER_FOXGLOVE_ALLOWED_ORIGINS lists the exact origins allowed\n")
        if self.token is not None:
            given = parse_qs(urlsplit(request.path).query).get("token", [""])[0]
            auth = request.headers.get("Authorization", "")
            if not given and auth.startswith("Bearer "):
                given = auth[7:]
            if not hmac.compare_digest(given.encode("utf-8", "replace"), self.token):
                self.refused += 1
                log.warning("Foxglove live view: refused a connection without the right token")
                return conn.respond(401, "missing or wrong token: connect to ws://<host>:<port>/?token=<"
                                         "AERMANI_RECORDER_FOXGLOVE_TOKEN>\n")
        return None

    # ---- connections

    def _handle(self, conn: ServerConnection) -> None:
        if conn.subprotocol != SUBPROTOCOL:
            conn.close(1002, f"this server speaks the {SUBPROTOCOL} subprotocol only")
            return
        client = _Client(conn, self.backlog)
        with self._lock:  # the snapshot and the registration together: a new channel is in one or the other
            self._clients.add(client)
            known = [ch.advert() for ch in self._channels.values()]
        sender = threading.Thread(target=self._send, args=(client,), name="foxglove-live-send", daemon=True)
        try:
            conn.send(json.dumps({"op": "serverInfo", "name": self.name, "capabilities": [],
                                  "sessionId": self.session}))
            conn.send(json.dumps({"op": "advertise", "channels": known}))
            sender.start()
            for message in conn:
                if isinstance(message, str):
                    self._on_request(client, message)
        except ConnectionClosed:
            pass
        finally:
            with self._lock:
                self._clients.discard(client)
            while True:  # make room for the stop marker: whatever is queued is not sent any more
                try:
                    client.out.put_nowait(_STOP)
                    break
                except queue.Full:
                    client.out.get_nowait()
            if sender.is_alive():
                sender.join(5.0)

    def _send(self, client: _Client) -> None:
        while True:
            item = client.out.get()
            if item is _STOP:
                return
            try:
                client.conn.send(item)
            except ConnectionClosed:
                return

    def _on_request(self, client: _Client, text: str) -> None:
        try:
            req = json.loads(text)
            op = req.get("op")
            if op == "subscribe":
                with self._lock:
                    ids = {ch.id for ch in self._channels.values()}
                for sub in req.get("subscriptions", []):
                    cid, sid = int(sub["channelId"]), int(sub["id"])
                    if cid in ids and sid not in client.subs.values():
                        client.subs[cid] = sid
            elif op == "unsubscribe":
                gone = {int(s) for s in req.get("subscriptionIds", [])}
                client.subs = {c: s for c, s in client.subs.items() if s not in gone}
        except (ValueError, TypeError, KeyError, AttributeError) as exc:
            client.put(json.dumps({"op": "status", "level": 2, "message": f"bad request: {exc}"[:200]}))

    # ---- data (writer thread)

    def log(self, key: str, encoding: str, payload: bytes | memoryview, log_time_ns: int) -> None:
        """Stream one sample to its subscribers, advertising its channel first if it is new. Never blocks."""
        with self._lock:
            ch = self._channels.get((key, encoding))
            new = ch is None
            if ch is None:
                ch = self._channels[(key, encoding)] = _channel(len(self._channels) + 1, key, encoding)
            clients = list(self._clients)
        for c in clients:
            if new:
                c.put(json.dumps({"op": "advertise", "channels": [ch.advert()]}))
            sid = c.subs.get(ch.id)
            if sid is not None:
                c.put(struct.pack("<BIQ", MESSAGE_DATA, sid, log_time_ns) + bytes(payload))

    def stop(self) -> None:
        self._server.shutdown()
        with self._lock:
            clients = list(self._clients)
        for c in clients:
            c.conn.close(1001, "recorder stopping")
        self._thread.join(5.0)
