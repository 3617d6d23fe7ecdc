"""Task suites as data: the paper's four categories, user task files, and their expansion into episodes."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from shared.errors import ConfigError
from shared.messages import MAX_COMMAND_CHARS, JudgeCriteria, Scenario, command_text
from shared.search import NOT_FOUND_MAX_STEPS
from shared.skills import MOTION_PRIMITIVES

SUITES_DIR = Path(__file__).resolve().parent / "suites"
# Paper order (Section IV-B, Table II); also the row order of the report.
PAPER_SUITES = ("localization", "clutter", "sequential", "search")
SUITE_TITLES = {
    "localization": "Localization",
    "clutter": "Pick from Clutter",
    "sequential": "Sequential",
    "search": "Search & Pick",
}
# The paper's AERMANI-VLM reasoning steps per suite (Table II), the bar the rules baseline must meet.
PAPER_RS = {"localization": 11.0, "clutter": 14.1, "sequential": 19.2, "search": 23.7}
DEFAULT_T_MAX_S = 600.0  # paper: T_max = 10 min
# Held-out evaluation (docs/evaluation.md, "Suites and splits"): every built-in task line belongs to one split.
# `dev` is what the project is built and tuned against; `test` gives the headline figures and is never looked
# at while changing the project. Commands are disjoint between the splits, and so are the layout seeds: a
# derived seed of split k lies in [k * 2^30, (k + 1) * 2^30).
SPLITS = ("dev", "test")
DEFAULT_SEEDS_PER_LINE = 2
"""Layouts per suite line when a run names neither --episodes nor --seeds-per-line: every line runs, each on two
layouts (episodes = lines x 2)."""
DEFAULT_SPLIT = "dev"
_SEED_RANGE = 1 << 30


MOTION_KINDS = (*MOTION_PRIMITIVES, "turn", "approach")
"""What an expected motion may name: a motion primitive, `turn` (yaw steps in either direction, all the same
way: "turn around", "spin around") or `approach` (come near the thing named in `to`)."""


class ExpectedMotion(BaseModel):
    """One motion a command asks for (`EvalTask.motions`), checked from the recorded trajectory."""

    model_config = ConfigDict(frozen=True, extra="forbid", use_attribute_docstrings=True)

    skill: Literal["yaw_left", "yaw_right", "forward", "backward", "left", "right", "up", "down", "turn", "approach"]
    """The motion: a motion primitive's name (its direction), `turn` or `approach`."""
    times: int = Field(1, ge=1, le=16)
    """How many steps of it the command asks for ("twice": 2); `approach` is one arrival."""
    to: str | None = None
    """`approach`: the surface (or object) the vehicle must come near."""

    @model_validator(mode="after")
    def _to_for_approach(self) -> ExpectedMotion:
        if (self.skill == "approach") != (self.to is not None):
            raise ValueError("an approach names what it goes `to`, and only an approach does")
        if self.skill == "approach" and self.times != 1:
            raise ValueError("an approach is one arrival (times 1)")
        return self

    def text(self) -> str:
        return f"approach the {self.to}" if self.skill == "approach" else f"{self.skill} x{self.times}"


class SizeChoice(BaseModel):
    """Which object a size comparison names, decided by the simulator from the layout's true sizes."""

    model_config = ConfigDict(frozen=True, extra="forbid", use_attribute_docstrings=True)

    kind: Literal["size"] = "size"
    select: Literal["largest", "smallest", "tallest", "shortest"]
    """largest/smallest: by the volume of the true bounding box; tallest/shortest: by its height."""
    among: tuple[str, ...] = Field(..., min_length=2)
    """The objects compared (all laid out)."""

    def candidates(self) -> tuple[str, ...]:
        return self.among

    def text(self) -> str:
        return f"the {self.select} of {', '.join(self.among)}"


class ConditionalChoice(BaseModel):
    """Which branch of a conditional holds ("if the apple is on the table take it, otherwise the orange"),
    decided by the simulator from what is in the world when the task starts."""

    model_config = ConfigDict(frozen=True, extra="forbid", use_attribute_docstrings=True)

    kind: Literal["conditional"] = "conditional"
    if_present: str
    """The object the condition asks about."""
    on: str | None = None
    """Where it must be for the condition to hold (a surface); None: anywhere in the room."""
    then: str
    """The object to take when the condition holds."""
    otherwise: str
    """The object to take when it does not."""

    def candidates(self) -> tuple[str, ...]:
        return (self.then, self.otherwise)

    def text(self) -> str:
        where = f" on the {self.on}" if self.on else ""
        return f"the {self.then} if a {self.if_present} is{where}, otherwise the {self.otherwise}"


class EvalTask(BaseModel):
    """One task: a command and what counts as success, plus what the simulator must lay out."""

    model_config = ConfigDict(frozen=True, extra="forbid", use_attribute_docstrings=True)

    command: str = Field(..., min_length=1, max_length=MAX_COMMAND_CHARS)
    """Natural-language command L sent to the reasoner."""
    suite: str = "custom"
    """Task category (localization, clutter, sequential, search, or a user's own name)."""
    split: str = DEFAULT_SPLIT
    """Evaluation split: dev (build and tune against it) or test (held out, headline figures only)."""
    target_object: str
    """Canonical name of the object that must be grasped (e.g. "red cup")."""
    accept_objects: tuple[str, ...] = ()
    """Other objects that also satisfy the command (e.g. any snack for "Bring me a snack")."""
    destination: str | None = None
    """Surface the object must end on; None means success is the object held at the end."""
    seed: int | None = None
    """Layout seed; None lets the runner derive one from --seed and the episode index."""
    distractors: tuple[str, ...] | None = None
    """Other objects to lay out; None lets the simulator's seed choose."""
    extra_objects: tuple[str, ...] = ()
    """Objects that must be present (e.g. the tools of "Ignore the tools ...")."""
    target_out_of_view: bool = False
    """Put the target outside the initial view (search tasks)."""
    placements: dict[str, str] | None = None
    """Object -> surface it must start on (e.g. {"orange": "counter"} for "approach the counter ...")."""
    t_max_s: float | None = Field(None, gt=0, le=3600)
    """T_max override for this task, seconds."""
    criteria: JudgeCriteria = JudgeCriteria()
    """What the judge requires (a pick's lift and hold; a placement's rest time, upright and height tolerances).
    Part of the task, laid out with its scenario, so no caller of the judge can loosen it."""
    expect: Literal["success", "not_found"] = "success"
    """`not_found`: the world lacks `target_object` (the scenario lays out only `distractors` and
    `extra_objects`, which must not name it), and the episode succeeds when the task ends failed with a
    not-found reason within `not_found_max_steps` reasoning steps: a policy that claims success, gives up for
    another reason, or searches without end fails it."""
    motions: tuple[ExpectedMotion, ...] = ()
    """The motions the command asks for before the pick, in order (e.g. [{"skill": "up"}, {"skill": "yaw_right"}]
    for "go a bit higher, turn right, and fetch the cup"): the runner checks from the recorded trajectory that
    each happened, in that order, before the grasp that picked the object; an episode whose motions did not
    happen is not a success, whatever the judge says of the pick."""
    choice: SizeChoice | ConditionalChoice | None = Field(None, discriminator="kind")
    """What decides the right object, when the command leaves it to the world (a size comparison, a
    conditional): the simulator decides it from the layout at the start, the decision is recorded per episode,
    and only that object counts (it replaces `target_object` and `accept_objects` for the judge)."""
    not_found_max_steps: int = Field(NOT_FOUND_MAX_STEPS, ge=1, le=200)
    """A not-found task's bound on reasoning steps: by default the steps of a whole search of the room plus the
    `done` and a little slack (shared/search.py, the same coverage the rules baseline's search budget comes
    from); a line whose command asks for motions first adds them. Records from before it was derived carry 40."""

    @field_validator("command")
    @classmethod
    def _strip(cls, v: str) -> str:
        return command_text(v)

    @model_validator(mode="after")
    def _absent_target_is_absent(self) -> EvalTask:
        if self.expect == "not_found":
            if self.distractors is None:
                raise ValueError("a not_found task lists its distractors: the seed must not choose the absent "
                                 f"{self.target_object!r}")
            if self.target_object in (*self.distractors, *self.extra_objects, *(self.placements or {})):
                raise ValueError(f"a not_found task's world must lack {self.target_object!r}")
        return self

    @model_validator(mode="after")
    def _choice_is_laid_out(self) -> EvalTask:
        if self.choice is None:
            return self
        laid_out = {self.target_object, *self.extra_objects, *(self.distractors or ()), *(self.placements or {})}
        if self.target_object not in self.choice.candidates():
            raise ValueError(f"the target {self.target_object!r} is not one the choice can name "
                             f"({', '.join(self.choice.candidates())})")
        if isinstance(self.choice, SizeChoice) and not set(self.choice.among) <= laid_out:
            missing = sorted(set(self.choice.among) - laid_out)
            raise ValueError(f"a size choice compares objects the layout has: {missing} are not laid out")
        return self

    @property
    def accepted(self) -> tuple[str, ...]:
        return (self.target_object, *self.accept_objects)

    def scenario(self, seed: int) -> Scenario:
        target = None if self.expect == "not_found" else self.target_object
        return Scenario(seed=seed, target_object=target, destination=self.destination,
                        distractors=self.distractors, target_out_of_view=self.target_out_of_view,
                        extra_objects=self.extra_objects, placements=self.placements, criteria=self.criteria)


class EpisodeSpec(BaseModel):
    """One episode to run: a task with its seed under one backend and variant. `episode_id` is stable
    across runs (it names the configuration, the suite and the index), which is what makes runs resumable."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    episode_id: str
    task: EvalTask
    seed: int
    index: int
    backend: str
    variant: str


def load_jsonl(path: Path, default_suite: str | None = None) -> list[EvalTask]:
    """Tasks from a JSON Lines file; blank lines and lines starting with # are skipped."""
    tasks: list[EvalTask] = []
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise ConfigError(f"cannot read task file {path}: {exc}")
    for n, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            data = json.loads(line)
            if default_suite and "suite" not in data:
                data["suite"] = default_suite
            tasks.append(EvalTask.model_validate(data))
        except (json.JSONDecodeError, ValidationError) as exc:
            raise ConfigError(f"{path}:{n}: not a valid task ({exc}); expected one JSON object per line with "
                              f'"command", "suite", "target_object", "destination", "seed"')
    if not tasks:
        raise ConfigError(f"{path} holds no tasks")
    return tasks


def check_split(split: str) -> str:
    if split not in SPLITS:
        raise ConfigError(f"unknown split {split!r}; use one of {', '.join(SPLITS)}")
    return split


def load_suites(names: list[str] | None = None, split: str | None = DEFAULT_SPLIT) -> dict[str, list[EvalTask]]:
    """The built-in suites (aermani/evaluation/suites/<name>.jsonl), in paper order, with the tasks of one
    split (None: both splits, for checks of the suites themselves)."""
    if split is not None:
        check_split(split)
    available = {p.stem: p for p in SUITES_DIR.glob("*.jsonl")}
    wanted = list(names) if names else [s for s in PAPER_SUITES if s in available]
    unknown = [n for n in wanted if n not in available]
    if unknown:
        raise ConfigError(f"unknown suites {unknown}; available: {sorted(available)}")
    out = {}
    for name in wanted:
        tasks = [t for t in load_jsonl(available[name], default_suite=name) if split is None or t.split == split]
        if not tasks:
            raise ConfigError(f"suite {name} has no {split} tasks")
        out[name] = tasks
    return out


def derive_seed(base_seed: int, suite: str, index: int, split: str = DEFAULT_SPLIT) -> int:
    """A layout seed that depends only on (split, base seed, suite, index), stable across Python runs. The
    splits draw from disjoint ranges (dev: [0, 2^30), test: [2^30, 2^31)), so no layout is in both."""
    digest = hashlib.sha256(f"{split}/{base_seed}/{suite}/{index}".encode()).digest()
    return SPLITS.index(check_split(split)) * _SEED_RANGE + (int.from_bytes(digest[:4], "big") % _SEED_RANGE)


def config_label(backend: str, variant: str) -> str:
    return f"{backend}/{variant}"


def expand(tasks_by_suite: dict[str, list[EvalTask]], *, episodes: int | None, backends: list[str],
           variants: list[str], base_seed: int = 0, seeds_per_line: int | None = None) -> list[EpisodeSpec]:
    """Episodes for every (backend, variant) x suite: `episodes` per suite cycling through the suite's tasks
    (None: each task once), or with `seeds_per_line` every task on that many layouts. Seeds are the task's own
    or derived, and identical across variants, so every variant sees the same layouts."""
    specs: list[EpisodeSpec] = []
    for backend in backends:
        for variant in variants:
            for suite, tasks in tasks_by_suite.items():
                n = len(tasks) * seeds_per_line if seeds_per_line else len(tasks) if episodes is None else episodes
                for i in range(n):
                    task = tasks[i % len(tasks)]
                    seed = task.seed if task.seed is not None else derive_seed(base_seed, suite, i, task.split)
                    eid = f"{backend}/{variant}/{suite}/{i:03d}-s{seed}"
                    specs.append(EpisodeSpec(episode_id=eid, task=task, seed=seed, index=i, backend=backend,
                                             variant=variant))
    return specs


def group_by_suite(tasks: list[EvalTask]) -> dict[str, list[EvalTask]]:
    out: dict[str, list[EvalTask]] = {}
    for t in tasks:
        out.setdefault(t.suite, []).append(t)
    return out
