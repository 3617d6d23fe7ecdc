"""Conformance check of a running service against the declared contract, in the spirit of Gymnasium's
`check_env`: every real service and every test fake must pass it.

For a service name, the declarations in `shared/keys.py` say what it must do: the topics it publishes
(periodic ones must show a sample within the timeout, and every sample must decode to the declared type),
the queryables it serves (each must answer a malformed request with an error or a valid reply, never
time out; a queryable without a request body must answer with its declared reply type), its liveliness
token and its health. The action queryables also get a valid request that the contract says must be
refused, never run (`VALID_PROBES`: a skill goal naming no skill, a cancel of a goal nobody sent); the
reply must decode and refuse with a reason. With `library` (the live skill library), every skill a status
or a reasoning step names must be in it. `check_service` returns a report; `Report.raise_for_failures()`
makes it an assert.
"""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import dataclass, field
from typing import Any

from shared.bus import Bus, Subscription, check_vehicle, decoder
from shared.errors import AermaniError, NoResponder, QueryTimeout, RemoteError
from shared.keys import ALIVE_TOKEN, HEALTH_TOPIC, Keys, Protobuf, Query, Topic, declared_by
from shared.messages import CancelGoal, ReasoningStep, SkillLibrary, SkillRequest, SkillStatus
from shared.sensors import PROTO_TYPES, decode_proto

MALFORMED = b"\x00 this is not a valid request \xff"
PROBE_SKILL = "conformance_probe_no_such_skill"
VALID_PROBES: dict[str, Any] = {
    "executor/run_skill": SkillRequest(skill=PROBE_SKILL, task_id="conformance"),
    "executor/check_skill": SkillRequest(skill=PROBE_SKILL, task_id="conformance"),
    "executor/cancel_skill": CancelGoal(goal_id="conformance-unknown-goal", reason="conformance probe",
                                        source="conformance"),
    "reasoner/cancel_task": CancelGoal(goal_id="conformance-unknown-task", reason="conformance probe",
                                       source="conformance"),
}
"""Valid requests each action server (and the executor's check) must refuse (with `accepted=False` and a
reason), by key name."""


@dataclass
class Finding:
    """One check on one key."""

    key: str
    ok: bool
    detail: str


@dataclass
class Report:
    """What `check_service` found for one service."""

    service: str
    vehicle_id: str
    findings: list[Finding] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return all(f.ok for f in self.findings)

    def add(self, key: str, ok: bool, detail: str) -> None:
        self.findings.append(Finding(key, ok, detail))

    def summary(self) -> str:
        lines = [f"{self.service} on {self.vehicle_id}: {'conforms' if self.ok else 'DOES NOT CONFORM'}"]
        lines += [f"  {'ok  ' if f.ok else 'FAIL'} {f.key}: {f.detail}" for f in self.findings]
        return "\n".join(lines)

    def raise_for_failures(self) -> None:
        if not self.ok:
            raise AssertionError(self.summary())


def _decode(decl: Topic[Any], data: bytes) -> Any:
    if isinstance(decl.type, Protobuf):
        return decode_proto(PROTO_TYPES[decl.type.full_name], data)
    return decoder(decl.type)(data)


async def _check_topic(bus: Bus, keys: Keys, decl: Topic[Any], report: Report, timeout: float,
                       library: SkillLibrary | None, require: bool) -> None:
    key = decl.bind(keys.vehicle_id).key
    sub: Subscription[bytes] = bus.subscribe(key, maxsize=50)  # raw bytes: the check decodes itself to name the problem
    try:
        got: list[Any] = []
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while loop.time() < deadline and len(got) < 3:
            try:
                data = await sub.recv(timeout=max(0.05, deadline - loop.time()))
            except TimeoutError:
                break
            try:
                value = _decode(decl, data)
                check_vehicle(key, value)  # every subscriber refuses another vehicle's sample
                got.append(value)
            except AermaniError as exc:
                report.add(key, False, f"a sample does not decode as {getattr(decl.type, '__name__', decl.type)}: "
                                       f"{exc}")
                return
        if not got:
            if require and decl.periodic:
                report.add(key, False, f"periodic topic: no sample within {timeout:.1f} s")
            return
        if library is not None:
            names = {s.name for s in library.skills}
            used = [s.skill for s in got if isinstance(s, SkillStatus) and s.skill != PROBE_SKILL]
            used += [s.ste.skill for s in got if isinstance(s, ReasoningStep) and s.ste is not None]
            bad = [n for n in used if n not in names]
            if bad:
                report.add(key, False, f"names skills that are not in the library: {sorted(set(bad))}")
                return
        report.add(key, True, f"{len(got)} valid sample(s)")
    finally:
        sub.close()


async def _check_query(bus: Bus, keys: Keys, decl: Query[Any, Any], report: Report, timeout: float) -> None:
    target = decl.bind(keys.vehicle_id)
    key = target.key
    if decl.request is None:
        try:
            reply: Any = await bus.query(target, None, timeout=timeout)
        except (NoResponder, QueryTimeout) as exc:
            report.add(key, False, f"no answer: {exc}")
            return
        except AermaniError as exc:
            report.add(key, False, f"answered with an error or a malformed reply: {exc}")
            return
        report.add(key, True, f"answers with {type(reply).__name__}")
        return
    try:
        replies = await bus.query_all(key, MALFORMED, timeout=timeout, first_only=True)
    except QueryTimeout:
        replies = []
    if not replies:
        report.add(key, False,
                   f"no answer to a malformed request within {timeout:.1f} s (nobody serves it, or it hung)")
        return
    ok, data = replies[0]
    if not ok:
        report.add(key, True, "a malformed request gets an error reply: " + data.decode(errors="replace")[:80])
        return
    try:
        reply = decoder(decl.reply)(data)
    except AermaniError as exc:
        report.add(key, False, f"a malformed request got a reply that is not a {decl.reply}: {exc}")
        return
    report.add(key, True, f"a malformed request gets a structured refusal ({type(reply).__name__})")


async def _check_valid_probe(bus: Bus, keys: Keys, decl: Query[Any, Any], report: Report, timeout: float) -> None:
    target = decl.bind(keys.vehicle_id)
    try:
        reply: Any = await bus.query(target, VALID_PROBES[decl.name], timeout=timeout)
    except AermaniError as exc:
        report.add(target.key, False, f"a valid request got no structured reply: {exc}")
        return
    if getattr(reply, "accepted", True) or not getattr(reply, "reason", ""):
        report.add(target.key, False, f"accepted a request it must refuse, or refused it without a reason: {reply!r}")
        return
    report.add(target.key, True, f"a valid request it must refuse is refused: {reply.reason[:80]}")


async def check_service(bus: Bus, service: str, vehicle_id: str = "am1", *, timeout: float = 5.0,
                        expect_alive: bool = True, expect_health: bool = False, require_periodic: bool = True,
                        library: SkillLibrary | None = None, skip: tuple[str, ...] = ()) -> Report:
    """Check the running `service` of `vehicle_id` against its declarations. `skip` names declarations
    (by key name) that this deployment of the service legitimately leaves out, e.g. `camera/@segmentation`
    for a camera that has no oracle."""
    keys = Keys(vehicle_id)
    report = Report(service, vehicle_id)
    if expect_alive:
        token = ALIVE_TOKEN.bind(vehicle_id, service=service).key
        alive = await bus.alive(token, timeout=timeout)
        report.add(token, bool(alive), "liveliness token present" if alive else "no liveliness token")
    topics, queries = declared_by(service)
    checks = [_check_topic(bus, keys, t, report, timeout, library, require_periodic) for t in topics
              if t.name not in skip]
    if expect_health:
        health = HEALTH_TOPIC.bind(vehicle_id, service=service)
        periodic_health: Topic[Any] = Topic(health.key.split("/", 3)[3], HEALTH_TOPIC.type, HEALTH_TOPIC.doc, service,
                                periodic=True)
        checks.append(_check_topic(bus, keys, periodic_health, report, max(timeout, 3.0), None, True))
    await asyncio.gather(*checks)
    for q in queries:
        if q.name not in skip:
            with contextlib.suppress(RemoteError):
                await _check_query(bus, keys, q, report, timeout)
            if q.name in VALID_PROBES:
                await _check_valid_probe(bus, keys, q, report, timeout)
    if not report.findings:
        report.add(service, False, "the declarations name nothing this service does: is the name right?")
    return report
