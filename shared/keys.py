"""The Zenoh key space of aermani, declared once: every key with its kind and its message type(s).

A key is `aermani/v1/<vehicle_id>/<name>`. Each name below is a declaration object: a `Topic` (a
publication and the type of its samples), a `Query` (a queryable with its request and reply types) or a
`Token` (a liveliness token). `Keys("am2").autopilot_state` binds a declaration to a vehicle; the bus
takes the bound declaration and infers every type from it, so no call site names a type again.
`docs/architecture.md`'s key table is generated from `DECLARATIONS` (`python -m shared.keydoc`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Generic, Self, TypeVar

from pydantic import BaseModel

from shared.messages import (
    Abort,
    AbortAck,
    ApprovalDecision,
    ApprovalStatus,
    AutopilotCommand,
    AutopilotResult,
    CancelGoal,
    CancelReply,
    Detections,
    GoalRef,
    Health,
    Heartbeat,
    JudgeRequest,
    JudgeResult,
    LocalizeRequest,
    MemoryRestore,
    ObjectEstimate,
    PlacementEstimate,
    PreflightReport,
    ReasoningStep,
    ResetNotice,
    Scenario,
    SimLabels,
    SimResetResult,
    SimState,
    SkillAccept,
    SkillLibrary,
    SkillRequest,
    SkillStatus,
    TaskAccept,
    TaskRequest,
    TaskStatus,
    VehicleState,
    WorkingMemory,
)

ROOT = "aermani/v1"
DEFAULT_VEHICLE_ID = "am1"
FLEET_ID = "fleet"
"""Reserved in place of a vehicle id: keys under `aermani/v1/fleet/` address every vehicle at once."""
ALIVE = "alive"
HEALTH = "health"
HEARTBEAT = "heartbeat"

M = TypeVar("M")
Req = TypeVar("Req")
Rep = TypeVar("Rep")


@dataclass(frozen=True)
class Protobuf:
    """A sensor payload in one of Foxglove's protobuf schemas; it travels (and is received) as bytes."""

    full_name: str
    """Protobuf full name, e.g. `foxglove.CompressedImage`."""

    @property
    def __name__(self) -> str:  # read by error messages like a model's name
        return self.full_name


@dataclass(frozen=True)
class Json:
    """Free-form JSON (a dict of figures); used only by diagnostics keys."""

    description: str

    @property
    def __name__(self) -> str:
        return "JSON"


def type_name(t: Any) -> str:
    """Human name of a declared payload type: `VehicleState`, `foxglove.RawImage`, `ArmCommand | ...`."""
    if t is None:
        return "(empty)"
    if isinstance(t, Protobuf):
        return t.full_name
    if isinstance(t, Json):
        return f"JSON ({t.description})"
    if isinstance(t, type):
        return t.__name__
    args = getattr(t, "__args__", None)
    if args:  # Annotated[Union[...], Field(...)] or a plain union
        inner = args[0] if getattr(t, "__metadata__", None) else t
        members = getattr(inner, "__args__", (inner,))
        return " | ".join(type_name(a) for a in members)
    return str(t)


MESSAGE_MAX_BYTES = 1 << 20
"""Default size cap of a JSON message sample (1 MiB: a ReasoningStep with its prompt is tens of KiB)."""
FRAME_MAX_BYTES = 32 << 20
"""Default size cap of a protobuf sample and of a plain key's raw bytes (32 MiB: an uncompressed 1080p RGB-D
pair is 10 MiB)."""


def max_bytes_of(t: Any, declared: int | None = None) -> int:
    """The size cap of a sample of declared type `t` (None: raw bytes on a plain key)."""
    if declared is not None:
        return declared
    return FRAME_MAX_BYTES if t is None or isinstance(t, Protobuf) else MESSAGE_MAX_BYTES


def schema_name(t: Any) -> str | None:
    """The Zenoh encoding schema a payload of declared type `t` is sent with (None when it varies)."""
    if isinstance(t, Protobuf):
        return t.full_name
    if isinstance(t, type) and issubclass(t, BaseModel):
        fn = getattr(t, "full_schema_name", None)
        return fn() if fn else f"aermani.{t.__name__}"
    return None


@dataclass(frozen=True)
class Topic(Generic[M]):
    """A publication: who publishes it, and the type of every sample on it."""

    name: str
    """Key after the vehicle prefix; `{service}` is filled in by `Keys.health`."""
    type: Any
    """Sample type: a message model, a union, or a `Protobuf` schema."""
    doc: str
    """What the samples mean."""
    publisher: str
    """Service(s) that publish it."""
    reliable: bool = True
    """False for streams where late is worse than lost (frames, state): congestion drops, express."""
    periodic: bool = False
    """Published on a clock (not only on events): a running publisher must show a sample within seconds."""
    max_bytes: int | None = None
    """Largest sample a subscriber accepts (None: `MESSAGE_MAX_BYTES` for messages, `FRAME_MAX_BYTES` for
    protobuf frames); a larger one is dropped before it is copied or decoded, and counted."""

    kind = "pub"

    def bind(self, vehicle_id: str, **params: str) -> BoundTopic[M]:
        return BoundTopic(f"{vehicle_prefix(vehicle_id)}/{self.name.format(**params)}", self)

    def fleet(self, **params: str) -> BoundTopic[M]:
        """The same topic on every vehicle (`aermani/v1/*/<name>`), for fleet-wide subscribers."""
        return BoundTopic(f"{ROOT}/*/{self.name.format(**params)}", self)


@dataclass(frozen=True)
class Query(Generic[Req, Rep]):
    """A queryable: the request it takes and the reply it gives."""

    name: str
    request: Any
    """Request type (None: no body)."""
    reply: Any
    """Reply type."""
    doc: str
    server: str
    """Service that answers it."""

    kind = "query"

    def bind(self, vehicle_id: str) -> BoundQuery[Req, Rep]:
        return BoundQuery(f"{vehicle_prefix(vehicle_id)}/{self.name}", self)


@dataclass(frozen=True)
class Token:
    """A liveliness token: present while its owner's session is alive."""

    name: str
    doc: str
    owner: str

    kind = "liveliness"

    def bind(self, vehicle_id: str, **params: str) -> BoundToken:
        return BoundToken(f"{vehicle_prefix(vehicle_id)}/{self.name.format(**params)}", self)


class _Bound(str):
    """A full key (a `str`, usable wherever a key string is) that also carries its declaration."""

    decl: Any

    def __new__(cls, key: str, decl: Any) -> Self:
        obj = super().__new__(cls, key)
        obj.decl = decl
        return obj

    @property
    def key(self) -> str:
        return str.__str__(self)


class BoundTopic(_Bound, Generic[M]):
    """A topic on one vehicle (or the fleet); the bus takes its types from `decl`."""

    decl: Topic[M]


class BoundQuery(_Bound, Generic[Req, Rep]):
    """A queryable on one vehicle; the bus takes its request and reply types from `decl`."""

    decl: Query[Req, Rep]


class BoundToken(_Bound):
    """A liveliness token key on one vehicle."""

    decl: Token


class _TopicOn(Generic[M]):
    """`Keys(...).<name>` for a topic: the declaration bound to that vehicle."""

    def __init__(self, decl: Topic[M]) -> None:
        self.decl = decl

    def __get__(self, keys: Keys, owner: type) -> BoundTopic[M]:
        return self.decl.bind(keys.vehicle_id)


class _QueryOn(Generic[Req, Rep]):
    """`Keys(...).<name>` for a queryable: the declaration bound to that vehicle."""

    def __init__(self, decl: Query[Req, Rep]) -> None:
        self.decl = decl

    def __get__(self, keys: Keys, owner: type) -> BoundQuery[Req, Rep]:
        return self.decl.bind(keys.vehicle_id)


# --------------------------------------------------------------------------- the declarations

CAMERA_COLOR: Topic[bytes] = Topic(
    "camera/color", Protobuf("foxglove.CompressedImage"), "colour frame, JPEG", "sim, camera", reliable=False,
    periodic=True)
CAMERA_DEPTH: Topic[bytes] = Topic(
    "camera/depth", Protobuf("foxglove.CompressedImage"),
    "depth, 16-bit PNG (lossless) millimetres, aligned to colour, same stamp",
    "sim, camera", reliable=False, periodic=True)
CAMERA_CALIBRATION: Topic[bytes] = Topic(
    "camera/calibration", Protobuf("foxglove.CameraCalibration"), "pinhole intrinsics of the colour camera",
    "sim, camera", periodic=True)
CAMERA_SEGMENTATION: Topic[bytes] = Topic(
    "camera/@segmentation", Protobuf("foxglove.RawImage"),
    "16UC1 instance ids (oracle only; a verbatim chunk: `**` does not match it, so only an explicit subscriber such"
    " as the oracle segmenter makes the simulator render it, and the recorder takes it only when asked)", "sim",
    reliable=False, periodic=True)
TF: Topic[bytes] = Topic(
    "tf", Protobuf("foxglove.FrameTransforms"), "world->base_link, base_link->camera, base_link->gripper",
    "autopilot_bridge, sim, camera", reliable=False, periodic=True)
SIM_LABELS: Topic[SimLabels] = Topic(
    "sim/labels", SimLabels, "instance id -> name for camera/@segmentation (oracle only)", "sim",
    periodic=True)
SIM_JUDGE: Query[JudgeRequest, JudgeResult] = Query(
    "sim/judge", JudgeRequest, JudgeResult, "ground-truth judge (evaluation only; no policy may read it)", "sim")
SIM_RESET: Query[Scenario, SimResetResult] = Query(
    "sim/reset", Scenario, SimResetResult, "lay out a new scenario (evaluation)", "sim")
SIM_STATS: Query[Any, dict[str, Any]] = Query(
    "sim/stats", Json("optional 'reset'"), Json("figures"), "setpoint intervals, fps, MAVLink counters", "sim")
SIM_FAULT: Query[Any, dict[str, Any]] = Query(
    "sim/fault", Json("{unit: camera | mavlink_signal, type: off | stuck | ok, duration_s}"), Json("the fault"),
    "failure injection, like PX4 SITL's `failure` command (fault-injection tests only)", "sim")
SIM_RESET_NOTICE: Topic[ResetNotice] = Topic(
    "sim/reset_notice", ResetNotice, "the world was reset: forget what was held and seen", "sim")
SIM_STATE: Topic[SimState] = Topic(
    "sim/state", SimState, "the simulator's whole state when a skill ended (where `aermani fork` starts)", "sim")
AUTOPILOT_STATE: Topic[VehicleState] = Topic(
    "autopilot/state", VehicleState, "pose, velocity, armed, mode, landed state, battery, gripper, link health",
    "autopilot_bridge", reliable=False, periodic=True)
AUTOPILOT_PREFLIGHT: Topic[PreflightReport] = Topic(
    "autopilot/preflight", PreflightReport, "each preflight verdict: the take-off gate, on request, the operator's",
    "autopilot_bridge, aermani preflight")
AUTOPILOT_COMMAND: Query[AutopilotCommand, AutopilotResult] = Query(
    "autopilot/command", AutopilotCommand, AutopilotResult, "arm, takeoff, goto, hold, land, gripper",
    "autopilot_bridge")
PERCEPTION_LOCALIZE_OBJECT: Query[LocalizeRequest, ObjectEstimate] = Query(
    "perception/localize_object", LocalizeRequest, ObjectEstimate, "obj_localization", "perception")
PERCEPTION_LOCALIZE_PLACEMENT: Query[LocalizeRequest, PlacementEstimate] = Query(
    "perception/localize_placement", LocalizeRequest, PlacementEstimate, "placement_localization", "perception")
PERCEPTION_DETECTIONS: Topic[Detections] = Topic(
    "perception/detections", Detections, "what is visible now", "perception", periodic=True)
EXECUTOR_RUN_SKILL: Query[SkillRequest, SkillAccept] = Query(
    "executor/run_skill", SkillRequest, SkillAccept, "skill goal -> accepted/rejected (action protocol)",
    "executor")
EXECUTOR_CHECK_SKILL: Query[SkillRequest, SkillAccept] = Query(
    "executor/check_skill", SkillRequest, SkillAccept,
    "could this skill start now (run_skill's preconditions and envelope)? starts nothing; asked before an approval",
    "executor")
EXECUTOR_CANCEL_SKILL: Query[CancelGoal, CancelReply] = Query(
    "executor/cancel_skill", CancelGoal, CancelReply, "cancel a running skill goal (action protocol)",
    "executor")
EXECUTOR_SKILL_RESULT: Query[GoalRef, SkillStatus] = Query(
    "executor/skill_result", GoalRef, SkillStatus,
    "the latest status of a skill goal, its result once ended (action protocol: what a client whose subscription "
    "was still on its way missed)", "executor")
EXECUTOR_SKILL_STATUS: Topic[SkillStatus] = Topic(
    "executor/skill_status", SkillStatus, "feedback and result of each skill goal", "executor")
EXECUTOR_SKILLS: Query[None, SkillLibrary] = Query(
    "executor/skills", None, SkillLibrary, "the live skill library", "executor")
EXECUTOR_MEMORY: Topic[WorkingMemory] = Topic(
    "executor/memory", WorkingMemory, "working memory: localized objects, placements, held object", "executor",
    periodic=True)
EXECUTOR_RESTORE_MEMORY: Query[MemoryRestore, CancelReply] = Query(
    "executor/restore_memory", MemoryRestore, CancelReply,
    "put a recorded working memory back for a task (`aermani fork`); refused while a skill runs", "executor")
REASONER_START_TASK: Query[TaskRequest, TaskAccept] = Query(
    "reasoner/start_task", TaskRequest, TaskAccept, "task goal -> accepted/rejected (action protocol)",
    "reasoner")
REASONER_CANCEL_TASK: Query[CancelGoal, CancelReply] = Query(
    "reasoner/cancel_task", CancelGoal, CancelReply, "cancel a running task (action protocol)", "reasoner")
REASONER_TASK_RESULT: Query[GoalRef, TaskStatus] = Query(
    "reasoner/task_result", GoalRef, TaskStatus,
    "the latest status of a task, its result once ended (action protocol: what a client whose subscription was "
    "still on its way missed)", "reasoner")
REASONER_STEP: Topic[ReasoningStep] = Topic(
    "reasoner/step", ReasoningStep, "every reasoning step: DRT, STE, raw answer, latency", "reasoner")
REASONER_TASK_STATUS: Topic[TaskStatus] = Topic(
    "reasoner/task_status", TaskStatus, "feedback and result of each task", "reasoner (the gateway: the end of a "
    "task whose reasoner died)")
REASONER_APPROVAL: Topic[ApprovalStatus] = Topic(
    "reasoner/approval", ApprovalStatus, "operator approval of a critical skill: pending, then decided",
    "reasoner")
REASONER_DECIDE_APPROVAL: Query[ApprovalDecision, CancelReply] = Query(
    "reasoner/decide_approval", ApprovalDecision, CancelReply, "approve or reject a pending skill", "reasoner")
SAFETY_ABORT: Topic[Abort] = Topic("safety/abort", Abort, "stop: hold and end the task (anyone)", "any")
SAFETY_ABORT_ACK: Topic[AbortAck] = Topic(
    "safety/abort_ack", AbortAck, "an abort was obeyed (vehicle commanded to hold)", "executor, autopilot_bridge")
HEALTH_TOPIC: Topic[Health] = Topic(f"{HEALTH}/{{service}}", Health, "a service's health, 1 Hz", "every service")
HEARTBEAT_TOPIC: Topic[Heartbeat] = Topic(
    f"{HEARTBEAT}/{{service}}", Heartbeat, "the service's event loop runs, 2 Hz (a hung one goes quiet)",
    "every service", reliable=False, periodic=True)
ALIVE_TOKEN = Token(f"{ALIVE}/{{service}}", "presence of a service", "every service")

FLEET_ABORT: BoundTopic[Abort] = BoundTopic(f"{ROOT}/{FLEET_ID}/{SAFETY_ABORT.name}", SAFETY_ABORT)
"""The fleet-wide abort: every vehicle's executor, bridge and reasoner obey it as their own."""

DECLARATIONS: tuple[Topic[Any] | Query[Any, Any] | Token, ...] = (
    CAMERA_COLOR, CAMERA_DEPTH, CAMERA_CALIBRATION, CAMERA_SEGMENTATION, TF, SIM_LABELS, SIM_JUDGE, SIM_RESET,
    SIM_STATS, SIM_FAULT, SIM_RESET_NOTICE, SIM_STATE, AUTOPILOT_STATE, AUTOPILOT_PREFLIGHT, AUTOPILOT_COMMAND,
    PERCEPTION_LOCALIZE_OBJECT,
    PERCEPTION_LOCALIZE_PLACEMENT, PERCEPTION_DETECTIONS, EXECUTOR_RUN_SKILL, EXECUTOR_CHECK_SKILL,
    EXECUTOR_CANCEL_SKILL, EXECUTOR_SKILL_RESULT, EXECUTOR_SKILL_STATUS, EXECUTOR_SKILLS, EXECUTOR_MEMORY,
    EXECUTOR_RESTORE_MEMORY,
    REASONER_START_TASK, REASONER_CANCEL_TASK, REASONER_TASK_RESULT, REASONER_STEP,
    REASONER_TASK_STATUS, REASONER_APPROVAL, REASONER_DECIDE_APPROVAL, SAFETY_ABORT, SAFETY_ABORT_ACK, HEALTH_TOPIC,
    HEARTBEAT_TOPIC,
    ALIVE_TOKEN,
)
BY_NAME: dict[str, Topic[Any] | Query[Any, Any] | Token] = {d.name: d for d in DECLARATIONS}


def _serves(decl_owner: str, service: str) -> bool:
    """`"reasoner (the gateway: ...)"` names the reasoner: a parenthesis is a note, not an owner."""
    return service in [o.split("(", 1)[0].strip() for o in decl_owner.split(",")]


def declared_by(service: str) -> tuple[list[Topic[Any]], list[Query[Any, Any]]]:
    """The topics a service publishes and the queryables it serves, by the declarations."""
    topics = [d for d in DECLARATIONS
              if isinstance(d, Topic) and d is not HEALTH_TOPIC and _serves(d.publisher, service)]
    queries = [d for d in DECLARATIONS if isinstance(d, Query) and _serves(d.server, service)]
    return topics, queries


def vehicle_prefix(vehicle_id: str = DEFAULT_VEHICLE_ID) -> str:
    if not vehicle_id or "/" in vehicle_id or any(c in vehicle_id for c in "*$?#"):
        raise ValueError(f"invalid vehicle id {vehicle_id!r}: use letters, digits, '-' or '_'")
    if vehicle_id == FLEET_ID:
        raise ValueError(f"vehicle id {FLEET_ID!r} is reserved for fleet-wide keys (aermani/v1/{FLEET_ID}/...)")
    return f"{ROOT}/{vehicle_id}"


def declaration_of(key: str) -> Topic[Any] | Query[Any, Any] | Token | None:
    """The declaration a full key belongs to (`aermani/v1/am1/health/gateway` -> HEALTH_TOPIC), or None."""
    parts = str(key).split("/")
    if len(parts) < 4 or "/".join(parts[:2]) != ROOT:
        return None
    name = "/".join(parts[3:])
    if name in BY_NAME:
        return BY_NAME[name]
    if parts[3] == HEALTH and len(parts) == 5:
        return HEALTH_TOPIC
    if parts[3] == HEARTBEAT and len(parts) == 5:
        return HEARTBEAT_TOPIC
    if parts[3] == ALIVE and len(parts) == 5:
        return ALIVE_TOKEN
    return None


@dataclass(frozen=True)
class Keys:
    """The declarations bound to one vehicle. `Keys("am2").autopilot_state.key` ->
    `aermani/v1/am2/autopilot/state`."""

    vehicle_id: str = DEFAULT_VEHICLE_ID

    def key(self, suffix: str) -> str:
        return f"{vehicle_prefix(self.vehicle_id)}/{suffix}"

    @property
    def prefix(self) -> str:
        return vehicle_prefix(self.vehicle_id)

    @property
    def all(self) -> str:
        return f"{self.prefix}/**"

    camera_color = _TopicOn(CAMERA_COLOR)
    camera_depth = _TopicOn(CAMERA_DEPTH)
    camera_calibration = _TopicOn(CAMERA_CALIBRATION)
    camera_segmentation = _TopicOn(CAMERA_SEGMENTATION)
    tf = _TopicOn(TF)
    sim_labels = _TopicOn(SIM_LABELS)
    sim_judge = _QueryOn(SIM_JUDGE)
    sim_reset = _QueryOn(SIM_RESET)
    sim_stats = _QueryOn(SIM_STATS)
    sim_fault = _QueryOn(SIM_FAULT)
    sim_reset_notice = _TopicOn(SIM_RESET_NOTICE)
    sim_state = _TopicOn(SIM_STATE)
    autopilot_state = _TopicOn(AUTOPILOT_STATE)
    autopilot_preflight = _TopicOn(AUTOPILOT_PREFLIGHT)
    autopilot_command = _QueryOn(AUTOPILOT_COMMAND)
    localize_object = _QueryOn(PERCEPTION_LOCALIZE_OBJECT)
    localize_placement = _QueryOn(PERCEPTION_LOCALIZE_PLACEMENT)
    detections = _TopicOn(PERCEPTION_DETECTIONS)
    run_skill = _QueryOn(EXECUTOR_RUN_SKILL)
    check_skill = _QueryOn(EXECUTOR_CHECK_SKILL)
    cancel_skill = _QueryOn(EXECUTOR_CANCEL_SKILL)
    skill_result = _QueryOn(EXECUTOR_SKILL_RESULT)
    skill_status = _TopicOn(EXECUTOR_SKILL_STATUS)
    skills = _QueryOn(EXECUTOR_SKILLS)
    memory = _TopicOn(EXECUTOR_MEMORY)
    restore_memory = _QueryOn(EXECUTOR_RESTORE_MEMORY)
    start_task = _QueryOn(REASONER_START_TASK)
    cancel_task = _QueryOn(REASONER_CANCEL_TASK)
    task_result = _QueryOn(REASONER_TASK_RESULT)
    reasoning_step = _TopicOn(REASONER_STEP)
    task_status = _TopicOn(REASONER_TASK_STATUS)
    approval = _TopicOn(REASONER_APPROVAL)
    decide_approval = _QueryOn(REASONER_DECIDE_APPROVAL)
    abort = _TopicOn(SAFETY_ABORT)
    abort_ack = _TopicOn(SAFETY_ABORT_ACK)

    def health(self, service: str) -> BoundTopic[Health]:
        return HEALTH_TOPIC.bind(self.vehicle_id, service=service)

    def heartbeat(self, service: str) -> BoundTopic[Heartbeat]:
        return HEARTBEAT_TOPIC.bind(self.vehicle_id, service=service)

    def alive(self, service: str) -> BoundToken:
        return ALIVE_TOKEN.bind(self.vehicle_id, service=service)


def alive_pattern(vehicle_id: str | None = None) -> str:
    """Liveliness pattern for one vehicle, or for the whole fleet when `vehicle_id` is None."""
    return f"{ROOT}/{vehicle_id or '*'}/{ALIVE}/*"


def heartbeat_pattern() -> str:
    """Every service's heartbeat across the fleet."""
    return f"{ROOT}/*/{HEARTBEAT}/*"


def parse_alive_key(key: str) -> tuple[str, str]:
    """`aermani/v1/am1/alive/executor` -> ("am1", "executor")."""
    parts = str(key).split("/")
    if len(parts) != 5 or parts[3] != ALIVE:
        raise ValueError(f"not a liveliness key: {key!r}")
    return parts[2], parts[4]
