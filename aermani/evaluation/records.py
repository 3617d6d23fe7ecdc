"""The per-episode record written to episodes.jsonl: the task, the verdict and every reasoning step."""

from __future__ import annotations

import json
import threading
from pathlib import Path

from pydantic import BaseModel, ConfigDict, model_validator

from aermani.evaluation.tasks import EvalTask
from shared.messages import JudgeResult, ReasoningStep, TaskStatus
from shared.tasks import REFUSED_BEFORE_TAKEOFF

RESULTS_FILE = "episodes.jsonl"


class ChoiceOutcome(BaseModel):
    """A choice task's decision by the simulator and what the policy did with it (EpisodeRecord.choice)."""

    model_config = ConfigDict(frozen=True)

    criterion: str
    """What decides the object, in words."""
    answer: tuple[str, ...]
    """The object(s) meeting it in this world (two on a tie)."""
    reason: str
    """Why, from the world: the true sizes, or where the conditional's object is."""
    chosen: str | None = None
    """The object the policy picked (the grasp that succeeded last), if any."""
    informed: bool | None = None
    """Whether the policy had seen what decides the choice before it picked: every compared object (size), the
    place the condition is about (conditional); None where the recorded steps cannot tell (no live observation
    in the prompt and no localization of them)."""
    needed: tuple[str, ...] = ()
    """What the policy had to see for its choice to be informed."""
    seen: tuple[str, ...] = ()
    """What of that the policy had seen before the pick."""


class EpisodeRecord(BaseModel):
    """Everything about one finished episode; the report and the metrics are computed from these only."""

    model_config = ConfigDict(extra="ignore", use_attribute_docstrings=True)

    episode_id: str
    """Stable id: <backend>/<variant>/<suite>/<index>-s<seed>."""
    suite: str
    """Task category."""
    backend: str
    """Reasoner backend (a registered kind, see `aermani vlm backends`)."""
    variant: str
    """Prompt variant."""
    model: str = ""
    """Model name for model backends."""
    task: EvalTask
    """The task."""
    seed: int
    """Layout seed."""
    vehicle_id: str = ""
    """Simulated vehicle that ran it."""
    task_id: str = ""
    """Reasoner task id."""
    state: str = "error"
    """Terminal task state (succeeded, failed, aborted, timeout) or error when the harness failed."""
    message: str = ""
    """Reasoner's or harness's explanation."""
    success: bool = False
    """Success as SR counts it: the task ended `succeeded` (before T_max) AND the judge found the right object
    placed on the destination (or held)."""
    judge_success: bool | None = None
    """The simulator's ground-truth judge alone, whatever the task's end state (None in records from before it
    was kept apart)."""
    verdict: str = ""
    """Why the verdict is what it is."""
    held: str | None = None
    """What the gripper held at the end (ground truth)."""
    collisions: tuple[str, ...] = ()
    """Collisions reported by the simulator."""
    steps: list[ReasoningStep] = []
    """Every reasoning step of the task, in order."""
    status: TaskStatus | None = None
    """Terminal task status."""
    judge: JudgeResult | None = None
    """The simulator's answer to the success question."""
    t_max_s: float = 600.0
    """T_max in force."""
    started_ns: int = 0
    """When the task was started (harness clock)."""
    sim_started_s: float | None = None
    """Simulated seconds since the reset when the task was started (the judge's clock, asked just before)."""
    sim_ended_s: float | None = None
    """Simulated seconds since the reset when the terminal status arrived (asked just after)."""
    ended_ns: int = 0
    """When the terminal status arrived."""
    attempts: int = 1
    """Trials started for this episode (a take-off failure before the first reasoning step restarts it)."""
    restarts: list[str] = []
    """Why each earlier trial of this episode was restarted (one line per restart)."""
    stale_memory: str = ""
    """Legacy (records from before the executor followed the sim's reset notice): the harness found the
    executor's memory left over from the previous episode and restarted the executor process. Reported."""
    foreign_samples: int = 0
    """Step samples seen on this vehicle's key during the episode that belonged to another task (cross-talk)."""
    motions_ok: bool | None = None
    """Whether the motions the task asks for (`task.motions`) happened before the pick, from the recorded
    trajectory (None: the task asks for none, or a record from before they were checked)."""
    motions_detail: str = ""
    """How each motion was found in the trajectory, or the first that was not."""
    choice: ChoiceOutcome | None = None
    """A choice task's decision by the simulator (the object meeting the size comparison or the conditional's
    branch, from the world at the start), the object chosen and whether the policy had seen what decides it."""
    harness_error: str = ""
    """Set when the episode could not run (reset failed, no status...)."""

    @model_validator(mode="after")
    def _refusal_is_a_result(self) -> EpisodeRecord:
        """Records from harness versions that excluded a refused command as "failed before the first reasoning
        step": a refusal is the policy's answer, so such an episode counts as a failure (it stays listed with
        its retries)."""
        if (self.harness_error.startswith("failed before the first reasoning step") and self.status is not None
                and self.status.message.startswith(REFUSED_BEFORE_TAKEOFF)):
            self.harness_error = ""
        return self

    @property
    def duration_s(self) -> float:
        """End-to-end task time: from the reasoner's start/end stamps when present, else the harness's."""
        if self.status is not None and self.status.started_ns and self.status.ended_ns:
            return (self.status.ended_ns - self.status.started_ns) / 1e9
        return max(0.0, (self.ended_ns - self.started_ns) / 1e9)

    @property
    def sim_duration_s(self) -> float | None:
        """End-to-end task time in simulated seconds (None in records from before the judge told its clock)."""
        if self.sim_started_s is None or self.sim_ended_s is None:
            return None
        return max(0.0, self.sim_ended_s - self.sim_started_s)

    @property
    def config(self) -> str:
        return f"{self.backend}/{self.variant}"


class ResultsFile:
    """Append-only JSONL of EpisodeRecords, one line per finished episode, flushed at once so an interrupted
    run loses at most the episodes in flight. A truncated last line (killed mid-write) is ignored."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()

    def load(self) -> list[EpisodeRecord]:
        out: dict[str, EpisodeRecord] = {}
        if not self.path.exists():
            return []
        for line in self.path.read_text(encoding="utf-8").splitlines():
            line = line.strip()
            if not line:
                continue
            try:
                rec = EpisodeRecord.model_validate(json.loads(line))
            except (json.JSONDecodeError, ValueError):
                continue
            out[rec.episode_id] = rec  # a rerun episode replaces an older line
        return list(out.values())

    def finished_ids(self) -> set[str]:
        """Episodes that ran to a verdict; those the harness could not run are tried again on a rerun."""
        return {r.episode_id for r in self.load() if not r.harness_error}

    def append(self, rec: EpisodeRecord) -> None:
        line = rec.model_dump_json() + "\n"
        with self._lock:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "a", encoding="utf-8") as f:
                # A torn line from a killed run must not glue onto this one.
                if f.tell() > 0:
                    with open(self.path, "rb") as r:
                        r.seek(-1, 2)
                        if r.read(1) != b"\n":
                            f.write("\n")
                f.write(line)
                f.flush()
