"""Input and output models of the gateway's HTTP API (bus messages stay in shared.messages)."""

from __future__ import annotations

from enum import StrEnum
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

from shared.messages import MAX_COMMAND_CHARS, SkillStatus, Variant, VehicleState, command_text

VEHICLE_ID_PATTERN = r"^[A-Za-z0-9_-]{1,32}$"


class ApiModel(BaseModel):
    """Base of the HTTP API's models: field docstrings become the schema descriptions; unknown fields are rejected."""

    model_config = ConfigDict(use_attribute_docstrings=True, extra="forbid")


# --------------------------------------------------------------------------- errors


class ErrorBody(ApiModel):
    """Every 4xx/5xx answer has this body."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"error": "conflict", "detail": "task task-1a2b3c4d5e6f is still running on am1; abort it first",
         "status": 409}]})

    error: str
    """Short machine-readable error name (not_found, conflict, unauthorized, validation_error...)."""
    detail: str
    """What was wrong, and what to do about it."""
    status: int
    """The HTTP status code, repeated for clients that lose it."""
    fields: list[dict[str, Any]] | None = None
    """For validation errors: each offending field with its location and message."""


# --------------------------------------------------------------------------- tasks


class TaskCreate(ApiModel):
    """A command for one vehicle."""

    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True, json_schema_extra={"examples": [
        {"command": "pick up the red cup and place it on the table", "vehicle_id": "am1"},
        {"command": "put the banana in the bowl", "variant": "drt_v2", "t_max_s": 300}]})

    command: str = Field(..., min_length=1, max_length=MAX_COMMAND_CHARS)
    """Natural-language command (printable text, at most 500 characters)."""
    vehicle_id: str | None = Field(None, pattern=VEHICLE_ID_PATTERN)
    """Target vehicle; may be omitted only while one vehicle's reasoner is alive (422 with several)."""
    backend: str | None = Field(None, pattern=r"^[a-z][a-z0-9_]{0,31}$")
    """Override of the reasoner's policy backend: a kind registered in the reasoner (`aermani vlm backends`);
    the reasoner refuses an unknown one, or one it cannot build, with the reason (409)."""
    variant: Variant | None = None
    """Override of the prompt variant."""
    t_max_s: float | None = Field(None, gt=0, le=3600)
    """Override of T_max, seconds."""
    takeoff: bool = True
    """Take off first when the vehicle is on the ground."""

    @field_validator("command")
    @classmethod
    def _printable(cls, v: str) -> str:
        return command_text(v)


class TaskLinks(ApiModel):
    """Hypermedia links of a task: itself, its event stream and its abort endpoint."""

    self: str
    """URL of the task."""
    events: str
    """URL of its Server-Sent Events stream."""
    abort: str
    """URL to abort it (POST)."""


class TaskPhase(StrEnum):
    """A task's state as the API shows it: the reasoner's TaskState, plus `aborting` between an abort the
    gateway sent and the task's end being stored (the reasoner has not said yet how the task ended)."""

    PENDING = "pending"
    RUNNING = "running"
    ABORTING = "aborting"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    ABORTED = "aborted"
    TIMEOUT = "timeout"


class TaskCreated(ApiModel):
    """Response to POST /tasks: the accepted task's id, vehicle, state and links."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"task_id": "task-1a2b3c4d5e6f", "vehicle_id": "am1", "state": "pending",
         "links": {"self": "/api/v1/tasks/task-1a2b3c4d5e6f", "events": "/api/v1/tasks/task-1a2b3c4d5e6f/events",
                   "abort": "/api/v1/tasks/task-1a2b3c4d5e6f/abort"}}]})

    task_id: str
    """Id of the accepted task."""
    vehicle_id: str
    """Vehicle it runs on."""
    state: TaskPhase
    """State right after acceptance (pending or running)."""
    links: TaskLinks
    """Where to follow it."""


class TaskSummary(ApiModel):
    """One task in a listing: id, vehicle, command, state and timing."""

    task_id: str
    """Task id."""
    vehicle_id: str
    """Vehicle."""
    command: str
    """The command L."""
    state: TaskPhase
    """pending, running, aborting (an abort was sent, the task's end is not stored yet), then succeeded,
    failed, aborted or timeout."""
    message: str = ""
    """Why it ended the way it did."""
    created_ns: int
    """When the gateway accepted (or first saw) it, ns since the epoch."""
    updated_ns: int
    """Last change, ns since the epoch."""
    steps: int = 0
    """Reasoning steps so far."""


class TaskPage(ApiModel):
    """A page of the task listing with the total count for pagination."""

    items: list[TaskSummary]
    """Tasks, newest first."""
    total: int
    """Tasks matching the filter."""
    offset: int
    """Offset of the first item."""
    limit: int
    """Page size used."""


class StepOut(ApiModel):
    """One reasoning step: the DRT, the STE and how the skill ended (see shared.messages.ReasoningStep)."""

    event_id: int
    """Id of the event that last updated this step."""
    step: dict[str, Any]
    """The ReasoningStep as published by the reasoner (task_id, step, drt, ste, calls, skill_state...)."""


class Metrics(ApiModel):
    """Per-task metrics: reasoning steps, model calls, invalid answers, IAR, skills used and durations."""

    steps: int = 0
    """Reasoning steps recorded."""
    model_calls: int = 0
    """Model queries, valid and invalid."""
    invalid_answers: int = 0
    """Answers that did not parse into a valid DRT/STE."""
    iar: float | None = None
    """Invalid Answer Ratio = invalid answers / model calls (None before the first call)."""
    latency_p50_s: float | None = None
    """Median model latency, seconds."""
    latency_p95_s: float | None = None
    """95th-percentile model latency, seconds."""
    skills: dict[str, int] = {}
    """Terminal skill results by state (succeeded, failed...)."""
    skill_time_s: float = 0.0
    """Total wall time of the executed skills."""
    duration_s: float | None = None
    """Task wall time so far (or in total once ended)."""
    speculative_steps: int = 0
    """Steps whose answer was asked for while the previous skill flew and used (AERMANI_REASONER_SPECULATE); the
    task's status says how many were asked for (`speculations`, `speculations_used`)."""


class TaskDetail(TaskSummary):
    """A task in full: its request, latest status, every reasoning step and skill result."""

    request: dict[str, Any] = {}
    """The request as posted (overrides included)."""
    status: dict[str, Any] | None = None
    """Latest TaskStatus from the reasoner."""
    reasoning_steps: list[StepOut] = []
    """Every reasoning step, in order, with DRT and STE."""
    skill_results: list[dict[str, Any]] = []
    """Final SkillStatus of every skill the executor ran for this task."""
    metrics: Metrics = Metrics()
    """Figures so far."""
    last_event_id: int = 0
    """Id of the newest event of this task (for resuming the stream)."""


# --------------------------------------------------------------------------- abort


class AbortIn(ApiModel):
    """Body of an abort request: the reason and, optionally, the one vehicle to stop."""

    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True,
                              json_schema_extra={"examples": [{"reason": "person entered the area"}]})

    reason: str = Field("operator abort via gateway", min_length=1, max_length=200)
    """Why (recorded by the executor and the reasoner)."""
    vehicle_id: str | None = Field(None, pattern=r"^[A-Za-z0-9_-]{1,32}$")
    """Only this vehicle (POST /abort); every vehicle when omitted."""


def abort_summary(acked: dict[str, dict[str, str]]) -> dict[str, str]:
    """One line per vehicle for AbortOut.messages: the executor's answer, else the bridge's."""
    return {vid: by.get("executor") or by.get("autopilot_bridge") or next(iter(by.values()), "")
            for vid, by in acked.items()}


class AbortOut(ApiModel):
    """Result of an abort: the vehicles addressed, which acknowledged, and each service's answer."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"vehicles": ["am1"], "acknowledged": ["am1"], "task_id": "task-1a2b3c4d5e6f",
         "messages": {"am1": "stopped grasp (goal goal-0123456789ab), holding position"},
         "services": {"am1": {"executor": "stopped grasp (goal goal-0123456789ab), holding position",
                              "autopilot_bridge": "holding in AUTO.LOITER (PX4 Hold)"}}}]})

    vehicles: list[str]
    """Vehicles the abort was sent to."""
    acknowledged: list[str]
    """Vehicles where at least one service (executor or autopilot bridge) acknowledged the abort in time."""
    task_id: str | None = None
    """Task aborted, when one was named."""
    messages: dict[str, str] = {}
    """What each acknowledging vehicle did: its executor's answer (e.g. "holding position"), else its
    autopilot bridge's."""
    services: dict[str, dict[str, str]] = {}
    """Per vehicle, which services acknowledged and what each did ({"am1": {"executor": ...,
    "autopilot_bridge": ...}}); a service missing here did not answer in time (dead or unreachable)."""


# --------------------------------------------------------------------------- health


class VehicleHealth(ApiModel):
    """Health of one vehicle: service liveliness, autopilot link and offboard state, battery."""

    vehicle_id: str
    """Vehicle id."""
    services: dict[str, bool]
    """Liveliness of each service seen for this vehicle."""
    link_ok: bool | None = None
    """Autopilot heartbeats arrive (None: no state received yet)."""
    offboard_ok: bool | None = None
    """OFFBOARD with setpoints streaming."""
    armed: bool | None = None
    """Motors armed."""
    mode: str | None = None
    """Flight mode."""
    battery_remaining: float | None = None
    """Battery, percent."""
    segmenter: str | None = None
    """Perception's segmenter (color, sam3, or sim: the simulator's ground-truth oracle, not real perception)."""
    realism: str | None = None
    """The simulator's realism (realistic, harsh or ideal), when the vehicle is simulated."""
    battery_voltage: float | None = None
    """Battery, volts."""
    state_age_s: float | None = None
    """Age of the newest vehicle state, seconds."""
    state: VehicleState | None = None
    """Newest vehicle state (pose, velocity, gripper...)."""
    camera_age_s: float | None = None
    """Age of the newest camera frame, seconds."""
    running_task: str | None = None
    """Id of the task running on it, if any."""


class HealthOut(ApiModel):
    """Response of GET /health: the gateway, its database and every vehicle's health."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"ok": True, "database": True, "vehicles": [{"vehicle_id": "am1", "services": {"reasoner": True,
         "executor": True}, "link_ok": True, "offboard_ok": False, "battery_remaining": 87.0}]}]})

    ok: bool
    """Gateway and its database work; at least one vehicle is reachable."""
    database: bool
    """The SQLite store answers."""
    vehicles: list[VehicleHealth]
    """Every vehicle seen on the bus."""


SkillStatusOut = SkillStatus


class SkillsOut(ApiModel):
    """The skill library a vehicle's executor serves."""

    vehicle_id: str
    """Vehicle."""
    skills: list[dict[str, Any]]
    """Every skill (see shared.messages.SkillSpec): name, category, description, argument, policy_visible."""


class DetectionsOut(ApiModel):
    """What perception sees now on one vehicle."""

    vehicle_id: str
    """Vehicle."""
    stamp_ns: int
    """Time of the frame the detections come from."""
    items: list[dict[str, Any]]
    """Detections (see shared.messages.Detection): label, category, centroid, size, confidence."""


class SkillRunIn(ApiModel):
    """Run one skill outside a task (only when the gateway allows it)."""

    skill: str = Field(..., min_length=1, max_length=64, pattern=r"^[a-z][a-z0-9_]*$")
    """Registered skill name, e.g. `yaw_left` or `obj_localization`."""
    argument: str | None = Field(None, max_length=200)
    """Object or surface query, for skills that take one."""
    timeout_s: float = Field(120.0, gt=0, le=600)
    """How long to wait for the result."""


class SkillRunOut(ApiModel):
    """How a single skill ended."""

    vehicle_id: str
    skill: str
    state: str
    """succeeded, failed, timeout or aborted."""
    message: str
    """The executor's explanation."""
    perceived: str = ""
    """What perception reported during the skill."""


class ApprovalOut(ApiModel):
    """A skill waiting for the operator (see shared.messages.ApprovalStatus)."""

    approval_id: str
    vehicle_id: str
    task_id: str
    step: int
    skill: str
    argument: str | None = None
    reasoning: str = ""
    """Why the policy chose it."""
    stamp_ns: int
    expires_ns: int = 0
    """When it expires (the vehicle then holds and the step fails)."""


class ApprovalDecisionIn(ApiModel):
    """The operator's decision."""

    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True,
                              json_schema_extra={"examples": [{"approve": False, "reason": "wrong cup"}]})

    approve: bool
    """True runs the skill; False makes the policy choose again."""
    reason: str = Field("", max_length=300)
    """Why (the policy reads it on a rejection)."""
    operator: str = Field("operator", min_length=1, max_length=64)
    """Who decides."""


class ApprovalDecisionOut(ApiModel):
    """The decision was delivered to the reasoner."""

    approval_id: str
    vehicle_id: str
    approved: bool
