"""Recorded runs as tools read them: each task's reasoning steps with what the stack measured at each step.

Two sources:

- an MCAP log (the recorder's): the steps, and for each the observation its decision saw, rebuilt from the log's
  vehicle states, detections and working memory as `aermani rereason` rebuilds it (services/reasoner/rereason.py;
  verified against the recorded History text where the log has it);
- an evaluation directory (or its episodes.jsonl): the steps of every episode; the measurements are read back
  from the History part of the prompt each step was shown (the vehicle's position, what perception saw, the
  working memory; written by services/reasoner/prompt.py) and from the previous skill's outcome (the gripper's
  telemetry at its end). A variant whose prompt has no live observation (unstructured, paper History) leaves
  those unmeasured.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from aermani.evaluation.grounding import StepGrounding, StepObservation, check_steps
from aermani.evaluation.records import RESULTS_FILE, EpisodeRecord, ResultsFile
from shared.errors import AermaniError
from shared.messages import Detection, ReasoningStep, Vec3


class RunError(AermaniError):
    """A path that is not a readable recorded run (missing, not MCAP, no reasoning step)."""


@dataclass
class RunStep:
    """One recorded step and what was measured when it observed."""

    step: ReasoningStep
    observation: StepObservation | None
    grounding: StepGrounding | None = None
    verified: bool | None = None
    """Whether the rebuilt observation reproduces the History text the model was shown (an MCAP log's steps;
    None where there is nothing to compare, and for an evaluation's, read from that text itself)."""


@dataclass
class RunTask:
    """One task of a run (an episode of an evaluation), its steps in order."""

    key: str
    """How the task is named in the run: its task id, or the episode id of an evaluation."""
    task_id: str
    command: str
    backend: str
    variant: str
    state: str
    steps: list[RunStep] = field(default_factory=list)


@dataclass
class Run:
    """A recorded run: where it came from and its tasks."""

    path: str
    kind: str
    """mcap or evaluation."""
    tasks: list[RunTask]


def load_run(path: str | Path) -> Run:
    """The run at `path`: an MCAP log, an evaluation directory, or an episodes.jsonl. Raises RunError."""
    p = Path(path)
    if not p.exists():
        raise RunError(f"{p}: no such file or directory")
    run = _load_evaluation(p) if p.is_dir() or p.suffix == ".jsonl" else _load_mcap(p)
    if not any(t.steps for t in run.tasks):
        hint = (" (a log the recorder did not finish may hold them in chunks only `aermani log recover` salvages)"
                if run.kind == "mcap" else "")
        raise RunError(f"{p} has no recorded reasoning steps{hint}")
    for task in run.tasks:
        for rs, g in zip(task.steps, check_steps((s.step, s.observation) for s in task.steps), strict=True):
            rs.grounding = g
    return run


# --------------------------------------------------------------------------- MCAP logs


def _load_mcap(p: Path) -> Run:
    from services.reasoner.rereason import LogIndex, observed_steps
    from shared.mcaplog import task_statuses

    try:
        with open(p, "rb") as f:
            magic = f.read(8)
    except OSError as exc:
        raise RunError(f"{p}: cannot read it: {exc}") from exc
    if not magic.startswith(b"\x89MCAP"):
        raise RunError(f"{p} is not an MCAP log (nor an evaluation directory or episodes.jsonl)")
    try:
        index = LogIndex(p)
        statuses = task_statuses(p)
    except Exception as exc:  # a damaged log: the reader's own words
        raise RunError(f"{p}: cannot read the log ({exc}); `aermani log recover` salvages an unfinished one") from exc
    tasks = []
    for task in index.tasks:
        st = statuses.get(task.task_id)
        first = task.steps[0] if task.steps else None
        rt = RunTask(task.task_id, task.task_id, task.command, (st.backend if st else "") or
                     (first.backend if first else ""), task.variant, str(st.state) if st else "unknown")
        for rec, obs, exact in observed_steps(index, task):
            rt.steps.append(RunStep(rec, None if obs is None else _from_observation(obs), verified=exact))
        tasks.append(rt)
    return Run(str(p), "mcap", tasks)


def _from_observation(obs: object) -> StepObservation:
    """A StepObservation from the reasoner's Observation (services/reasoner/prompt.py)."""
    state = getattr(obs, "state", None)
    memory = getattr(obs, "memory", None)
    detections = tuple(getattr(obs, "detections", ()) or ())
    positions = [(d.label, d.centroid.x, d.centroid.y, d.centroid.z) for d in detections if d.centroid is not None]
    if memory is not None:
        positions += [(o.label, o.position.x, o.position.y, o.position.z)
                      for o in (*memory.objects, *memory.placements, *memory.seen)]
    return StepObservation(
        detections=detections, held_object=memory.held_object if memory is not None else None,
        memory_known=memory is not None, gripper_holding=state.gripper_holding if state is not None else None,
        position=state.position if state is not None else None, positions=tuple(positions), source="log")


# --------------------------------------------------------------------------- evaluation directories

_NOW = re.compile(r"^Now: (?:position \((?P<x>-?[\d.]+), (?P<y>-?[\d.]+), (?P<z>-?[\d.]+)\) m, .*?|vehicle pose "
                  r"unknown), holding: (?P<held>.*)\.$", re.M)
_SEES = re.compile(r"^Perception sees now: (?P<items>.*)\.$", re.M)
_MEMORY = re.compile(r"^Working memory: (?P<text>.*)$", re.M)
_AT = re.compile(r"(?:^|; |: )(?P<label>[^;:()]+?) at \((?P<x>-?[\d.]+), (?P<y>-?[\d.]+), (?P<z>-?[\d.]+)\)")


def observation_from_prompt(history: str, previous: ReasoningStep | None = None) -> StepObservation | None:
    """What the History part of a prompt told the model (services/reasoner/prompt.py: describe_state,
    describe_detections, memory_summary), with the gripper's telemetry from the previous skill's outcome.
    None when the text holds no live observation (the paper's History, or no History part)."""
    now, sees = _NOW.search(history), _SEES.search(history)
    if now is None and sees is None:
        return None
    detections: tuple[Detection, ...] | None = None
    if sees is not None:
        items = sees.group("items")
        detections = () if items == "nothing recognised" else tuple(
            Detection(label=item.split(" [", 1)[0].strip()) for item in items.split("; ") if item.strip())
    held = now.group("held") if now is not None else None
    position = (Vec3(x=float(now.group("x")), y=float(now.group("y")), z=float(now.group("z")))
                if now is not None and now.group("x") is not None else None)
    positions: list[tuple[str, float, float, float]] = []
    memory = _MEMORY.search(history)
    if memory is not None:
        positions = [(m.group("label").strip(), float(m.group("x")), float(m.group("y")), float(m.group("z")))
                     for m in _AT.finditer(memory.group("text"))]
    telemetry = None
    facts = previous.outcome.facts if previous is not None and previous.outcome is not None else None
    if facts is not None and facts.gripper_width_m is not None:  # the executor read the gripper at its end
        telemetry = facts.holding is not None
    return StepObservation(detections=detections, held_object=None if held in (None, "nothing") else held,
                           memory_known=held is not None, gripper_holding=telemetry, position=position,
                           positions=tuple(positions), source="prompt")


def record_steps(record: EpisodeRecord) -> list[RunStep]:
    """An evaluation episode's steps in order, each with what its prompt said was measured."""
    out: list[RunStep] = []
    prev: ReasoningStep | None = None
    for s in sorted(record.steps, key=lambda s: s.step):
        history = s.prompt.get("history")
        out.append(RunStep(s, observation_from_prompt(history, prev) if history else None))
        prev = s
    return out


_GROUNDING_CACHE: dict[int, tuple[EpisodeRecord, list[StepGrounding]]] = {}
_CACHE_MAX = 20_000


def episode_grounding(record: EpisodeRecord) -> list[StepGrounding]:
    """The grounding check of every step of an evaluation episode (the report's GVR column). A report computes
    the metrics of one record for several tables: the result is kept while that record object lives."""
    hit = _GROUNDING_CACHE.get(id(record))
    if hit is not None and hit[0] is record:
        return hit[1]
    result = check_steps((s.step, s.observation) for s in record_steps(record))
    if len(_GROUNDING_CACHE) >= _CACHE_MAX:
        _GROUNDING_CACHE.clear()
    _GROUNDING_CACHE[id(record)] = (record, result)
    return result


def _load_evaluation(p: Path) -> Run:
    file = p / RESULTS_FILE if p.is_dir() else p
    if not file.exists():
        raise RunError(f"{p} is not an evaluation directory: no {RESULTS_FILE} in it")
    records = sorted(ResultsFile(file).load(), key=lambda r: r.episode_id)
    if not records:
        raise RunError(f"{file} holds no readable episode")
    tasks = []
    for r in records:
        rt = RunTask(r.episode_id, r.task_id, r.task.command, r.backend, r.variant, r.state, record_steps(r))
        tasks.append(rt)
    return Run(str(p), "evaluation", tasks)
