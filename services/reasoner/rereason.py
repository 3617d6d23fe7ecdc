"""Offline re-reasoning: re-run the reasoner's decision step on a log's recorded observations with another
backend or prompt variant, and compare with the recorded decisions. Nothing is published; no vehicle moves.

For step k of a recorded task the observation is rebuilt from the log: the colour frame whose stamp is the
step's `image_stamp_ns`, and the newest vehicle state, detections and working memory the reasoner had
received when it observed (log time = the recorder's receive time, on the same clock). The History is the
recorded one (steps 1..k-1 with their recorded skills and outcomes), so each step is a counterfactual:
"what would this policy have chosen here". The prompt is compiled, the backend queried and the answer
parsed and re-prompted exactly as the reasoner's loop does, with its own modules (prompt, parse, backends).
When the recorded prompt is there, the rebuilt History part is checked against it, and the observation
search widens until they match, so "same observation" is verified rather than assumed.
"""

from __future__ import annotations

import bisect
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from shared.errors import AermaniError
from shared.keys import (
    AUTOPILOT_STATE,
    CAMERA_COLOR,
    EXECUTOR_MEMORY,
    PERCEPTION_DETECTIONS,
    REASONER_STEP,
    REASONER_TASK_STATUS,
)
from shared.mcaplog import iter_samples, vehicle_of
from shared.messages import (
    Detections,
    ModelCall,
    ReasoningStep,
    ResumeStep,
    SkillLibrary,
    TaskStatus,
    VehicleState,
    WorkingMemory,
)
from shared.sensors import PROTO_TYPES, stamp_to_ns
from shared.stats import percentile_or_none as percentile

SEARCH_BEFORE_NS = 3_000_000_000  # how far before the decision to look for the observed samples
SEARCH_AFTER_NS = 500_000_000  # receive-time jitter between the reasoner and the recorder
MAX_COMBINATIONS = 20_000


class RereasonError(AermaniError):
    """The log cannot be re-reasoned (no steps, reasoner modules missing, bad backend)."""


@dataclass
class StepComparison:
    """One re-reasoned step next to the recorded one: both decisions and whether they agree."""

    task_id: str
    step: int
    recorded_skill: str | None
    recorded_argument: str | None
    skill: str | None
    argument: str | None
    agree: bool
    """Same skill and same argument (case and spacing aside)."""
    skill_agree: bool
    """Same skill name."""
    valid: bool
    calls: int
    invalid_calls: int
    latency_s: float
    observation_exact: bool | None
    """The rebuilt History part equals the recorded one (None when the log has no prompt to compare)."""
    error: str = ""
    raw_answers: list[str] = field(default_factory=list)

    def call(self, recorded: bool) -> str:
        skill, arg = (self.recorded_skill, self.recorded_argument) if recorded else (self.skill, self.argument)
        if skill is None:
            return "(invalid)"
        return f"{skill}({arg})" if arg else skill


def _pct(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:.0f}%"


def _sec(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.2f}s"


@dataclass
class RereasonResult:
    """Result of re-reasoning a log with a backend and variant: every step comparison and the agreement rate."""

    log: str
    backend: str
    variant: str
    steps: list[StepComparison]

    @property
    def agreement_rate(self) -> float | None:
        return sum(s.agree for s in self.steps) / len(self.steps) if self.steps else None

    @property
    def skill_agreement_rate(self) -> float | None:
        return sum(s.skill_agree for s in self.steps) / len(self.steps) if self.steps else None

    @property
    def invalid_rate(self) -> float | None:
        calls = sum(s.calls for s in self.steps)
        return sum(s.invalid_calls for s in self.steps) / calls if calls else None

    @property
    def differing(self) -> list[tuple[str, int]]:
        return [(s.task_id, s.step) for s in self.steps if not s.agree]

    def latency(self, q: float) -> float | None:
        return percentile([s.latency_s / max(1, s.calls) for s in self.steps], q)

    def summary(self) -> dict[str, Any]:
        exact = [s.observation_exact for s in self.steps if s.observation_exact is not None]
        return {
            "steps": len(self.steps), "agreement_rate": self.agreement_rate,
            "skill_agreement_rate": self.skill_agreement_rate, "invalid_rate": self.invalid_rate,
            "failed_steps": sum(not s.valid for s in self.steps),
            "latency_p50_s": self.latency(50), "latency_p95_s": self.latency(95),
            "differing_steps": [f"{t}#{n}" for t, n in self.differing],
            "observations_verified": f"{sum(exact)}/{len(exact)}" if exact else "n/a",
        }

    def as_dict(self) -> dict[str, Any]:
        return {"log": self.log, "backend": self.backend, "variant": self.variant, "summary": self.summary(),
                "steps": [asdict(s) for s in self.steps]}

    def render(self) -> str:
        m = self.summary()
        lines = [f"rereason {self.log} with {self.backend} ({self.variant}): {m['steps']} steps",
                 f"  agreement {_pct(m['agreement_rate'])} (skill only {_pct(m['skill_agreement_rate'])}), "
                 f"invalid answers {_pct(m['invalid_rate'])}, latency p50 {_sec(m['latency_p50_s'])} "
                 f"p95 {_sec(m['latency_p95_s'])}, observations verified {m['observations_verified']}"]
        for s in self.steps:
            if not s.agree:
                why = f"  [{s.error}]" if s.error else ""
                lines.append(f"  differs: {s.task_id} step {s.step}: recorded {s.call(True)}, "
                             f"now {s.call(False)}{why}")
        if not self.differing and self.steps:
            lines.append("  every decision agrees")
        return "\n".join(lines)


# --------------------------------------------------------------------------- what the log says


class _Stream:
    """Values of one stream ordered by log (receive) time."""

    def __init__(self) -> None:
        self.times: list[int] = []
        self.values: list[Any] = []

    def add(self, t: int, v: Any) -> None:
        self.times.append(t)
        self.values.append(v)

    def finish(self) -> None:
        order = sorted(range(len(self.times)), key=self.times.__getitem__)
        self.times = [self.times[i] for i in order]
        self.values = [self.values[i] for i in order]

    def at(self, t: int) -> Any:
        i = bisect.bisect_right(self.times, t)
        return self.values[i - 1] if i else None

    def window(self, t0: int, t1: int) -> list[Any]:
        """The value current at t0 and every later one up to t1, newest first (None included if any)."""
        i0 = bisect.bisect_right(self.times, t0)
        i1 = bisect.bisect_right(self.times, t1)
        vals = [self.values[i0 - 1] if i0 else None, *self.values[i0:i1]]
        return list(reversed(vals))


@dataclass
class RecordedTask:
    """A task as found in a log: its id, vehicle, command, prompt variant and recorded reasoning steps."""

    task_id: str
    vehicle_id: str
    command: str
    variant: str
    steps: list[ReasoningStep]


class LogIndex:
    """One pass over a log: the reasoner's inputs and outputs per vehicle."""

    def __init__(self, path: str | Path) -> None:
        self.path = str(path)
        self.state: dict[str, _Stream] = {}
        self.detections: dict[str, _Stream] = {}
        self.memory: dict[str, _Stream] = {}
        self.frames: dict[str, dict[int, bytes]] = {}
        self.library: SkillLibrary | None = None
        steps: dict[str, dict[int, ReasoningStep]] = {}
        vehicles: dict[str, str] = {}
        statuses: dict[str, TaskStatus] = {}
        img_cls = PROTO_TYPES["foxglove.CompressedImage"]
        for s in iter_samples(path):
            vid = vehicle_of(s.key) or ""
            topic = s.key.split("/", 3)[3] if s.key.count("/") >= 3 else s.key
            try:
                if topic == AUTOPILOT_STATE.name:
                    state = VehicleState.model_validate_json(s.payload)
                    self.state.setdefault(vid, _Stream()).add(s.log_time_ns, state)
                elif topic == PERCEPTION_DETECTIONS.name:
                    self.detections.setdefault(vid, _Stream()).add(s.log_time_ns,
                                                                   Detections.model_validate_json(s.payload))
                elif topic == EXECUTOR_MEMORY.name:
                    self.memory.setdefault(vid, _Stream()).add(s.log_time_ns,
                                                               WorkingMemory.model_validate_json(s.payload))
                elif topic == CAMERA_COLOR.name:
                    msg = img_cls()
                    msg.ParseFromString(s.payload)
                    self.frames.setdefault(vid, {})[stamp_to_ns(msg.timestamp)] = bytes(msg.data)
                elif topic == REASONER_STEP.name:
                    st = ReasoningStep.model_validate_json(s.payload)
                    steps.setdefault(st.task_id, {})[st.step] = st
                    vehicles.setdefault(st.task_id, vid)
                elif topic == REASONER_TASK_STATUS.name:
                    ts = TaskStatus.model_validate_json(s.payload)
                    statuses[ts.task_id] = ts
                    vehicles.setdefault(ts.task_id, vid)
                elif s.schema_name == "aermani.SkillLibrary" or s.encoding.endswith(";aermani.SkillLibrary"):
                    self.library = SkillLibrary.model_validate_json(s.payload)
            except Exception:  # a malformed sample is not an observation the reasoner could have used
                continue
        for group in (self.state, self.detections, self.memory):
            for stream in group.values():
                stream.finish()
        self.tasks: list[RecordedTask] = []
        for task_id, by_step in steps.items():
            ordered = [by_step[k] for k in sorted(by_step)]
            status = statuses.get(task_id)
            command = status.command if status else ordered[0].prompt.get("command", "")
            self.tasks.append(RecordedTask(task_id, vehicles.get(task_id, ""), command,
                                           (status.variant if status else "") or ordered[0].variant, ordered))

    def frame(self, vid: str, stamp_ns: int) -> bytes | None:
        frames = self.frames.get(vid, {})
        if stamp_ns in frames:
            return frames[stamp_ns]
        if not frames or not stamp_ns:
            return None
        return frames[min(frames, key=lambda t: abs(t - stamp_ns))]


# --------------------------------------------------------------------------- the decision step


def _reasoner():
    """The reasoner's loop modules, imported on first use (the backends load their SDKs)."""
    try:
        from services.reasoner import backends, library, loop, parse, prompt
        from services.reasoner.settings import ReasonerSettings
    except ImportError as exc:  # pragma: no cover - only without the reasoner package
        raise RereasonError(f"rereason needs the reasoner's prompt/parse/backends modules: {exc}") from exc
    return backends, library, loop, parse, prompt, ReasonerSettings


def _norm(arg: str | None) -> str:
    return " ".join((arg or "").lower().split())


def resume_steps(steps: list[ReasoningStep]) -> list[ResumeStep]:
    """The History's entries of recorded steps, as the loop appended them (a flight fork's `Resume.history`)."""
    out: list[ResumeStep] = []
    for rec in steps:
        if rec.ste is None:
            if not rec.calls and not rec.prompt:
                continue  # a model outage record: the loop ended the task there
            err = rec.calls[-1].error if rec.calls else "no answer"
            out.append(ResumeStep(step=rec.step, skill="(invalid answer)", state="failed",
                                  message=f"no valid skill after {rec.retries} re-prompts: {err}; held"))
            continue
        drt = rec.drt
        out.append(ResumeStep(
            step=rec.step, skill=rec.ste.skill, argument=rec.ste.argument,
            state=rec.skill_state.value if rec.skill_state is not None else "failed", message=rec.skill_message,
            perceived=rec.outcome.perceived if rec.outcome else "", summary=(drt.summary if drt else None) or "",
            reasoning=(drt.reasoning if drt else None) or "", outcome=rec.outcome,
            image_description=(drt.image_description if drt else None) or "",
            prediction=((drt.action_predictions or {}).get(rec.ste.skill, "") if drt else "")))
    return out


def _history_before(loop_mod, prompt_mod, steps: list[ReasoningStep], k: int, settings) -> Any:
    """The reasoner's History after the recorded steps before index k, built as its loop builds it."""
    history = prompt_mod.History(settings.history_full_steps, settings.history_max_chars)
    for r in resume_steps(steps[:k]):
        history.append(loop_mod.history_entry(r))
    return history


def _observation(index: LogIndex, prompt_mod, vid: str, rec: ReasoningStep, history,
                 want_history: str | None) -> tuple[Any, bool | None]:
    """The observation the reasoner had at this step, verified against the recorded History part."""
    model_s = sum(c.latency_s for c in rec.calls)
    t_obs = rec.stamp_ns - int(model_s * 1e9)
    image = index.frame(vid, rec.image_stamp_ns) if rec.image_stamp_ns else None
    streams = (index.state.get(vid, _Stream()), index.detections.get(vid, _Stream()), index.memory.get(vid, _Stream()))

    def build(state, det, mem):
        return prompt_mod.Observation(image_jpeg=image, image_stamp_ns=rec.image_stamp_ns, state=state,
                                      detections=det.items if det else (), memory=mem)

    first = build(*(s.at(t_obs) for s in streams))
    if want_history is None:
        return first, None
    if history.render(first) == want_history:
        return first, True
    # The receive times of reasoner and recorder differ by a little: search nearby samples for the ones
    # that reproduce the History text the model actually saw.
    lo, hi = t_obs - SEARCH_BEFORE_NS, rec.stamp_ns + SEARCH_AFTER_NS
    states, dets, mems = (s.window(lo, hi) for s in streams)
    rendered: set[str] = set()
    n = 0
    for det in dets:
        for mem in mems:
            for state in states:
                n += 1
                if n > MAX_COMBINATIONS:
                    return first, False
                obs = build(state, det, mem)
                text = history.render(obs)
                if text == want_history:
                    return obs, True
                rendered.add(text)
    return first, False


def observed_steps(index: LogIndex, task: RecordedTask,
                   settings: Any = None) -> list[tuple[ReasoningStep, Any, bool | None]]:
    """(step, the Observation its decision saw, whether that observation reproduces the recorded History text)
    for every recorded step of `task`: the observation rebuilt as `rereason_log` rebuilds it (None for a model
    outage record, which observed nothing). For tools that set a step's words beside what was measured."""
    mods = _reasoner()
    loop_mod, prompt_mod, reasoner_settings = mods[2], mods[4], mods[5]
    settings = settings or reasoner_settings()
    out: list[tuple[ReasoningStep, Any, bool | None]] = []
    for k, rec in enumerate(task.steps):
        if not rec.prompt and not rec.calls:
            out.append((rec, None, None))
            continue
        history = _history_before(loop_mod, prompt_mod, task.steps, k, settings)
        obs, exact = _observation(index, prompt_mod, task.vehicle_id, rec, history, rec.prompt.get("history"))
        out.append((rec, obs, exact))
    return out


async def _decide(mods, backend, settings, variant: str, library, command: str, history, obs):
    """One decision with the reasoner's own prompt compiler, parser and re-prompt budget."""
    _backends, _library, loop, parse, prompt_mod, _ = mods
    from services.reasoner.backends.base import ModelRequest
    compiled = prompt_mod.PromptCompiler(variant, library).compile(command, history, obs)
    ctx = loop.policy_context(command, variant, library, history, obs)
    feedback: list[tuple[str, str]] = []
    calls: list[ModelCall] = []
    parsed = None
    for _attempt in range(settings.max_reprompts + 1):
        t0 = time.perf_counter()
        try:
            reply = await backend.complete(ModelRequest(compiled, ctx, list(feedback)))
        except AermaniError as exc:
            calls.append(ModelCall(raw_answer="", valid=False, error=f"model error: {exc}",
                                   latency_s=time.perf_counter() - t0))
            break
        try:
            parsed = parse.parse_answer(reply.text, variant, library, coverage=settings.prediction_coverage)
            calls.append(ModelCall(raw_answer=parse.recorded_answer(reply.text), valid=True, latency_s=reply.latency_s))
            break
        except AermaniError as exc:  # InvalidAnswer
            calls.append(ModelCall(raw_answer=parse.recorded_answer(reply.text), valid=False, error=str(exc),
                                   latency_s=reply.latency_s))
            feedback.append((reply.text, str(exc)))
    return parsed, calls


def make_offline_backend(name: str, model: str | None = None, answers: str | Path | None = None):
    """A backend for offline use: rules, openai, anthropic (keys from the environment), or replay of the
    answers recorded in an MCAP log."""
    backends, _library, _loop, _parse, _prompt, reasoner_settings = _reasoner()
    if name == "replay":
        from services.reasoner.backends.replay import ReplayBackend
        from shared.mcaplog import McapReplaySource

        if answers is None:
            raise RereasonError("backend replay needs --answers LOG.mcap (the log whose answers to replay)")
        return ReplayBackend(McapReplaySource(answers))
    try:
        settings = reasoner_settings(backend=name, model=model or "")
        return backends.make_backend(settings, name)
    except Exception as exc:
        raise RereasonError(f"cannot make backend {name!r}: {exc}") from exc


async def rereason_log(path: str | Path, *, backend: str = "rules", variant: str | None = None,
                       model: str | None = None, task_id: str | None = None, answers: str | Path | None = None,
                       backend_obj: Any = None, settings: Any = None) -> RereasonResult:
    """Re-run every recorded decision of `path` (or of one task) with another backend and/or variant.
    `backend_obj` (any reasoner Backend) overrides `backend`, e.g. a scripted policy in tests."""
    mods = _reasoner()
    _backends, library_mod, loop_mod, _parse, prompt_mod, reasoner_settings = mods
    if variant is not None and variant not in prompt_mod.PROMPT_PARTS:
        raise RereasonError(f"unknown variant {variant!r}; use one of {', '.join(prompt_mod.PROMPT_PARTS)}")
    index = LogIndex(path)
    tasks = [t for t in index.tasks if task_id is None or t.task_id == task_id]
    if not tasks:
        raise RereasonError(f"{path} has no recorded reasoning steps" + (f" for task {task_id}" if task_id else ""))
    settings = settings or reasoner_settings()
    library = index.library or library_mod.default_library()
    policy = backend_obj or make_offline_backend(backend, model, answers)
    name = getattr(policy, "name", "") or backend
    out: list[StepComparison] = []
    used_variant = variant or tasks[0].variant
    try:
        for task in tasks:
            var = variant or task.variant or "full"
            for k, rec in enumerate(task.steps):
                if not rec.prompt and not rec.calls:
                    continue  # a model outage record: no decision was taken
                history = _history_before(loop_mod, prompt_mod, task.steps, k, settings)
                # The History part does not depend on the variant, so the recorded one is the reference.
                want = rec.prompt.get("history")
                obs, exact = _observation(index, prompt_mod, task.vehicle_id, rec, history, want)
                parsed, calls = await _decide(mods, policy, settings, var, library, task.command, history, obs)
                skill = parsed.ste.skill if parsed else None
                arg = parsed.ste.argument if parsed else None
                rs = rec.ste.skill if rec.ste else None
                ra = rec.ste.argument if rec.ste else None
                out.append(StepComparison(
                    task_id=task.task_id, step=rec.step, recorded_skill=rs, recorded_argument=ra, skill=skill,
                    argument=arg, agree=skill == rs and _norm(arg) == _norm(ra), skill_agree=skill == rs,
                    valid=parsed is not None, calls=len(calls), invalid_calls=sum(not c.valid for c in calls),
                    latency_s=sum(c.latency_s for c in calls), observation_exact=exact,
                    error="" if parsed is not None else (calls[-1].error if calls else "no answer"),
                    raw_answers=[c.raw_answer for c in calls]))
    finally:
        if backend_obj is None:
            close = getattr(policy, "aclose", None)
            if close is not None:
                await close()
    return RereasonResult(str(path), name, used_variant, out)
