"""The Zenoh key space of aermani in one place: `aermani/v1/<vehicle_id>/<topic>`."""

from __future__ import annotations

from dataclasses import dataclass

ROOT = "aermani/v1"
DEFAULT_VEHICLE_ID = "am1"

# Topic suffixes (after the vehicle prefix). Kind: pub = publication, q = queryable, tok = liveliness.
CAMERA_COLOR = "camera/color"  # pub  foxglove.CompressedImage (JPEG), protobuf
CAMERA_DEPTH = "camera/depth"  # pub  foxglove.RawImage 16UC1 millimetres, same timestamp as color
CAMERA_CALIBRATION = "camera/calibration"  # pub  foxglove.CameraCalibration
CAMERA_SEGMENTATION = "camera/segmentation"  # pub  foxglove.RawImage 16UC1 instance ids (sim only)
SIM_LABELS = "sim/labels"  # pub  SimLabels JSON: instance id -> name (sim only)
SIM_JUDGE = "sim/judge"  # q    JudgeRequest -> JudgeResult (evaluation only; no policy may read it)
SIM_RESET = "sim/reset"  # q    Scenario -> SimResetResult
SIM_STATS = "sim/stats"  # q    (optional b"reset") -> JSON figures: setpoint intervals, fps, MAVLink counters
TF = "tf"  # pub  foxglove.FrameTransforms (world->base_link, base_link->camera, base_link->gripper)
AUTOPILOT_STATE = "autopilot/state"  # pub  VehicleState
AUTOPILOT_COMMAND = "autopilot/command"  # q    AutopilotCommand -> AutopilotResult
PERCEPTION_LOCALIZE_OBJECT = "perception/localize_object"  # q LocalizeRequest -> ObjectEstimate
PERCEPTION_LOCALIZE_PLACEMENT = "perception/localize_placement"  # q LocalizeRequest -> PlacementEstimate
PERCEPTION_DETECTIONS = "perception/detections"  # pub Detections
EXECUTOR_RUN_SKILL = "executor/run_skill"  # q    SkillRequest -> SkillAccept
EXECUTOR_SKILL_STATUS = "executor/skill_status"  # pub  SkillStatus
EXECUTOR_SKILLS = "executor/skills"  # q    (empty) -> SkillLibrary
EXECUTOR_MEMORY = "executor/memory"  # pub  WorkingMemory
REASONER_START_TASK = "reasoner/start_task"  # q    TaskRequest -> TaskAccept
REASONER_STEP = "reasoner/step"  # pub  ReasoningStep
REASONER_TASK_STATUS = "reasoner/task_status"  # pub  TaskStatus
SAFETY_ABORT = "safety/abort"  # pub  Abort (anyone may trigger)
SAFETY_ABORT_ACK = "safety/abort_ack"  # pub  AbortAck (executor: held)
HEALTH = "health"  # pub  health/<service>: Health
ALIVE = "alive"  # tok  alive/<service>


def vehicle_prefix(vehicle_id: str = DEFAULT_VEHICLE_ID) -> str:
    if not vehicle_id or "/" in vehicle_id or any(c in vehicle_id for c in "*$?#"):
        raise ValueError(f"invalid vehicle id {vehicle_id!r}: use letters, digits, '-' or '_'")
    return f"{ROOT}/{vehicle_id}"


@dataclass(frozen=True)
class Keys:
    """Fully qualified keys for one vehicle. `Keys("am2").autopilot_state` -> `aermani/v1/am2/autopilot/state`."""

    vehicle_id: str = DEFAULT_VEHICLE_ID

    def key(self, suffix: str) -> str:
        return f"{vehicle_prefix(self.vehicle_id)}/{suffix}"

    @property
    def prefix(self) -> str:
        return vehicle_prefix(self.vehicle_id)

    @property
    def all(self) -> str:
        return f"{self.prefix}/**"

    camera_color = property(lambda self: self.key(CAMERA_COLOR))
    camera_depth = property(lambda self: self.key(CAMERA_DEPTH))
    camera_calibration = property(lambda self: self.key(CAMERA_CALIBRATION))
    camera_segmentation = property(lambda self: self.key(CAMERA_SEGMENTATION))
    sim_labels = property(lambda self: self.key(SIM_LABELS))
    sim_judge = property(lambda self: self.key(SIM_JUDGE))
    sim_reset = property(lambda self: self.key(SIM_RESET))
    sim_stats = property(lambda self: self.key(SIM_STATS))
    tf = property(lambda self: self.key(TF))
    autopilot_state = property(lambda self: self.key(AUTOPILOT_STATE))
    autopilot_command = property(lambda self: self.key(AUTOPILOT_COMMAND))
    localize_object = property(lambda self: self.key(PERCEPTION_LOCALIZE_OBJECT))
    localize_placement = property(lambda self: self.key(PERCEPTION_LOCALIZE_PLACEMENT))
    detections = property(lambda self: self.key(PERCEPTION_DETECTIONS))
    run_skill = property(lambda self: self.key(EXECUTOR_RUN_SKILL))
    skill_status = property(lambda self: self.key(EXECUTOR_SKILL_STATUS))
    skills = property(lambda self: self.key(EXECUTOR_SKILLS))
    memory = property(lambda self: self.key(EXECUTOR_MEMORY))
    start_task = property(lambda self: self.key(REASONER_START_TASK))
    reasoning_step = property(lambda self: self.key(REASONER_STEP))
    task_status = property(lambda self: self.key(REASONER_TASK_STATUS))
    abort = property(lambda self: self.key(SAFETY_ABORT))
    abort_ack = property(lambda self: self.key(SAFETY_ABORT_ACK))

    def health(self, service: str) -> str:
        return self.key(f"{HEALTH}/{service}")

    def alive(self, service: str) -> str:
        return self.key(f"{ALIVE}/{service}")


def alive_pattern(vehicle_id: str | None = None) -> str:
    """Liveliness pattern for one vehicle, or for the whole fleet when `vehicle_id` is None."""
    return f"{ROOT}/{vehicle_id or '*'}/{ALIVE}/*"


def parse_alive_key(key: str) -> tuple[str, str]:
    """`aermani/v1/am1/alive/executor` -> ("am1", "executor")."""
    parts = str(key).split("/")
    if len(parts) != 5 or parts[3] != ALIVE:
        raise ValueError(f"not a liveliness key: {key!r}")
    return parts[2], parts[4]
