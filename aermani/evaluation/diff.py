"""`aermani diff A B`: two recorded runs side by side, step by step, and where they diverge.

Each step shows what was measured when it observed (detections, held object, vehicle position), its DRT, the
skill and argument chosen and the skill's outcome code, and the grounding check's flags (grounding.py). Two
steps differ when their skill or argument (case and spacing aside) or their outcome code differ, or when one
run has the step and the other has not; the first such step is the divergence.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from rich.console import Group
from rich.table import Table
from rich.text import Text

from aermani.evaluation.runs import Run, RunError, RunStep, RunTask, load_run
from shared.text import plain_text


def _norm(arg: str | None) -> str:
    return " ".join((arg or "").lower().split())


def _outcome(rs: RunStep) -> str | None:
    s = rs.step
    if s.outcome is not None and s.outcome.code is not None:
        return str(s.outcome.code)
    return str(s.skill_state) if s.skill_state is not None else None


def step_view(rs: RunStep | None) -> dict[str, Any] | None:
    """One side of a compared step, as --json prints it."""
    if rs is None:
        return None
    s, obs = rs.step, rs.observation
    drt = s.drt
    p = obs.position if obs is not None else None
    return {
        "observation": None if obs is None else {
            "detections": None if obs.detections is None else [d.label for d in obs.detections],
            "held_object": obs.held_object if obs.memory_known else None,
            "gripper_holding": obs.gripper_holding,
            "position": None if p is None else [round(p.x, 2), round(p.y, 2), round(p.z, 2)],
            "source": obs.source, "verified": rs.verified},
        "drt": None if drt is None else drt.model_dump(mode="json", exclude_none=True),
        "skill": s.ste.skill if s.ste else None,
        "argument": s.ste.argument if s.ste else None,
        "skill_state": str(s.skill_state) if s.skill_state is not None else None,
        "outcome": _outcome(rs),
        "grounding": rs.grounding.as_dict() if rs.grounding is not None else None,
    }


@dataclass
class StepPair:
    """Step k of both runs and whether they differ."""

    step: int
    a: RunStep | None
    b: RunStep | None
    differs: bool
    why: str
    divergence: bool = False


@dataclass
class TaskDiff:
    """Two tasks compared step by step."""

    a: RunTask
    b: RunTask
    steps: list[StepPair] = field(default_factory=list)

    @property
    def first_divergence(self) -> int | None:
        return next((p.step for p in self.steps if p.differs), None)


def _why(a: RunStep | None, b: RunStep | None) -> str:
    if a is None or b is None:
        return "only in " + ("B" if a is None else "A")
    sa, sb = a.step.ste, b.step.ste
    ca = (sa.skill, _norm(sa.argument)) if sa else None
    cb = (sb.skill, _norm(sb.argument)) if sb else None
    if ca != cb:
        return "skill" if (ca or ("",))[0] != (cb or ("",))[0] else "argument"
    if _outcome(a) != _outcome(b):
        return "outcome"
    return ""


def compare_tasks(a: RunTask, b: RunTask) -> TaskDiff:
    by_a = {rs.step.step: rs for rs in a.steps}
    by_b = {rs.step.step: rs for rs in b.steps}
    out = TaskDiff(a, b)
    for k in sorted(set(by_a) | set(by_b)):
        why = _why(by_a.get(k), by_b.get(k))
        out.steps.append(StepPair(k, by_a.get(k), by_b.get(k), bool(why), why))
    first = out.first_divergence
    for p in out.steps:
        p.divergence = p.step == first
    return out


def _episode_key(task: RunTask) -> str:
    """An evaluation episode's id without its backend and variant: the same task and seed in another run."""
    return task.key.split("/", 2)[2] if task.key.count("/") >= 2 else task.key


def _pick(run: Run, name: str | None) -> list[RunTask]:
    if name is None:
        return run.tasks
    chosen = [t for t in run.tasks if name in (t.key, t.task_id)]
    if not chosen:
        known = ", ".join(t.key for t in run.tasks[:10])
        raise RunError(f"{run.path} has no task {name!r}; its tasks: {known}")
    return chosen


def pair_tasks(a: Run, b: Run, task_a: str | None = None, task_b: str | None = None) -> list[tuple[RunTask, RunTask]]:
    """Which task of A is compared with which of B: the named ones; episodes of two evaluations by suite, index
    and seed; otherwise in order."""
    ta, tb = _pick(a, task_a), _pick(b, task_b)
    if a.kind == b.kind == "evaluation" and task_a is None and task_b is None:
        keyed = {_episode_key(t): t for t in tb}
        pairs = [(t, keyed[_episode_key(t)]) for t in ta if _episode_key(t) in keyed]
        if pairs:
            return pairs
    return list(zip(ta, tb, strict=False))


@dataclass
class RunDiff:
    """Two runs compared: each task pair's step comparison."""

    a: Run
    b: Run
    tasks: list[TaskDiff]

    def as_dict(self) -> dict[str, Any]:
        return {"a": {"path": self.a.path, "kind": self.a.kind}, "b": {"path": self.b.path, "kind": self.b.kind},
                "tasks": [{
                    "a": _task_head(t.a), "b": _task_head(t.b), "first_divergence": t.first_divergence,
                    "steps": [{"step": p.step, "differs": p.differs, "why": p.why, "divergence": p.divergence,
                               "a": step_view(p.a), "b": step_view(p.b)} for p in t.steps]}
                    for t in self.tasks]}


def _task_head(t: RunTask) -> dict[str, Any]:
    checked = [s.grounding for s in t.steps if s.grounding is not None and s.grounding.checked]
    return {"key": t.key, "task_id": t.task_id, "command": t.command, "backend": t.backend, "variant": t.variant,
            "state": t.state, "steps": len(t.steps), "grounding_checked_steps": len(checked),
            "grounding_flagged_steps": [g.step for g in checked if g.violated]}


def diff_runs(path_a: str, path_b: str, task_a: str | None = None, task_b: str | None = None) -> RunDiff:
    """Load both runs and compare them (raises RunError on a missing or unreadable run)."""
    a, b = load_run(path_a), load_run(path_b)
    pairs = pair_tasks(a, b, task_a, task_b)
    if not pairs:
        raise RunError(f"no task of {path_a} pairs with one of {path_b}; name them with --task-a/--task-b")
    return RunDiff(a, b, [compare_tasks(x, y) for x, y in pairs])


# --------------------------------------------------------------------------- terminal rendering


def _clip(text: object, n: int = 160) -> str:
    """Model or log text for the terminal: control and invisible characters removed, one line, clipped."""
    text = " ".join(plain_text(text).split())
    return text if len(text) <= n else text[: n - 1] + "…"


def _cell(rs: RunStep | None) -> Text:
    """One side of a step as terminal text. Everything from the log is data: Text, never markup."""
    if rs is None:
        return Text("(no such step)", style="dim")
    v = step_view(rs)
    assert v is not None
    out = Text()
    obs = v["observation"]
    if obs is not None:
        dets = obs["detections"]
        held = obs["held_object"] or ("nothing" if obs["gripper_holding"] is not True else "something")
        pos = obs["position"]
        out.append(_clip("sees " + (", ".join(dets) or "nothing" if dets is not None else "?"), 200), style="cyan")
        where = f" | at ({pos[0]:.2f}, {pos[1]:.2f}, {pos[2]:.2f})" if pos else ""
        out.append(f" | holds {_clip(held, 60)}{where}\n", style="cyan")
    drt = v["drt"] or {}
    for key, label in (("image_description", "image"), ("summary", "summary"), ("reasoning", "reasoning")):
        if drt.get(key):
            out.append(f"{label}: ", style="dim")
            out.append(_clip(drt[key]) + "\n")
    call = "(no valid answer)" if v["skill"] is None else (
        f"{v['skill']}({v['argument']})" if v["argument"] else v["skill"])
    out.append("-> ")
    out.append(_clip(call, 100), style="bold")
    out.append(f"  [{v['outcome'] or '?'}]", style="green" if v["outcome"] == "succeeded" else "yellow")
    g = rs.grounding
    for viol in g.violations if g is not None else []:
        out.append(f"\n! grounding ({viol.field}): ", style="bold red")
        out.append(_clip(viol.reason, 200), style="red")
    return out


def render(diff: RunDiff) -> Group:
    """Rich tables, one per task pair."""
    parts: list[Any] = []
    for t in diff.tasks:
        first = t.first_divergence
        head = Text()
        head.append("A ", style="bold")
        for name, run, task in (("A", diff.a, t.a), ("B", diff.b, t.b)):
            if name == "B":
                head.append("B ", style="bold")
            head.append(_clip(f"{run.path} task {task.key} [{task.backend}, {task.variant}] -> {task.state}", 300)
                        + "\n")
        head.append(_clip(f"command: {t.a.command}" + ("" if t.a.command == t.b.command else
                                                        f"  |  B: {t.b.command}"), 300))
        table = Table("step", "A", "B", "", show_lines=True, expand=True)
        for p in t.steps:
            mark = Text("")
            if p.divergence:
                mark = Text(f"DIVERGES ({p.why})", style="bold magenta")
            elif p.differs:
                mark = Text(f"differs ({p.why})", style="magenta")
            table.add_row(Text(str(p.step)), _cell(p.a), _cell(p.b), mark)
        flagged_a = [s.step.step for s in t.a.steps if s.grounding and s.grounding.violated]
        flagged_b = [s.step.step for s in t.b.steps if s.grounding and s.grounding.violated]
        foot = Text(("runs agree on every step" if first is None else f"first divergence at step {first}") +
                    f"; grounding flags: A steps {flagged_a or 'none'}, B steps {flagged_b or 'none'}")
        parts += [head, table, foot, Text("")]
    return Group(*parts)
