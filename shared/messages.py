"""Versioned, frozen message models for everything on the bus that is not sensor data.

Conventions: world frame ENU, body frame FLU, SI units, yaw in radians (ENU, counter-clockwise from +x),
times in integer nanoseconds since the epoch. Every model has a `kind` literal (the discriminator), a
`schema_version`, and a docstring per field; its JSON schema is the MCAP schema of its channel.
"""

from __future__ import annotations

import math
import time
import uuid
from enum import StrEnum
from typing import Annotated, Any, ClassVar, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

SCHEMA_VERSION = 1
"""Major version of the message schemas. A receiver rejects a message of a newer major version with an
error naming both versions."""
SCHEMA_MINOR = 13
"""Minor version: bumped when fields are added (or deprecated and ignored, never removed). A receiver accepts a
message of a newer minor version, ignoring the fields it does not know (logged once per field)."""
MAX_COMMAND_CHARS = 500
"""Longest natural-language command L (TaskRequest, TaskStatus; the gateway's and MCP's bodies take the same)."""
MAX_QUERY_CHARS = 200
"""Longest object or surface query, skill argument or label (perception truncates a query to it)."""

# Bounds of every string and sequence in the contract: each field takes one of these (a test fails on a field
# without one). They are far above what the services send and far below the 1 MiB sample cap
# (shared.keys.MESSAGE_MAX_BYTES), so they refuse a forged or runaway payload, never a real one.
MAX_ID_CHARS = 64
"""Longest id: a task, goal, request or approval id (`task-`, `goal-`, `req-`, `appr-` + 12 hex digits)."""
ID_PATTERN = rf"^[A-Za-z0-9_.:-]{{0,{MAX_ID_CHARS}}}$"
"""An id: letters, digits and `_ . : -` (it goes into URLs, logs and file names); empty where none is set."""
VEHICLE_ID_PATTERN = r"^[A-Za-z0-9_-]{1,32}$"
"""A vehicle id, as the services' settings take it (AERMANI_VEHICLE_ID) and the gateway's body; never `fleet`."""
MAX_NAME_CHARS = 64
"""Longest name of a thing of the stack: a skill, service, PX4 mode, parameter, check, unit, segmenter."""
MAX_LABEL_CHARS = MAX_QUERY_CHARS
"""Longest label of a thing in the world (an object or surface name, open vocabulary) or a who (abort source)."""
MAX_TEXT_CHARS = 10_000
"""Longest human-readable text: a message, reason or explanation (a sentence or a paragraph in practice; the
backends cut quoted error bodies to 200 characters)."""
MAX_TRACE_CHARS = 100_000
"""Longest model text: a raw answer (the parser records at most 32 000 characters and a note), a parse error that
quotes it, a DRT field, a prompt part (the History is capped at history_max_chars, 6000 by default)."""
MAX_DETECTIONS = 1024
"""Most detections of one frame, and labels visible in it (the catalogue has 14 objects and a few surfaces)."""
MAX_MEMORY_OBJECTS = 1024
"""Most entries of each working-memory table (objects, placements, seen: one per label) and executed skills
(the executor keeps the last 200)."""
MAX_CHECKS = 64
"""Most checks of one preflight report or judge verdict (about 10 of each today)."""
MAX_SKILLS = 256
"""Most skills of the library (about 20 today), parameters of one skill, action predictions' entries."""
MAX_MODEL_CALLS = 64
"""Most model calls of one reasoning step (the re-prompt budget is at most 10)."""
MAX_CANDIDATES = 256
"""Most SayCan candidates (the parser reads at most 200) and plan-once steps (at most 40) of one step."""
MAX_PROMPT_PARTS = 64
"""Most named prompt parts of one step (command, preamble, history, skill_library, rules...)."""
MAX_PREDICTIONS = 8192
"""Most action predictions of one DRT: one per skill is asked; what a 32 000-character answer can hold is less."""
MAX_SCENARIO_OBJECTS = 64
"""Most distractors, extra objects or start placements of one scenario."""
MAX_WORLD_OBJECTS = 1024
"""Most instances of a simulated layout (labels, ground-truth objects) and collisions since a reset."""
MAX_SIM_STATE_CHARS = 1_000_000
"""Longest simulator state document (SimState.state: about 12 kB for a room of 14 objects)."""
MAX_HISTORY_STEPS = 1024
"""Most History entries a resumed task carries (a task's step cap is at most a few hundred)."""
MAX_HEALTH_DETAILS = 256
"""Most entries of a health's details (a dozen figures today; their values are bounded by the byte cap only)."""
# Physical bounds: a value beyond them is a broken estimate or a forged message, never a state to act on.
MAX_COORDINATE_M = 10_000.0
"""Largest |x|, |y|, |z| of any position or extent, metres (a local frame of +-10 km)."""
MAX_VEHICLE_SPEED_MS = 50.0
"""Largest |velocity| component a multirotor state may report, m/s."""
MAX_ANGLE_RAD = 2 * math.pi + 1e-6
"""Largest |yaw|, |roll|, |pitch|, radians."""
MAX_BATTERY_VOLTAGE_V = 100.0
"""Largest battery voltage, volts (a 12S pack is ~50 V)."""


def _not_fleet(v: str) -> str:
    if v == "fleet":  # shared.keys.FLEET_ID (not imported: keys imports this module)
        raise ValueError("vehicle id 'fleet' is reserved for fleet-wide keys")
    return v


def _well_formed(v: Any) -> Any:
    from shared.text import well_formed

    return well_formed(v) if isinstance(v, str) else v


# A bounded str is validated by pydantic-core as UTF-8, which a lone surrogate (half an emoji a model or an HTTP
# client sent as `\ud83d`) cannot be: refused, it would lose the step or status that quotes it. Free text is made
# well formed first (U+FFFD for the surrogate, as the bus writes it anyway); ids and vehicle ids are refused.
_WELL_FORMED = BeforeValidator(_well_formed)

Id = Annotated[str, Field(max_length=MAX_ID_CHARS, pattern=ID_PATTERN)]
"""A task, goal, request or approval id (ID_PATTERN)."""
VehicleId = Annotated[str, Field(max_length=32, pattern=VEHICLE_ID_PATTERN), AfterValidator(_not_fleet)]
"""A vehicle id (VEHICLE_ID_PATTERN); a subscriber also refuses a payload whose vehicle id is not its key's."""
Name = Annotated[str, Field(max_length=MAX_NAME_CHARS), _WELL_FORMED]
"""A name of the stack's own (MAX_NAME_CHARS)."""
Label = Annotated[str, Field(max_length=MAX_LABEL_CHARS), _WELL_FORMED]
"""A label of a thing in the world (MAX_LABEL_CHARS)."""


def _clipped(limit: int) -> BeforeValidator:
    """Free text built by the stack itself (python mode: a status quoting an exception, a model's answer or a
    peer's reason) is cut to `limit` with a note saying so, so that the step or status carrying it is never
    lost to its own bound; text received off the wire (JSON mode) is not cut: over the bound, it is refused."""

    def clip(v: Any, info: ValidationInfo) -> Any:
        if info.mode == "python" and isinstance(v, str) and len(v) > limit:
            note = f" ... [{len(v)} characters, cut to {limit}]"
            return v[:limit - len(note)] + note
        return v

    return BeforeValidator(clip)


Text = Annotated[str, Field(max_length=MAX_TEXT_CHARS), _WELL_FORMED, _clipped(MAX_TEXT_CHARS)]
"""Human-readable text (MAX_TEXT_CHARS; cut to it when the stack builds a message, refused over it when received)."""
Trace = Annotated[str, Field(max_length=MAX_TRACE_CHARS), _WELL_FORMED, _clipped(MAX_TRACE_CHARS)]
"""Model text (MAX_TRACE_CHARS; cut to it when the stack builds a message, refused over it when received)."""


def now_ns() -> int:
    """Wall-clock time in integer nanoseconds since the epoch."""
    return time.time_ns()


def new_id(prefix: str = "") -> str:
    return f"{prefix}{uuid.uuid4().hex[:12]}"


class Message(BaseModel):
    """Base of every bus message: frozen, strict about unknown fields, versioned, finite numbers only."""

    model_config = ConfigDict(frozen=True, extra="forbid", use_attribute_docstrings=True, allow_inf_nan=False)
    schema_name: ClassVar[str] = ""

    schema_version: int = SCHEMA_VERSION
    """Major schema version of this message; bumped on incompatible changes."""
    schema_minor: int = SCHEMA_MINOR
    """Minor schema version; bumped when fields are added (older receivers ignore the new fields)."""

    @classmethod
    def full_schema_name(cls) -> str:
        """Name used for the Zenoh encoding schema and the MCAP schema, e.g. `aermani.VehicleState`."""
        return f"aermani.{cls.__name__}"


class Part(BaseModel):
    """Base of nested value objects (not published on their own)."""

    model_config = ConfigDict(frozen=True, extra="forbid", use_attribute_docstrings=True, allow_inf_nan=False)


# --------------------------------------------------------------------------- geometry


class Vec3(Part):
    """A 3-vector in metres (a position or an extent), in the frame the field names."""

    x: float = Field(default=0.0, ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)
    """x in metres (world ENU: east/forward at start; body FLU: forward)."""
    y: float = Field(default=0.0, ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)
    """y in metres (world ENU: north/left at start; body FLU: left)."""
    z: float = Field(default=0.0, ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)
    """z in metres (up)."""

    def as_tuple(self) -> tuple[float, float, float]:
        return (self.x, self.y, self.z)


class Pose(Part):
    """A position and a yaw in the world frame (ENU)."""

    position: Vec3 = Vec3()
    """Position in the world frame (ENU), metres."""
    yaw: float = 0.0
    """Heading in radians, ENU, counter-clockwise from world +x."""


class BBox2D(Part):
    """An axis-aligned box in image pixels."""

    x0: int
    """Left pixel column (inclusive)."""
    y0: int
    """Top pixel row (inclusive)."""
    x1: int
    """Right pixel column (exclusive)."""
    y1: int
    """Bottom pixel row (exclusive)."""


# --------------------------------------------------------------------------- autopilot


class LandedState(StrEnum):
    """PX4's landed state (MAV_LANDED_STATE), as the bridge reports it."""

    UNKNOWN = "unknown"
    ON_GROUND = "on_ground"
    IN_AIR = "in_air"
    TAKEOFF = "takeoff"
    LANDING = "landing"


class GripperState(StrEnum):
    """What the gripper reports: open, closed, or unknown."""

    UNKNOWN = "unknown"
    OPEN = "open"
    CLOSED = "closed"


ABORT_OVERRIDE = "aborted by "
"""How `VehicleState.override` starts when an abort took control ("aborted by <source>: <reason>")."""


class VehicleState(Message):
    """The vehicle as the autopilot bridge sees it, at >= 20 Hz: pose, motion, PX4 mode, health."""

    kind: Literal["vehicle_state"] = "vehicle_state"
    stamp_ns: int = Field(default_factory=now_ns, ge=0)
    """When the bridge produced this state (ns since epoch)."""
    vehicle_id: VehicleId = "am1"
    """Vehicle this state belongs to."""
    position: Vec3 = Vec3()
    """Body origin in the world frame (ENU), metres."""
    velocity: Vec3 = Vec3()
    """Velocity in the world frame (ENU), m/s; each component within +-50 m/s."""
    yaw: float = Field(default=0.0, ge=-MAX_ANGLE_RAD, le=MAX_ANGLE_RAD)
    """Heading, radians, ENU."""
    roll: float = Field(default=0.0, ge=-MAX_ANGLE_RAD, le=MAX_ANGLE_RAD)
    """Roll, radians (FLU)."""
    pitch: float = Field(default=0.0, ge=-MAX_ANGLE_RAD, le=MAX_ANGLE_RAD)
    """Pitch, radians (FLU, positive nose up)."""
    armed: bool = False
    """Whether the motors are armed."""
    mode: Name = "UNKNOWN"
    """PX4 flight mode name, e.g. OFFBOARD, POSCTL, AUTO.TAKEOFF, AUTO.LOITER, AUTO.LAND."""
    landed_state: LandedState = LandedState.UNKNOWN
    """Landed state from EXTENDED_SYS_STATE."""
    battery_voltage: float | None = Field(None, ge=0.0, le=MAX_BATTERY_VOLTAGE_V)
    """Battery voltage in volts, if reported."""
    battery_remaining: float | None = Field(None, ge=0.0, le=100.0)
    """Battery remaining in percent (0-100), if reported."""
    gripper: GripperState = GripperState.UNKNOWN
    """Last commanded/acknowledged gripper state."""
    gripper_width: float | None = None
    """Opening between the gripper's fingers, metres, if the gripper reports it."""
    gripper_holding: bool | None = None
    """Whether the gripper senses an object between its fingers (contact on both), if it reports it."""
    link_ok: bool = False
    """True while heartbeats arrive (none for 2 s means link lost)."""
    offboard_ok: bool = False
    """True while in OFFBOARD with the setpoint stream running."""
    last_heartbeat_ns: int = Field(0, ge=0)
    """Receive time of the last autopilot HEARTBEAT."""
    message: Text = ""
    """Latest human-readable status (STATUSTEXT, link loss...)."""
    override: Text = ""
    """Why PX4, the pilot or an abort has taken control from the stack ("PX4 switched from OFFBOARD to AUTO.RTL",
    "aborted by <source>: <reason>"); while set, the bridge neither re-enters OFFBOARD nor takes off for the task
    that was flying. Empty: the stack may fly."""
    override_ns: int = 0
    """Bridge time when `override` was set (0 when empty): a change tells a new takeover from an old one."""

    # What the bridge always sends: a state on the wire without these does not say where the vehicle is.
    WIRE_FIELDS: ClassVar[tuple[str, ...]] = ("kind", "stamp_ns", "vehicle_id", "position", "velocity", "armed",
                                              "landed_state", "link_ok")

    def taken_by_abort(self, since_ns: int = 0) -> bool:
        """Whether an abort (not PX4 or the pilot) latched `override`, after `since_ns` (bridge time): the
        subscribers of an abort see it in any order, so a skill or a task that finds the bridge already holding
        for an abort ends ABORTED, not FAILED."""
        return self.override.startswith(ABORT_OVERRIDE) and self.override_ns > since_ns

    @model_validator(mode="before")
    @classmethod
    def _complete_on_the_wire(cls, data: Any, info: ValidationInfo) -> Any:
        if info.mode == "json" and isinstance(data, dict):
            missing = [f for f in cls.WIRE_FIELDS if f not in data]
            if missing:
                raise ValueError(f"a vehicle state on the bus must carry {list(cls.WIRE_FIELDS)}; missing {missing}")
        return data

    @field_validator("velocity")
    @classmethod
    def _physical_speed(cls, v: Vec3) -> Vec3:
        if max(abs(v.x), abs(v.y), abs(v.z)) > MAX_VEHICLE_SPEED_MS:
            raise ValueError(f"velocity ({v.x:.1f}, {v.y:.1f}, {v.z:.1f}) m/s exceeds {MAX_VEHICLE_SPEED_MS:.0f} m/s "
                             "per axis: not a multirotor state")
        return v


class ArmCommand(Message):
    """Arm the motors (PX4 arming checks apply)."""

    kind: Literal["arm"] = "arm"
    task_id: Id | None = None
    """Task on whose behalf (set by the executor); None for an operator's direct command."""


class DisarmCommand(Message):
    """Disarm the motors."""

    kind: Literal["disarm"] = "disarm"
    force: bool = False
    """Force the disarm past PX4's pre-checks (on the ground)."""
    kill: bool = False
    """Required to disarm while airborne: the motors stop and the vehicle falls. Emergency only; the bridge
    refuses an in-air disarm without it and logs every kill with its sender."""


class TakeoffCommand(Message):
    """Arm if needed, enter OFFBOARD and climb to `altitude`; done once there."""

    kind: Literal["takeoff"] = "takeoff"
    altitude: float = Field(1.5, gt=0.0, le=50.0)
    """Target altitude above the home position, metres."""
    task_id: Id | None = None
    """Task on whose behalf (set by the executor); None for an operator's direct command."""


class GotoCommand(Message):
    """Fly to a world position and yaw through the offboard setpoint stream."""

    kind: Literal["goto"] = "goto"
    position: Vec3
    """Target position, world ENU, metres."""
    yaw: float
    """Target heading, radians ENU."""
    max_speed: float | None = Field(None, gt=0.0, le=MAX_VEHICLE_SPEED_MS)
    """Optional speed limit for this motion, m/s (the bridge ramps the setpoint)."""
    task_id: Id | None = None
    """Task on whose behalf (set by the executor); None for an operator's direct command."""


class HoldCommand(Message):
    """Hold the current position (stop any motion)."""

    kind: Literal["hold"] = "hold"


class LandCommand(Message):
    """Land at the current position (PX4 AUTO.LAND)."""

    kind: Literal["land"] = "land"


class GripperCommand(Message):
    """Open or close the gripper."""

    kind: Literal["gripper"] = "gripper"
    action: Literal["open", "close"]
    """Open (release) or close (grab)."""


class PreflightCommand(Message):
    """Run the bridge's preflight checks (PX4's failsafe parameters, the vehicle's state); nothing moves."""

    kind: Literal["preflight"] = "preflight"


AutopilotCommand = Annotated[
    ArmCommand | DisarmCommand | TakeoffCommand | GotoCommand | HoldCommand | LandCommand | GripperCommand
    | PreflightCommand,
    Field(discriminator="kind"),
]


class PreflightCheck(Part):
    """One preflight check: what was read from the autopilot, what is required, and the verdict."""

    name: Name
    """The parameter (COM_OBL_RC_ACT...) or state (link, position, landed, battery) checked."""
    ok: bool
    value: Text = ""
    """What the autopilot reported ("" when it reported nothing)."""
    expected: Text = ""
    """What is required to fly."""
    reason: Text = ""
    """Why it matters, for a failed check; for a passed one, a caveat or empty (COM_OBL_RC_ACT Land lands
    wherever the vehicle is)."""


class PreflightReport(Message):
    """One preflight verdict, published for the record (the recorder keeps it in the flight's log): the
    bridge's gate before an arm or take-off and on request, the operator's full check from `aermani preflight`."""

    kind: Literal["preflight_report"] = "preflight_report"
    stamp_ns: int = Field(default_factory=now_ns, ge=0)
    """When the checks ran."""
    vehicle_id: VehicleId = "am1"
    """Vehicle checked."""
    trigger: Literal["request", "arm", "takeoff", "operator"]
    """What ran it: a preflight command, the gate before an arm or a take-off, or `aermani preflight`."""
    ok: bool
    """Every check passed."""
    checks: tuple[PreflightCheck, ...] = Field((), max_length=MAX_CHECKS)
    """Each check with its value and verdict."""
    overridden: bool = False
    """The gate failed and the operator's override let the vehicle arm anyway."""
    override_reason: str = Field("", max_length=200)
    """The reason the operator gave for the override."""


class AutopilotResult(Message):
    """The bridge's answer to an autopilot command, with PX4's ACK code where there is one."""

    kind: Literal["autopilot_result"] = "autopilot_result"
    ok: bool
    """Whether the command was accepted and carried out."""
    command: Name
    """Which command this answers (arm, takeoff, goto...)."""
    ack_code: int | None = None
    """PX4 COMMAND_ACK result code (0 accepted, 1 temporarily rejected, 2 denied, 3 unsupported, 4 failed,
    5 in progress), when a COMMAND_LONG was involved."""
    ack_name: Name = ""
    """MAV_RESULT name of ack_code."""
    message: Text = ""
    """Human-readable explanation."""
    aborted: bool = False
    """The command was stopped or refused because of an abort the bridge obeyed (it may have got the abort
    before the executor did): the skill that sent it ends ABORTED, not FAILED."""
    checks: tuple[PreflightCheck, ...] = Field((), max_length=MAX_CHECKS)
    """Every preflight check with its verdict: the answer to a preflight command, and to an arm or takeoff
    that the preflight refused."""


# --------------------------------------------------------------------------- perception


class LocalizeRequest(Message):
    """Ask perception to localize an object or a placement surface by an open-vocabulary query."""

    kind: Literal["localize_request"] = "localize_request"
    query: str = Field(..., max_length=10_000)
    """Free-text query: an object ("red cup", "the larger box") or a surface ("round table")."""
    object_size: Vec3 | None = None
    """For placement: size of the held object, for clearance."""
    max_frame_age_s: float = 1.0
    """Refuse frames older than this (seconds)."""


LocalizeReason = Literal[
    "ok", "not_visible", "too_few_points", "depth_invalid", "ambiguous", "bad_query", "no_frame", "stale_frame",
    "no_free_spot", "error",
]


class LocalizeAnswer(Message):
    """What perception's two answers (ObjectEstimate, PlacementEstimate) share: the query, found or not with
    the reason, the matched label, how sure, the evidence and the frame it comes from."""

    kind: Name = ""
    """The answer's kind (each subclass fixes it)."""
    query: Label
    """The query this answers (truncated to 200 characters)."""
    found: bool
    """Whether the thing was localized (an object's pose; a surface with a free placement pose)."""
    reason: LocalizeReason = "ok"
    """Why not, when not found."""
    message: Text = ""
    """Human-readable explanation."""
    label: Label = ""
    """Label of the matched object or surface."""
    confidence: float = 0.0
    """0..1."""
    n_points: int = 0
    """Number of 3D points supporting the estimate (for a placement: the surface plane's inliers)."""
    bbox: BBox2D | None = None
    """2D box of the matched object or surface in the image used."""
    frame_stamp_ns: int = 0
    """Timestamp of the colour/depth pair used."""


class ObjectEstimate(LocalizeAnswer):
    """Perception's answer to obj_localization: found or not (with the reason), pose, size, support."""

    kind: Literal["object_estimate"] = "object_estimate"
    pose: Pose | None = None
    """Object centroid (world ENU) and grasp yaw from its oriented box."""
    size: Vec3 | None = None
    """Object extent along its box axes (x along grasp yaw), metres."""
    top_z: float | None = None
    """Height of the object's top, world z, metres."""
    support_z: float | None = None
    """Height of the surface under it, world z, metres."""
    catalog_size: Vec3 | None = None
    """The matched class's catalogued extent as it stands when upright (x the long and y the short horizontal
    side, z the height), metres; None when the segmenter knows no catalogue (minor 13)."""


class PlacementEstimate(LocalizeAnswer):
    """Perception's answer to placement_localization: the surface and a free placement spot."""

    kind: Literal["placement_estimate"] = "placement_estimate"
    pose: Pose | None = None
    """Placement pose: where the held object's bottom should be released (world ENU), plus vertical offset."""
    surface_z: float | None = None
    """Height of the surface plane, world z, metres."""
    plane: tuple[float, float, float, float] | None = None
    """Plane (a, b, c, d) in the world frame, normal up."""
    vertical_offset: float = 0.0
    """Offset above the surface included in pose.position.z, metres."""
    clearance: float = 0.0
    """Distance from the spot to the nearest clutter or edge, metres."""


class Detection(Part):
    """One thing perception sees in the current frame."""

    label: Label
    """Label of the detected thing (object or surface name)."""
    category: Literal["object", "surface", "furniture", "other"] = "object"
    """What kind of thing it is."""
    bbox: BBox2D | None = None
    """2D box in the image."""
    centroid: Vec3 | None = None
    """3D centroid in the world frame."""
    size: Vec3 | None = None
    """3D extent, metres."""
    confidence: float = 0.0
    """0..1."""
    n_points: int = 0
    """Supporting 3D points."""
    catalog_size: Vec3 | None = None
    """An object's class's catalogued extent standing (as ObjectEstimate.catalog_size); None for a surface, or
    when the segmenter knows no catalogue (minor 13)."""


class Detections(Message):
    """Everything perception sees in one frame (published at a fixed rate)."""

    kind: Literal["detections"] = "detections"
    stamp_ns: int = Field(default_factory=now_ns)
    """Publish time."""
    frame_stamp_ns: int = 0
    """Timestamp of the frame these come from."""
    segmenter: Name = ""
    """Segmenter that produced them (sim, color, sam3)."""
    items: tuple[Detection, ...] = Field((), max_length=MAX_DETECTIONS)
    """What is visible now."""


# --------------------------------------------------------------------------- executor


class SkillState(StrEnum):
    """Life cycle of a skill goal: running, then one terminal state."""

    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    TIMEOUT = "timeout"
    REJECTED = "rejected"
    ABORTED = "aborted"

    @property
    def terminal(self) -> bool:
        return self is not SkillState.RUNNING


class SkillParameter(Part):
    """A fixed parameter of a skill (from the executor's settings), shown in the Skill Library."""

    name: Name
    """Parameter name."""
    value: float | Label | bool
    """Fixed value (from settings)."""
    unit: Name = ""
    """Unit, e.g. m or deg."""


class SkillSpec(Part):
    """One skill as the policy sees it: name, family, Skill Library text, argument rule."""

    name: Name
    """Skill name the policy uses, e.g. `forward`, `obj_localization`."""
    category: Literal["motion", "perception", "manipulation", "operator", "control"]
    """Family of the skill."""
    description: Text
    """Text shown to the model in the Skill Library."""
    argument: Label | None = None
    """What the argument is (e.g. "object query"), or None when the skill takes no argument."""
    argument_required: bool = False
    """Whether the argument must be given."""
    parameters: tuple[SkillParameter, ...] = Field((), max_length=MAX_SKILLS)
    """Fixed parameters of the routine."""
    policy_visible: bool = True
    """False for operator-only skills (takeoff, land, hold) that are not offered to the model."""


class SkillLibrary(Message):
    """The live skill library the executor serves: the policy's whole action space."""

    kind: Literal["skill_library"] = "skill_library"
    skills: tuple[SkillSpec, ...] = Field(..., max_length=MAX_SKILLS)
    """Every registered skill."""


class SkillRequest(Message):
    """Action protocol, skill level: the goal (run this skill with this argument)."""

    kind: Literal["skill_request"] = "skill_request"
    skill: str = Field(..., max_length=MAX_NAME_CHARS)
    """Registered skill name."""
    argument: str | None = Field(None, max_length=MAX_QUERY_CHARS)
    """Argument (object or surface query) for skills that take one."""
    task_id: Id = ""
    """Task this belongs to (empty for operator commands)."""
    step: int = 0
    """Reasoning step index within the task."""
    request_id: Id = Field(default_factory=lambda: new_id("req-"))
    """Caller's id, echoed in the status."""


class SkillAccept(Message):
    """Action protocol, skill level: the goal was accepted (with its goal id) or rejected (with why)."""

    kind: Literal["skill_accept"] = "skill_accept"
    accepted: bool
    """Whether the executor started the skill."""
    goal_id: Id = ""
    """Id to follow the skill's status (when accepted)."""
    reason: Text = ""
    """Why it was rejected, written for the model to read."""
    outcome: SkillOutcome | None = None
    """A rejection's outcome (its code, e.g. out_of_reach, and facts), the same as its rejected status carries;
    None when accepted (and from executors older than schema minor 3)."""


class MemoryObject(Part):
    """One entry of working memory: an object or a placement spot and where it was localized."""

    label: Label
    """Object or surface label."""
    query: Label = ""
    """The query that found it."""
    position: Vec3
    """World position (object centroid or placement spot)."""
    yaw: float = 0.0
    """Grasp or placement yaw."""
    size: Vec3 | None = None
    """Extent, metres."""
    top_z: float | None = None
    """Top of the object (objects)."""
    last_seen_ns: int = 0
    """When it was last localized."""
    confidence: float = 0.0
    """0..1."""


class WorkingMemory(Message):
    """The executor's working memory: what was localized, what is held, what was done."""

    kind: Literal["working_memory"] = "working_memory"
    stamp_ns: int = Field(default_factory=now_ns)
    """Publish time."""
    objects: tuple[MemoryObject, ...] = Field((), max_length=MAX_MEMORY_OBJECTS)
    """Localized objects (latest estimate per label)."""
    placements: tuple[MemoryObject, ...] = Field((), max_length=MAX_MEMORY_OBJECTS)
    """Localized placement spots (latest per surface)."""
    held_object: Label | None = None
    """Label of the object in the gripper, if any."""
    visible: tuple[Label, ...] = Field((), max_length=MAX_DETECTIONS)
    """Labels visible in the latest detections."""
    executed: tuple[Text, ...] = Field((), max_length=MAX_MEMORY_OBJECTS)
    """Skills executed so far in this task ("forward", "obj_localization(red cup)"...)."""
    seen: tuple[MemoryObject, ...] = Field((), max_length=MAX_MEMORY_OBJECTS)
    """Everything perception has detected so far, latest world position per label (coarse: detection
    centroids), so a search can turn toward what was seen before instead of scanning again."""


class MemoryRestore(Message):
    """Put a recorded working memory back (a flight fork, minor version 9): the executor takes it as the named
    task's, its sightings as old as they were when it was recorded (`taken_ns`)."""

    kind: Literal["memory_restore"] = "memory_restore"
    task_id: Id
    """The task that goes on with this memory (its first skill does not clear it)."""
    memory: WorkingMemory
    """The memory as recorded."""
    taken_ns: int = Field(..., gt=0)
    """When it was current (the recording's clock): every sighting keeps its age at that moment."""


class OutcomeCode(StrEnum):
    """Why a skill ended as it did: the fact a policy decides from (never the message's prose)."""

    SUCCEEDED = "succeeded"
    """The skill did what it was asked and its result was verified."""
    OUT_OF_REACH = "out_of_reach"
    """The target is farther than the skill may act (grasp reach, envelope, geofence)."""
    NOT_DETECTED = "not_detected"
    """Perception did not find the named object or surface."""
    MISALIGNED = "misaligned"
    """The gripper never came within its window of the object; nothing was closed."""
    MISSED = "missed"
    """The gripper closed but holds nothing (the object is still where it was)."""
    SLIPPED = "slipped"
    """The object was held and then lost (it slipped or fell from the gripper)."""
    KNOCKED_OVER = "knocked_over"
    """The object was moved or tipped by the attempt: re-localize it before trying again."""
    BLOCKED = "blocked"
    """A precondition or a safety limit refused the skill (clearance, altitude, holding, not airborne)."""
    UNSTABLE = "unstable"
    """The object was released but is not at rest on the named surface (rolled, toppled, fell off)."""
    ABORTED = "aborted"
    """An abort or a cancel stopped the skill; the vehicle holds."""
    TIMED_OUT = "timed_out"
    """The skill ran out of time before it could finish."""
    FAILED = "failed"
    """Another failure (the autopilot refused, the link was lost); the message says which."""


class SkillFacts(Part):
    """Measured facts behind an outcome code, in one fixed form the prompt shows and a policy reads."""

    distance_m: float | None = None
    """Distance from the vehicle (or gripper) to the target when the skill decided, metres."""
    reach_m: float | None = None
    """The farthest the skill may act from (with `out_of_reach`: how close to come before trying again), metres."""
    offset_m: float | None = None
    """Remaining horizontal offset between the gripper and the target when the skill decided, metres."""
    attempts: int = 0
    """How many attempts the skill made (grasp and place retry a bounded number of times)."""
    reasons: tuple[Annotated[str, Field(max_length=200)], ...] = Field(default=(), max_length=16)
    """One short reason per failed attempt, in order."""
    gripper_width_m: float | None = None
    """Opening between the finger pads at the end, metres (from the gripper's own telemetry)."""
    holding: Label | None = None
    """What the gripper holds at the end according to its contact sensing and width; None if empty."""
    target: Label | None = None
    """The object or surface the skill acted on."""
    upright: bool | None = None
    """After a place: whether the released object stands as tall as when it was held and was held standing
    (False: it lies fallen over, and no skill of this gripper can stand it up again); after a grasp: whether the
    fingers closed across the side they close across when it stands (False: it lies on its side, minor 13);
    None when not measured or not measurable (a round object, a box with no catalogued extent) (minor 12)."""


class SkillOutcome(Part):
    """Structured outcome of a skill: poses before and after, what was perceived, what is held."""

    code: OutcomeCode | None = None
    """Why the skill ended (None while running, and for messages older than schema minor 3)."""
    facts: SkillFacts = SkillFacts()
    """Measured facts behind the code."""

    start_pose: Pose | None = None
    """Vehicle pose when the skill started."""
    end_pose: Pose | None = None
    """Vehicle pose when the skill ended."""
    perceived: Text = ""
    """What perception reported (e.g. "red cup at (1.20, 0.30, 0.80)")."""
    held_object: Label | None = None
    """What the gripper holds after the skill."""
    estimate: ObjectEstimate | PlacementEstimate | None = None
    """The perception estimate produced, for localization skills."""


class SkillStatus(Message):
    """Action protocol, skill level: feedback (running) and the one terminal result of a goal."""

    kind: Literal["skill_status"] = "skill_status"
    stamp_ns: int = Field(default_factory=now_ns)
    """Publish time."""
    goal_id: Id
    """Goal id returned by run_skill."""
    request_id: Id = ""
    """Caller's request id."""
    task_id: Id = ""
    """Task id from the request."""
    step: int = 0
    """Step index from the request."""
    skill: Name
    """Skill name."""
    argument: Label | None = None
    """Skill argument."""
    state: SkillState
    """running, succeeded, failed, timeout, rejected, aborted."""
    message: Text = ""
    """Explanation, written for the model to read."""
    outcome: SkillOutcome = SkillOutcome()
    """What changed and what was perceived."""
    started_ns: int = 0
    """When the skill started."""
    ended_ns: int = 0
    """When it ended (0 while running)."""


class Abort(Message):
    """Stop now: every executor and reasoner of the vehicle holds and ends what runs."""

    kind: Literal["abort"] = "abort"
    stamp_ns: int = Field(default_factory=now_ns)
    """When the abort was requested."""
    reason: Text = "operator abort"
    """Why."""
    source: Label = "operator"
    """Who asked (gateway, operator, reasoner...)."""
    task_id: Id | None = None
    """Task to abort, or None for whatever runs."""


class AbortAck(Message):
    """The executor obeyed an abort (the vehicle was commanded to hold)."""

    kind: Literal["abort_ack"] = "abort_ack"
    stamp_ns: int = Field(default_factory=now_ns)
    """When the executor had commanded hold."""
    abort_stamp_ns: int
    """stamp_ns of the Abort this acknowledges."""
    goal_id: Id | None = None
    """The skill that was stopped, if any."""
    message: Text = ""
    """What was done."""
    service: Name = "executor"
    """Which service acknowledges (executor, autopilot_bridge)."""


# --------------------------------------------------------------------------- reasoner


class DescriptiveReasoningTrace(Part):
    """The paper's DRT; fields are None when the prompt variant does not ask for them."""

    image_description: Trace | None = None
    """Visible objects, their spatial arrangement and cues in the current image."""
    summary: Trace | None = None
    """Short recap of previous observations and executed skills."""
    action_predictions: dict[Trace, Trace] | None = Field(None, max_length=MAX_PREDICTIONS)
    """For every available skill, the predicted outcome of executing it now."""
    reasoning: Trace | None = None
    """Justification of the chosen skill from observation, history and predictions."""


class SkillToExecute(Part):
    """The paper's STE: one skill of the library plus its argument."""

    skill: Name
    """Skill name, exactly as in the Skill Library."""
    argument: Label | None = None
    """Object or surface query for localization skills; None otherwise."""

    @property
    def call(self) -> str:
        """How the stack writes the decision in text: `grasp(red cup)`, or the skill alone."""
        return f"{self.skill}({self.argument})" if self.argument else self.skill


Variant = Literal["unstructured", "no_drt", "drt_v1", "drt_v2", "drt_v3", "full", "react", "saycan", "direct",
                  "waypoint", "plan_once"]
BackendName = Annotated[str, Field(pattern=r"^([a-z][a-z0-9_.-]{0,63})?$")]
"""A registered reasoner backend (`rules`, `openai`, `anthropic`, `replay`, or a plug-in's name); the
reasoner's registry decides which exist, so the type fixes only the spelling."""
BackendLabel = Annotated[str, Field(pattern=r"^([a-z][a-z0-9_.-]{0,63}(:\S{1,200})?)?$")]
"""A backend with its model, as recorded: `rules`, `openai:gpt-4o`, `openai:Qwen/Qwen2-VL-7B-Instruct`."""
VARIANTS: tuple[str, ...] = ("unstructured", "no_drt", "drt_v1", "drt_v2", "drt_v3", "full", "react")
"""The prompt variants of the paper's Table IV ablation, plus its ReAct baseline."""
BASELINES: tuple[str, ...] = ("saycan", "direct", "waypoint", "plan_once")
"""The paper's Table III baseline frameworks over the same skill interface: SayCan-style scoring of every skill
(weighted by the executor's feasibility check), RT-2-style direct action, UAV-VLN-style waypoints (motion
primitives only), UAV-VLA-style one plan at the start (services/reasoner/baselines.py)."""


class ModelCall(Part):
    """One call to the model within a reasoning step: raw answer, validity, latency, tokens."""

    raw_answer: Trace
    """The model's answer, verbatim."""
    valid: bool
    """Whether it parsed into a valid DRT/STE."""
    error: Trace = ""
    """Why it was invalid (sent back to the model on re-prompt)."""
    latency_s: float = 0.0
    """Model response time, seconds."""
    tokens_in: int | None = None
    """Prompt tokens, when the backend reports them."""
    tokens_out: int | None = None
    """Answer tokens, when the backend reports them."""
    structured: bool = False
    """The answer was decoded under the answer's JSON schema (schema-constrained output), not free text."""
    tokens_cached: int | None = None
    """Prompt tokens the server read from its prompt cache, when it reports them."""


class StepTiming(Part):
    """Where one step's wall time went, as the reasoner saw it (seconds, this host's clock). What a user waits
    for besides the model and the skill is `to_model_s + accept_s + report_s`."""

    to_model_s: float = Field(0.0, ge=0)
    """From the previous skill's end (its status received; the take-off's for step 1) to this step's first model
    call: the observation's waits, the link gate and the prompt's compilation."""
    frame_wait_s: float = Field(0.0, ge=0)
    """Part of `to_model_s`: waiting for a colour frame newer than the previous skill's end."""
    detections_wait_s: float = Field(0.0, ge=0)
    """Part of `to_model_s`: waiting for detections newer than the previous skill's end."""
    state_wait_s: float = Field(0.0, ge=0)
    """Part of `to_model_s`: waiting for a vehicle state newer than the previous skill's end."""
    link_wait_s: float = Field(0.0, ge=0)
    """Part of `to_model_s`: the link gate holding the step while the vehicle's link or offboard was bad."""
    prompt_s: float = Field(0.0, ge=0)
    """Part of `to_model_s`: compiling the prompt."""
    model_s: float = Field(0.0, ge=0)
    """The model calls of the step, re-prompts and parsing between them included."""
    accept_s: float = Field(0.0, ge=0)
    """From sending the skill to the executor's acceptance (approvals included)."""
    skill_s: float = Field(0.0, ge=0)
    """The skill as the executor timed it (its start to its end)."""
    report_s: float = Field(0.0, ge=0)
    """From the executor's end of the skill to the reasoner holding its status (a clock offset between two
    hosts shows here; 0 when negative)."""


class SkillScore(Part):
    """SayCan-style: the model's usefulness score of one candidate skill, times the executor's feasibility."""

    skill: Name
    """Candidate skill."""
    argument: Label | None = None
    """Its argument."""
    score: float
    """The model's usefulness score, 0..1."""
    feasible: bool = False
    """Whether the executor would accept it now (its check_skill answer)."""
    reason: Text = ""
    """The executor's reason when it would not."""
    weighted: float = 0.0
    """score x feasibility (1 or 0): the highest one runs."""


class ReasoningStep(Message):
    """One step of Algorithm 1: prompt parts, model calls, DRT and STE, and the skill's outcome."""

    kind: Literal["reasoning_step"] = "reasoning_step"
    stamp_ns: int = Field(default_factory=now_ns)
    """When the step was decided (the model's answer parsed); its skill runs after this."""
    published_ns: int = 0
    """When the reasoner published this record: after the step's skill ended, seconds after `stamp_ns` for a
    long skill (0 in records older than schema minor 3). A consumer that was down between the two misses it."""
    vehicle_id: VehicleId = "am1"
    """Vehicle the task runs on."""
    task_id: Id
    """Task id."""
    step: int
    """Step index, from 1."""
    backend: BackendLabel = ""
    """Backend (rules, openai:<model>, anthropic:<model>, replay)."""
    variant: Variant = "full"
    """Prompt variant."""
    prompt: dict[Name, Trace] = Field({}, max_length=MAX_PROMPT_PARTS)
    """Prompt parts by name (command, preamble, history, skill_library, rules)."""
    image_stamp_ns: int = 0
    """Timestamp of the colour frame sent with the prompt (0 if none)."""
    calls: tuple[ModelCall, ...] = Field((), max_length=MAX_MODEL_CALLS)
    """Every model call of this step, invalid ones first, so IAR = invalid / calls."""
    drt: DescriptiveReasoningTrace | None = None
    """Parsed DRT of the accepted answer."""
    ste: SkillToExecute | None = None
    """Parsed STE of the accepted answer (None when the step failed)."""
    valid: bool = False
    """Whether a valid answer was obtained within the re-prompt budget."""
    retries: int = 0
    """Re-prompts used."""
    skill_state: SkillState | None = None
    """Termination status of the executed skill."""
    skill_message: Text = ""
    """Executor message."""
    outcome: SkillOutcome | None = None
    """Executor outcome."""
    overhead_s: float = 0.0
    """Framework time of the step excluding model calls and skill execution."""
    skill_duration_s: float = 0.0
    """Wall time of the skill."""
    timing: StepTiming | None = None
    """Where the step's time went (None in records older than schema minor 7 and for a step without a skill)."""
    scores: tuple[SkillScore, ...] = Field((), max_length=MAX_CANDIDATES)
    """SayCan-style variant: every candidate's score and feasibility (empty for other variants; minor 7)."""
    plan: tuple[SkillToExecute, ...] = Field((), max_length=MAX_CANDIDATES)
    """Plan-once variant: the whole plan, in the step that asked for it (empty otherwise; minor 7)."""
    speculative: bool = False
    """The answer was asked for while the previous skill flew, on the observation its predicted outcome implied
    (`prompt` is that one), and used because the fresh observation agreed (AERMANI_REASONER_SPECULATE; minor
    11)."""


class CancelGoal(Message):
    """Action protocol: ask the server of a goal (a skill or a task) to cancel it."""

    kind: Literal["cancel_goal"] = "cancel_goal"
    goal_id: Id = Field(...)
    """The goal to cancel (skill goal id or task id)."""
    reason: str = Field("cancelled", max_length=200)
    """Why, for the record."""
    source: str = Field("operator", max_length=MAX_NAME_CHARS)
    """Who asks."""


class GoalRef(Message):
    """Action protocol: ask the server of a goal (a skill goal id or a task id) for its latest status, its
    result once it ended (minor 8). After ROS 2's get_result: a client whose status subscription had not yet
    reached the server when the goal began (Zenoh propagates a subscription in the background) would otherwise
    wait for statuses that were published before anyone could hear them."""

    kind: Literal["goal_ref"] = "goal_ref"
    goal_id: Id = Field(...)
    """The goal (skill goal id or task id)."""


class CancelReply(Message):
    """Action protocol: whether a cancel request was taken."""

    kind: Literal["cancel_reply"] = "cancel_reply"
    accepted: bool
    """True when the goal was running and is being cancelled."""
    reason: Text = ""
    """Why not (unknown goal, already ended)."""


class ApprovalState(StrEnum):
    """Life cycle of an operator approval request."""

    PENDING = "pending"
    APPROVED = "approved"
    REJECTED = "rejected"
    EXPIRED = "expired"


class ApprovalStatus(Message):
    """An operator approval of a critical skill: pending while the reasoner waits, then how it was decided."""

    kind: Literal["approval_status"] = "approval_status"
    stamp_ns: int = Field(default_factory=now_ns)
    """Publish time."""
    approval_id: Id = Field(default_factory=lambda: new_id("appr-"))
    """Id to decide it by."""
    vehicle_id: VehicleId = "am1"
    """Vehicle that waits."""
    task_id: Id = ""
    """Task the skill belongs to."""
    step: int = 0
    """Reasoning step."""
    skill: Name
    """The skill the policy chose."""
    argument: Label | None = None
    """Its argument."""
    reasoning: Trace = ""
    """Why the policy chose it (its DRT reasoning), for the operator."""
    state: ApprovalState = ApprovalState.PENDING
    """pending, approved, rejected or expired."""
    reason: Text = ""
    """The operator's reason (rejections), or why it expired."""
    operator: Name = ""
    """Who decided."""
    expires_ns: int = 0
    """When a pending request expires (the step then fails and the vehicle holds)."""


class ApprovalDecision(Message):
    """The operator's answer to a pending approval."""

    kind: Literal["approval_decision"] = "approval_decision"
    approval_id: Id = Field(...)
    """The request decided."""
    approved: bool
    """True lets the skill run; False makes the policy choose again."""
    reason: str = Field("", max_length=300)
    """Why (shown to the policy in the History on a rejection)."""
    operator: str = Field("operator", max_length=MAX_NAME_CHARS)
    """Who decides (gateway user, MCP client...)."""


class ResetNotice(Message):
    """The simulated world was reset: what was held and seen belongs to the old world."""

    kind: Literal["reset_notice"] = "reset_notice"
    stamp_ns: int = Field(default_factory=now_ns)
    """When the reset finished."""
    seed: int = 0
    """Layout seed of the new world."""


class TaskState(StrEnum):
    """Life cycle of a task: pending, running, then one terminal state."""

    PENDING = "pending"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    ABORTED = "aborted"
    TIMEOUT = "timeout"

    @property
    def terminal(self) -> bool:
        return self not in (TaskState.PENDING, TaskState.RUNNING)


def command_text(v: str) -> str:
    """A natural-language command as every receiver takes it (task requests, evaluation task files, the
    gateway, MCP): stripped, not empty, no control characters but tab, no invisible formatting characters
    (a right-to-left override or a zero-width space would make the command read otherwise than it acts), no
    lone surrogates (a JSON `\\ud83d` decodes to one; it is no character and UTF-8 cannot carry it)."""
    from shared.text import hidden_characters

    v = v.strip()
    if not v:
        raise ValueError("command is empty")
    bad = hidden_characters(v)
    if bad:
        raise ValueError(f"command contains control, invisible formatting or lone surrogate characters "
                         f"({', '.join(bad[:8])}); send plain text")
    return v


class ForkOrigin(Part):
    """Where a forked task comes from: a recorded task and the step it continues before (minor version 9)."""

    log: Label = ""
    """The parent log's file name."""
    task_id: Id = ""
    """The parent task."""
    step: int = Field(1, ge=1)
    """The first step of the fork: the world is the parent's as it was before this step."""


class ResumeStep(Part):
    """One executed step of a resumed task, as the History remembers it (minor version 9)."""

    step: int = Field(0, ge=0)
    skill: Name
    """The skill run, or "(invalid answer)" for a step without a valid one."""
    argument: Label | None = None
    state: Name = "failed"
    """The skill's terminal state."""
    message: Text = ""
    perceived: Text = ""
    summary: str = Field("", max_length=MAX_TRACE_CHARS)
    reasoning: str = Field("", max_length=MAX_TRACE_CHARS)
    outcome: SkillOutcome | None = None
    image_description: str = Field("", max_length=MAX_TRACE_CHARS)
    prediction: str = Field("", max_length=MAX_TRACE_CHARS)


class Resume(Part):
    """A task continued from a recorded one (a flight fork, minor version 9): the steps before, and where from."""

    origin: ForkOrigin
    history: tuple[ResumeStep, ...] = Field((), max_length=MAX_HISTORY_STEPS)
    """The parent's steps before `origin.step`, oldest first."""


class TaskRequest(Message):
    """Action protocol, task level: the goal (a natural-language command L, with overrides)."""

    kind: Literal["task_request"] = "task_request"
    command: str = Field(..., min_length=1, max_length=MAX_COMMAND_CHARS)
    """Natural-language command L."""
    task_id: Id = Field(default_factory=lambda: new_id("task-"))
    """Task id (generated when omitted)."""
    backend: BackendName | None = None
    """Override of the reasoner's backend (rules, openai, anthropic, replay)."""
    variant: Variant | None = None
    """Override of the prompt variant."""
    t_max_s: float | None = Field(None, gt=0, le=3600)
    """Override of T_max, seconds."""
    takeoff: bool = True
    """Take off first when the vehicle is on the ground."""
    resume: Resume | None = None
    """Continue a recorded task from one of its steps (a flight fork, minor version 9): the History of the steps
    before it; the new task's steps are numbered from there."""

    @field_validator("command")
    @classmethod
    def _printable(cls, v: str) -> str:
        return command_text(v)


class TaskAccept(Message):
    """Action protocol, task level: the task was accepted (with its id) or rejected (with why)."""

    kind: Literal["task_accept"] = "task_accept"
    accepted: bool
    """Whether the task was started."""
    task_id: Id = ""
    """The task id."""
    reason: Text = ""
    """Why not (e.g. a task already runs on this vehicle)."""


class TaskStatus(Message):
    """Action protocol, task level: feedback while the task runs and its one terminal result."""

    kind: Literal["task_status"] = "task_status"
    stamp_ns: int = Field(default_factory=now_ns)
    """Publish time."""
    vehicle_id: VehicleId = "am1"
    """Vehicle."""
    task_id: Id
    """Task id."""
    command: str = Field(..., max_length=MAX_COMMAND_CHARS)
    """The command L."""
    state: TaskState
    """pending, running, succeeded, failed, aborted, timeout."""
    message: Text = ""
    """Explanation (why it failed, who aborted)."""
    steps: int = 0
    """Reasoning steps so far."""
    model_calls: int = 0
    """Model queries so far."""
    invalid_answers: int = 0
    """Invalid answers so far."""
    backend: BackendLabel = ""
    """Backend in use."""
    variant: Variant = "full"
    """Prompt variant in use."""
    started_ns: int = 0
    """Start time."""
    ended_ns: int = 0
    """End time (0 while running)."""
    forked_from: ForkOrigin | None = None
    """The recorded task this one continues (a flight fork, minor version 9)."""
    speculations: int = 0
    """Next steps asked for while the previous skill flew (AERMANI_REASONER_SPECULATE; minor 11). Their model
    calls count in `model_calls` only when the answer was used."""
    speculations_used: int = 0
    """Of those, the answers used: the skill ended as predicted and the fresh observation agreed (minor 11)."""


# --------------------------------------------------------------------------- health


class Health(Message):
    """A service's health, published at about 1 Hz."""

    kind: Literal["health"] = "health"
    stamp_ns: int = Field(default_factory=now_ns)
    """Publish time."""
    service: Name
    """Service name."""
    ok: bool
    """Whether the service works as it should."""
    message: Text = ""
    """What is wrong, when not ok."""
    details: dict[Label, Any] = Field({}, max_length=MAX_HEALTH_DETAILS)
    """Service-specific figures (fps, queue drops, file path...)."""


class Heartbeat(Message):
    """Proof that a service's event loop runs: every service publishes it twice a second (shared.service), and
    the launcher restarts a service whose heartbeat stops while its process lives (hung or stopped)."""

    kind: Literal["heartbeat"] = "heartbeat"
    stamp_ns: int = Field(default_factory=now_ns)
    """Publish time."""
    service: Name
    """Service name."""
    pid: int = Field(ge=0)
    """Process id, so a supervisor tells a restarted process from the one it replaced."""
    loop_lag_ms: float = Field(0.0, ge=0, allow_inf_nan=False)
    """How late the loop woke for this beat: a busy or blocked loop shows here first."""
    bus_dropped: int = Field(0, ge=0)
    """Samples this service's bus has dropped so far because a consumer was slow (minor version 2), so a
    supervisor or a soak run sees drops of services that publish no health of their own."""


# --------------------------------------------------------------------------- simulator (evaluation only)


class JudgeCriteria(Part):
    """What the simulator's judge requires of a pick or a placement (minor version 6). Part of a task's own
    definition (its suite line), laid out with its scenario at reset, so no caller of the judge can loosen it
    afterwards."""

    lift_m: float = Field(0.03, ge=0.0, le=1.0)
    """Picked: the object's bottom at least this far above the top of what it stood on, metres."""
    hold_s: float = Field(1.0, ge=0.0, le=60.0)
    """Picked: lifted and touching nothing but the vehicle for this long (simulated time), seconds."""
    rest_s: float = Field(2.0, ge=0.0, le=60.0)
    """Placed: at rest (the simulator's rest speed and spin) for this long (simulated time), seconds."""
    upright_tolerance_deg: float = Field(20.0, ge=0.0, le=180.0)
    """Placed: the object's own up axis within this angle of the world's up, signed (upside down is 180 deg;
    spheres have no up), degrees."""
    top_tolerance_m: float = Field(0.02, ge=0.0, le=0.5)
    """Placed: |object bottom - surface top| at most this, metres (contact penetration is a few mm)."""


class Scenario(Message):
    """A simulator layout to reset to (evaluation): seed, target, destination, distractors."""

    kind: Literal["scenario"] = "scenario"
    seed: int = 0
    """Layout seed."""
    target_object: Label | None = None
    """Canonical name of the object the task is about (e.g. "red cup")."""
    destination: Label | None = None
    """Canonical name of the destination surface (e.g. "table", "round table", "sink")."""
    distractors: tuple[Label, ...] | None = Field(None, max_length=MAX_SCENARIO_OBJECTS)
    """Other objects to place; None lets the seed choose."""
    target_out_of_view: bool = False
    """Put the target outside the initial camera view (search tasks)."""
    extra_objects: tuple[Label, ...] = Field((), max_length=MAX_SCENARIO_OBJECTS)
    """Objects that must be present besides target and distractors (e.g. both "orange" and "banana")."""
    start: Pose | None = None
    """Vehicle start pose on the ground; None lets the seed choose."""
    placements: dict[Label, Label] | None = Field(None, max_length=MAX_SCENARIO_OBJECTS)
    """Object -> surface it must start on (e.g. {"orange": "counter"}); others go where the seed puts them."""
    criteria: JudgeCriteria = JudgeCriteria()
    """Success criteria the judge applies in this layout, from the task's definition (minor version 6)."""


class SimLabel(Part):
    """One instance of the simulator's segmentation image (oracle mode only)."""

    id: int
    """Instance id in the segmentation image."""
    name: Label
    """Canonical name (e.g. "red cup", "round table")."""
    category: Literal["object", "surface", "furniture", "structure"]
    """Graspable object, support surface, other furniture, or walls/floor."""
    color: Name = ""
    """Dominant colour name."""
    size: Vec3 | None = None
    """Extent, metres."""


class SimLabels(Message):
    """Instance id -> name for the simulator's segmentation image (oracle mode only)."""

    kind: Literal["sim_labels"] = "sim_labels"
    stamp_ns: int = Field(default_factory=now_ns)
    """Publish time."""
    labels: tuple[SimLabel, ...] = Field((), max_length=MAX_WORLD_OBJECTS)
    """Instance id table of the current layout."""


class SimObjectTruth(Part):
    """Ground truth of one simulated object (judge only)."""

    name: Label
    """Canonical name."""
    category: Name
    """object, surface, furniture."""
    position: Vec3
    """Centre of the bounding box, world ENU."""
    yaw: float = 0.0
    """Yaw, radians."""
    size: Vec3
    """Extent, metres."""
    top_z: float = 0.0
    """Top height."""
    attached: bool = False
    """In the gripper."""
    support: Label | None = None
    """Surface it rests on, if any."""


class JudgeRequest(Message):
    """Ask the simulator's ground-truth judge a question (evaluation only)."""

    kind: Literal["judge_request"] = "judge_request"
    op: Literal["world", "on_surface", "held"] = "world"
    """world: everything; on_surface: is `object` placed on `surface` (out of the gripper, resting on it by
    contact, upright, inside its top's footprint, its bottom on the top, at rest for the scenario's
    `criteria.rest_s`); held: has the gripper picked an object (in both pads, lifted `criteria.lift_m` clear,
    touching nothing else, for `criteria.hold_s`)."""
    object: Label | None = None
    """Object name for on_surface."""
    surface: Label | None = None
    """Surface name for on_surface."""
    tolerance: float = 0.05
    """Deprecated (minor version 6) and ignored: the criteria are the task's (`Scenario.criteria`, fixed at
    reset), not the caller's, so no caller can loosen them. Kept so older senders still validate."""


class JudgeCheck(Part):
    """One check behind a judge's verdict, with what it measured (minor version 6)."""

    name: Name
    """in_gripper, clear, lift, hold (a pick); released, support, upright, footprint, top, rest (a placement)."""
    ok: bool
    """Whether this check passed."""
    detail: Text = ""
    """Why, in words."""
    measured: float | None = None
    """The measured number (lift m, hold s, tilt deg, distance inside the edge m, bottom - top m, rest s)."""
    limit: float | None = None
    """The criterion it is held to (from the scenario's `criteria`)."""
    unit: Name = ""
    """Unit of `measured` and `limit`."""


class SimIncident(Part):
    """Something the simulator recorded since the reset that a careful operator would count against a flight
    (minor version 10): the airframe or the gripper touching what it should not, an object knocked over or
    dropped."""

    kind: Literal["vehicle", "gripper", "knocked", "dropped"]
    """vehicle: the airframe or its gear touched furniture, a wall or the ceiling; gripper: a finger pad or arm
    struck furniture, a wall, the ceiling or an object other than the task's target; knocked: an object not in the
    pads tipped over or left what it stood on; dropped: an object lifted clear left the pads and fell more than
    0.1 m before coming to rest."""
    thing: Label
    """What was hit, knocked or dropped (walls are "wall")."""
    t_s: float
    """Simulated time since the reset, seconds."""
    detail: Text = ""
    """What was measured (contact speed, tilt, fall)."""


class JudgeResult(Message):
    """The judge's ground-truth answer (evaluation only; no policy reads it)."""

    kind: Literal["judge_result"] = "judge_result"
    ok: bool = True
    """Answer to the question (on_surface: whether it is placed; held: whether an object is picked)."""
    message: Text = ""
    """Why: the first failed check, or what passed, with the measured numbers."""
    checks: tuple[JudgeCheck, ...] = Field((), max_length=MAX_CHECKS)
    """Every check of the verdict with its measured number and limit (on_surface, held; minor version 6)."""
    pending_s: float | None = None
    """Simulated seconds after which the verdict would turn true if nothing moves (only a hold or rest time is
    short); None when waiting would not change it (minor version 6)."""
    objects: tuple[SimObjectTruth, ...] = Field((), max_length=MAX_WORLD_OBJECTS)
    """Ground truth of every object and surface (op=world)."""
    held: Label | None = None
    """Object in both pads, picked or not (`ok` of op held says whether it is picked)."""
    vehicle: Pose | None = None
    """Vehicle pose (ground truth)."""
    collisions: tuple[Text, ...] = Field((), max_length=MAX_WORLD_OBJECTS)
    """Incidents since the last reset as tags, each once: "vehicle-shelf" (the airframe), "gripper-table" (a
    pad or arm), "knocked-red cup", "dropped-red cup" (`incidents` has each with its time)."""
    incidents: tuple[SimIncident, ...] = Field((), max_length=MAX_WORLD_OBJECTS)
    """The same incidents with their kind, simulated time and what was measured (minor version 10)."""
    scenario: Scenario | None = None
    """Scenario in force."""
    sim_time_s: float | None = Field(None, ge=0.0)
    """Simulated seconds since the world was last reset, when the answer was made (minor version 10): the
    evaluation's clock for task time in simulated seconds, apart from the wall clock at a speed factor."""


class SimState(Message):
    """The simulator's whole state when a skill ended (minor version 9): a flight fork starts from it
    (`aermani fork`). Published by the simulator only; a real vehicle has none."""

    kind: Literal["sim_state"] = "sim_state"
    stamp_ns: int = Field(default_factory=now_ns)
    """When it was captured."""
    task_id: Id = ""
    """The task whose skill ended."""
    step: int = Field(0, ge=0)
    """The step whose skill ended (0: the take-off): the world before step `step + 1`."""
    skill: Name = ""
    """That skill."""
    sim_time_s: float = 0.0
    """Simulated time."""
    state: str = Field(..., max_length=MAX_SIM_STATE_CHARS)
    """The state as a JSON document (services/sim/snapshot.py: its `format` says how to read it)."""


class SimResetResult(Message):
    """Whether the simulator laid out the requested scenario."""

    kind: Literal["sim_reset_result"] = "sim_reset_result"
    ok: bool
    """Whether the world was reset."""
    message: Text = ""
    """Explanation."""
    scenario: Scenario | None = None
    """Scenario now in force (with everything the seed chose)."""


# Every publishable message type, for tests and the recorder.
MESSAGE_TYPES: tuple[type[Message], ...] = (
    VehicleState, ArmCommand, DisarmCommand, TakeoffCommand, GotoCommand, HoldCommand, LandCommand,
    GripperCommand, PreflightCommand, PreflightReport, AutopilotResult, LocalizeRequest, ObjectEstimate,
    PlacementEstimate, Detections,
    SkillLibrary, SkillRequest, SkillAccept, WorkingMemory, SkillStatus, Abort, AbortAck, ReasoningStep,
    TaskRequest, TaskAccept, TaskStatus, Health, Scenario, SimLabels, JudgeRequest, JudgeResult, SimResetResult,
    SimState, CancelGoal, GoalRef, CancelReply, ResetNotice, ApprovalStatus, ApprovalDecision, Heartbeat,
    MemoryRestore,
)
MESSAGES_BY_SCHEMA: dict[str, type[Message]] = {m.full_schema_name(): m for m in MESSAGE_TYPES}
