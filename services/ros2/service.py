"""The ROS 2 bridge: republishes one vehicle's bus traffic as ROS 2 topics in rmw_zenoh's wire format, on the
same Zenoh router, and serves `/<vehicle>/start_task` (aermani_msgs/srv/StartTask) as a ROS 2 service.

A ROS 2 Jazzy node with `RMW_IMPLEMENTATION=rmw_zenoh_cpp` that reaches the stack's router (rmw_zenoh's
default, tcp/localhost:7447, is `aermani up`'s router) sees the bridge's node, topics and service in
`ros2 node list`, `ros2 topic echo /am1/pose` and RViz. The bridge declares one liveliness token per
publisher, as rmw_zenoh does, so ROS 2's graph shows them; every publication carries rmw_zenoh's attachment.

What goes out is `shared.ros2.convert.CHANNELS`; a payload the converter cannot read is counted in health and
skipped. A start_task request goes to the gateway's HTTP API like any other client's (the gateway's token,
store and audit apply), and its answer, accepted with the task id or refused with the reason, is the reply.
A request that is not a StartTask (bad CDR, no attachment) gets an error reply and starts nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import secrets
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import httpx

from services.ros2.settings import Ros2Settings
from shared.bus import Bus, RawReply
from shared.messages import Health, now_ns
from shared.ros2.convert import CHANNELS, Channel, Converter, ros_token
from shared.ros2.wire import (
    DEFAULT_QOS,
    SENSOR_QOS,
    attachment,
    data_key,
    endpoint_token,
    node_token,
    parse_attachment,
    rihs01,
    store_name,
    typestore,
)

log = logging.getLogger("aermani.ros2")

SERVICE = "ros2"
START_TASK = "aermani_msgs/srv/StartTask"
CDR = "application/cdr"
IMAGE_SUFFIXES = ("camera/color", "camera/depth")
MAX_REQUEST_BYTES = 8192  # a command is at most 500 characters: a StartTask request is far below this
MAX_T_MAX_S = 3600.0  # the gateway's own bound


@dataclass
class Publisher:
    """One ROS 2 publisher: a channel, its data key and its rmw_zenoh identity."""

    channel: Channel
    topic: str
    key: str
    gid: bytes = field(default_factory=lambda: secrets.token_bytes(16))
    sequence: int = 0


class Bridge:
    """The bridge's state: publishers per aermani key suffix, the node's tokens, counters for health."""

    def __init__(self, bus: Bus, settings: Ros2Settings) -> None:
        self.bus, self.settings = bus, settings
        self.ts = typestore()
        self.convert = Converter(self.ts)
        self.zid = str(bus.session.zid())
        self.counts: Counter[str] = Counter()
        self._entity = 0
        self.publishers: dict[str, list[Publisher]] = {}
        for channel in CHANNELS:
            if channel.suffix in IMAGE_SUFFIXES and not settings.images:
                continue
            topic = channel.topic_for(settings.vehicle_id)
            key = data_key(settings.domain_id, topic, channel.ros_type, rihs01(channel.ros_type, self.ts))
            self.publishers.setdefault(channel.suffix, []).append(Publisher(channel, topic, key))
        self.service_name = f"/{ros_token(settings.vehicle_id)}/start_task"
        self.service_key = data_key(settings.domain_id, self.service_name, START_TASK, rihs01(START_TASK, self.ts))
        headers = {"Accept": "application/json"}
        if settings.gateway_token is not None:
            headers["Authorization"] = f"Bearer {settings.gateway_token.get_secret_value()}"
        self.http = httpx.AsyncClient(base_url=settings.gateway_url.rstrip("/"), headers=headers,
                                      timeout=settings.start_timeout_s)

    def _next_entity(self) -> int:
        self._entity += 1
        return self._entity

    def declare(self) -> None:
        """The node and its endpoints in ROS 2's graph (liveliness tokens), then the service's queryable."""
        s = self.settings
        self.bus.declare_token(node_token(s.domain_id, self.zid, 0, s.namespace, s.node_name))
        for pubs in self.publishers.values():
            for p in pubs:
                qos = SENSOR_QOS if p.channel.sensor else DEFAULT_QOS
                self.bus.declare_token(endpoint_token(
                    s.domain_id, self.zid, 0, self._next_entity(), "MP", s.namespace, s.node_name, p.topic,
                    p.channel.ros_type, p.key.rsplit("/", 1)[1], qos))
        self.bus.declare_token(endpoint_token(
            s.domain_id, self.zid, 0, self._next_entity(), "SS", s.namespace, s.node_name,
            self.service_name, START_TASK, self.service_key.rsplit("/", 1)[1], DEFAULT_QOS))
        # rmw_zenoh's clients query complete queryables only (target ALL_COMPLETE), as its servers declare.
        self.bus.serve(self.service_key, self.start_task, raw=True, with_attachment=True, complete=True)

    def forward(self, suffix: str, payload: bytes) -> None:
        """Publish one bus sample on every ROS 2 topic its key feeds."""
        for p in self.publishers.get(suffix, ()):
            try:
                cdr = self.ts.serialize_cdr(self.convert.convert(p.channel, payload), p.channel.ros_type)
            except Exception:  # a payload the converter cannot read is counted, never fatal
                self.counts[f"undecodable {suffix}"] += 1
                continue
            p.sequence += 1
            self.bus.publish_raw(p.key, bytes(cdr), CDR, reliable=not p.channel.sensor,
                                 attachment=attachment(p.sequence, now_ns(), p.gid))
            self.counts[p.topic] += 1

    async def start_task(self, data: bytes | None, att: bytes | None) -> RawReply:
        """A ROS 2 StartTask call: the command goes to the gateway; its answer is the reply. A request without
        rmw_zenoh's attachment gets an error reply (there is no caller to answer); any other bad request gets a
        StartTask response that refuses it with the reason, so `ros2 service call` never waits in vain."""
        if att is None:
            raise ValueError("a ROS 2 service request carries rmw_zenoh's attachment (sequence number and gid)")
        sequence, _, gid = parse_attachment(att)
        self.counts["start_task calls"] += 1
        accepted, task_id, reason = await self._answer(data)
        log.info("ROS 2 start_task (caller gid %s, request %d): %s", gid.hex(), sequence,
                 f"task {task_id}" if accepted else reason)
        reply = self.ts.types[store_name(f"{START_TASK}_Response")](accepted=accepted, task_id=task_id,
                                                                    reason=reason)
        cdr = self.ts.serialize_cdr(reply, store_name(f"{START_TASK}_Response"))
        return RawReply(bytes(cdr), CDR, attachment(sequence, now_ns(), gid))

    async def _answer(self, data: bytes | None) -> tuple[bool, str, str]:
        """(accepted, task id, reason) for a request's bytes."""
        if not data or len(data) > MAX_REQUEST_BYTES:
            return False, "", f"a StartTask request is 1 to {MAX_REQUEST_BYTES} bytes of CDR, got {len(data or b'')}"
        try:
            req = self.ts.deserialize_cdr(data, store_name(f"{START_TASK}_Request"))
        except Exception as exc:  # rosbags raises assorted errors on bytes that are not a StartTask_Request
            return False, "", f"not a CDR {START_TASK}_Request: {type(exc).__name__}"
        t_max_s = float(req.t_max_s)
        if t_max_s != 0 and not (math.isfinite(t_max_s) and 0 < t_max_s <= MAX_T_MAX_S):
            return False, "", f"t_max_s must be 0 (the reasoner's default) or in (0, {MAX_T_MAX_S:g}] s, got {t_max_s}"
        return await self._create(str(req.command), t_max_s)

    async def _create(self, command: str, t_max_s: float) -> tuple[bool, str, str]:
        """(accepted, task id, reason) of POST /tasks."""
        body: dict[str, Any] = {"command": command, "vehicle_id": self.settings.vehicle_id}
        if t_max_s > 0:
            body["t_max_s"] = t_max_s
        try:
            r = await self.http.post("/tasks", json=body)
        except httpx.TimeoutException:
            return False, "", (f"the gateway did not answer within {self.settings.start_timeout_s:g} s: the task may "
                               f"have started, see /{ros_token(self.settings.vehicle_id)}/reasoner/task_status")
        except httpx.HTTPError as exc:
            return False, "", f"the gateway at {self.settings.gateway_url} did not answer: {type(exc).__name__}"
        try:
            doc = r.json()
        except ValueError:
            doc = {}
        if r.status_code == 202 and isinstance(doc, dict) and doc.get("task_id"):
            return True, str(doc["task_id"]), ""
        detail = doc.get("detail") if isinstance(doc, dict) else None
        return False, "", f"gateway answered {r.status_code}: {str(detail or r.text)[:300]}"

    def health(self) -> Health:
        return Health(service=SERVICE, ok=True, details={
            "domain_id": self.settings.domain_id, "node": self.settings.node_name,
            "topics": sorted({p.topic for pubs in self.publishers.values() for p in pubs}),
            "counts": dict(self.counts)})


async def run(bus: Bus, settings: Ros2Settings, stop: asyncio.Event) -> None:
    bridge = Bridge(bus, settings)
    bridge.declare()
    prefix = f"aermani/v1/{settings.vehicle_id}/"

    async def pump(suffix: str) -> None:
        images = suffix in IMAGE_SUFFIXES
        sub = bus.subscribe(prefix + suffix, maxsize=2 if images else 100)
        while True:
            bridge.forward(suffix, await sub.recv())

    tasks = [asyncio.create_task(pump(suffix), name=f"ros2 {suffix}") for suffix in bridge.publishers]
    log.info("ROS 2 bridge for %s: node %s, domain %d, %d topics, service %s", settings.vehicle_id,
             settings.node_name, settings.domain_id, sum(len(p) for p in bridge.publishers.values()),
             bridge.service_name)
    try:
        while not stop.is_set():
            for t in tasks:
                if t.done():  # a pump that ended has failed: end the service (the launcher restarts it)
                    raise RuntimeError(f"{t.get_name()} stopped: {t.exception()!r}")
            bus.publish(settings.keys.health(SERVICE), bridge.health())
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), settings.health_period_s)
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await bridge.http.aclose()
