"""Readable timelines of the tasks in a log (`aermani log show`) and the HTML report (`aermani log export`)."""

from __future__ import annotations

import html
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from shared.keys import CAMERA_COLOR, REASONER_STEP, REASONER_TASK_STATUS
from shared.mcaplog import iter_samples, metadata, read_topic, topic_of, vehicle_of
from shared.messages import ReasoningStep, TaskStatus
from shared.sensors import PROTO_TYPES, stamp_to_ns
from shared.stats import percentile_or_none


@dataclass
class StepRow:
    """One reasoning step in a task timeline: the chosen skill, validity, retries, calls and outcome."""

    step: int
    stamp_ns: int
    skill: str | None
    argument: str | None
    valid: bool
    retries: int
    calls: int
    invalid_calls: int
    model_latency_s: float
    image_description: str | None
    summary: str | None
    reasoning: str | None
    skill_state: str | None
    skill_message: str
    skill_duration_s: float
    image_stamp_ns: int
    call_latencies_s: list[float] = field(default_factory=list)

    @property
    def call(self) -> str:
        if self.skill is None:
            return "(no valid answer)"
        return f"{self.skill}({self.argument})" if self.argument else self.skill


@dataclass
class TaskTimeline:
    """A task's readable timeline from a log: command, backend, variant, final state and its step rows."""

    task_id: str
    vehicle_id: str
    command: str
    backend: str
    variant: str
    state: str
    message: str
    started_ns: int
    ended_ns: int
    steps: list[StepRow] = field(default_factory=list)
    metrics: dict[str, Any] = field(default_factory=dict)


def step_row(s: ReasoningStep) -> StepRow:
    drt = s.drt
    return StepRow(
        step=s.step, stamp_ns=s.stamp_ns, skill=s.ste.skill if s.ste else None,
        argument=s.ste.argument if s.ste else None, valid=s.valid, retries=s.retries, calls=len(s.calls),
        invalid_calls=sum(1 for c in s.calls if not c.valid), model_latency_s=sum(c.latency_s for c in s.calls),
        image_description=drt.image_description if drt else None, summary=drt.summary if drt else None,
        reasoning=drt.reasoning if drt else None, skill_state=str(s.skill_state) if s.skill_state else None,
        skill_message=s.skill_message, skill_duration_s=s.skill_duration_s, image_stamp_ns=s.image_stamp_ns,
        call_latencies_s=[c.latency_s for c in s.calls],
    )


def timelines(path: str | Path, vehicle_id: str | None = None) -> list[TaskTimeline]:
    """One timeline per task in the log, in the order the tasks appear."""
    vid = vehicle_id or "*"
    steps: dict[str, dict[int, ReasoningStep]] = {}
    vehicles: dict[str, str] = {}
    for sample, s in read_topic(path, topic_of(vid, REASONER_STEP)):
        steps.setdefault(s.task_id, {})[s.step] = s  # a later version of a step replaces the earlier one
        vehicles.setdefault(s.task_id, vehicle_of(sample.key) or s.vehicle_id)
    statuses: dict[str, TaskStatus] = {}
    for sample, status in read_topic(path, topic_of(vid, REASONER_TASK_STATUS)):
        statuses[status.task_id] = status
        vehicles.setdefault(status.task_id, vehicle_of(sample.key) or status.vehicle_id)
    order = list(dict.fromkeys([*statuses, *steps]))
    out = []
    for task_id in order:
        st = statuses.get(task_id)
        rows = [step_row(s) for _, s in sorted(steps.get(task_id, {}).items())]
        first = next(iter(steps.get(task_id, {}).values()), None)
        command = st.command if st else (first.prompt.get("command", "") if first else "")
        tl = TaskTimeline(
            task_id=task_id, vehicle_id=vehicles.get(task_id, ""), command=command,
            backend=(st.backend if st else "") or (first.backend if first else ""),
            variant=st.variant if st else (first.variant if first else ""),
            state=str(st.state) if st else "unknown", message=st.message if st else "",
            started_ns=st.started_ns if st else 0, ended_ns=st.ended_ns if st else 0, steps=rows)
        tl.metrics = metrics(tl, st)
        out.append(tl)
    return out


def metrics(tl: TaskTimeline, st: TaskStatus | None) -> dict[str, Any]:
    latencies = [x for r in tl.steps for x in r.call_latencies_s]
    calls = sum(r.calls for r in tl.steps)
    invalid = sum(r.invalid_calls for r in tl.steps)
    if tl.started_ns and tl.ended_ns:
        task_time = (tl.ended_ns - tl.started_ns) / 1e9
    elif tl.steps:
        task_time = (tl.steps[-1].stamp_ns - tl.steps[0].stamp_ns) / 1e9 + tl.steps[-1].skill_duration_s
    else:
        task_time = None
    return {
        "steps": len(tl.steps),
        "model_calls": calls,
        "invalid_answers": invalid,
        "invalid_answer_rate": invalid / calls if calls else None,
        "model_latency_p50_s": percentile_or_none(latencies, 50),
        "model_latency_p95_s": percentile_or_none(latencies, 95),
        "skill_time_s": sum(r.skill_duration_s for r in tl.steps),
        "task_time_s": task_time,
        "state": tl.state,
    }


def report(path: str | Path, vehicle_id: str | None = None) -> dict[str, Any]:
    """Everything `log show --json` prints."""
    return {"log": str(path), "metadata": metadata(path),
            "tasks": [asdict(t) for t in timelines(path, vehicle_id)]}


def render_text(path: str | Path, vehicle_id: str | None = None) -> str:
    lines = [f"log {path}"]
    tls = timelines(path, vehicle_id)
    if not tls:
        lines.append("  no task in this log (no reasoner/step or reasoner/task_status samples)")
    for tl in tls:
        lines.append("")
        lines.append(f"task {tl.task_id} on {tl.vehicle_id}: \"{tl.command}\"  [{tl.backend}, {tl.variant}]")
        t0 = tl.started_ns or (tl.steps[0].stamp_ns if tl.steps else 0)
        for r in tl.steps:
            t = (r.stamp_ns - t0) / 1e9 if t0 else 0.0
            bad = f", {r.invalid_calls} invalid" if r.invalid_calls else ""
            lines.append(f"  {t:7.1f}s  step {r.step:>2}  {r.call:<40} -> {r.skill_state or '?':<9} "
                         f"skill {r.skill_duration_s:5.1f}s  model {r.model_latency_s:5.2f}s{bad}")
            why = r.reasoning or r.summary or r.image_description
            if why:
                lines.append(f"                   {_clip(why, 150)}")
            if r.skill_message and r.skill_state not in (None, "succeeded"):
                lines.append(f"                   executor: {_clip(r.skill_message, 150)}")
        m = tl.metrics
        lat = ("p50 {:.2f}s p95 {:.2f}s".format(m["model_latency_p50_s"], m["model_latency_p95_s"])
               if m["model_latency_p50_s"] is not None else "n/a")
        tt = f"{m['task_time_s']:.1f}s" if m["task_time_s"] is not None else "n/a"
        lines.append(f"  => {tl.state}{': ' + tl.message if tl.message else ''}; {m['steps']} steps, "
                     f"{m['model_calls']} model calls, {m['invalid_answers']} invalid, latency {lat}, task time {tt}")
    return "\n".join(lines)


def _clip(text: str, n: int) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= n else text[: n - 1] + "…"


# --------------------------------------------------------------------------- HTML export


def color_frames(path: str | Path, vehicle_id: str) -> list[tuple[int, bytes, str]]:
    """(stamp_ns, image bytes, format) of every colour frame of a vehicle."""
    out = []
    cls = PROTO_TYPES["foxglove.CompressedImage"]
    for s in iter_samples(path, CAMERA_COLOR.bind(vehicle_id).key):
        msg = cls()
        try:
            msg.ParseFromString(s.payload)
        except Exception:
            continue
        out.append((stamp_to_ns(msg.timestamp) or s.publish_time_ns, bytes(msg.data), msg.format or "jpeg"))
    return out


def closest(frames: list[tuple[int, bytes, str]], stamp_ns: int) -> tuple[int, bytes, str] | None:
    if not frames:
        return None
    return min(frames, key=lambda f: abs(f[0] - stamp_ns))


def export_html(path: str | Path, out_dir: str | Path, vehicle_id: str | None = None) -> Path:
    """Write out_dir/index.html with each step's camera frame (the colour frame closest to the step's
    image_stamp_ns, or to its stamp) beside its DRT; frames go to out_dir/frames/."""
    out = Path(out_dir)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    tls = timelines(path, vehicle_id)
    frame_cache: dict[str, list[tuple[int, bytes, str]]] = {}
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>aermani log report</title><style>"
        "body{font-family:sans-serif;margin:2em;max-width:1200px}"
        ".step{display:flex;gap:1.5em;border-top:1px solid #ccc;padding:1em 0}"
        ".step img{width:400px;flex:none}.none{width:400px;flex:none;color:#888}"
        "dt{font-weight:bold;margin-top:.4em}.bad{color:#b00}table{border-collapse:collapse}"
        "td,th{padding:.2em .8em;border:1px solid #ddd;text-align:left}</style></head><body>",
        f"<h1>aermani log report</h1><p>{html.escape(str(path))}</p>",
    ]
    for tl in tls:
        if tl.vehicle_id not in frame_cache:
            frame_cache[tl.vehicle_id] = color_frames(path, tl.vehicle_id or "*")
        frames = frame_cache[tl.vehicle_id]
        parts.append(f"<h2>{html.escape(tl.command)}</h2><p>task {html.escape(tl.task_id)} on "
                     f"{html.escape(tl.vehicle_id)}, backend {html.escape(tl.backend)}, variant "
                     f"{html.escape(tl.variant)}: <b>{html.escape(tl.state)}</b> {html.escape(tl.message)}</p>")
        parts.append("<table>" + "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(_fmt(v))}</td></tr>"
                                          for k, v in tl.metrics.items()) + "</table>")
        for r in tl.steps:
            frame = closest(frames, r.image_stamp_ns or r.stamp_ns)
            if frame is not None:
                ext = "png" if frame[2] == "png" else "jpg"
                name = f"frames/{_safe(tl.task_id)}-step{r.step:03d}.{ext}"
                (out / name).write_bytes(frame[1])
                dt_ms = (frame[0] - r.image_stamp_ns) / 1e6 if r.image_stamp_ns else None
                note = f" (frame {dt_ms:+.0f} ms from the prompt's)" if dt_ms is not None else ""
                img = f"<figure><img src='{name}' alt='step {r.step}'><figcaption>{note}</figcaption></figure>"
            else:
                img = "<div class='none'>no camera frame recorded</div>"
            drt = "".join(f"<dt>{label}</dt><dd>{html.escape(val)}</dd>" for label, val in (
                ("image description", r.image_description), ("summary", r.summary),
                ("reasoning", r.reasoning)) if val)
            cls = "" if r.skill_state in (None, "succeeded") else " class='bad'"
            parts.append(
                f"<div class='step'>{img}<div><h3>step {r.step}: {html.escape(r.call)}</h3>"
                f"<p{cls}>{html.escape(r.skill_state or '?')} in {r.skill_duration_s:.1f} s; "
                f"{html.escape(r.skill_message)}</p><p>model {r.model_latency_s:.2f} s, {r.calls} call(s), "
                f"{r.invalid_calls} invalid</p><dl>{drt}</dl></div></div>")
    if not tls:
        parts.append("<p>No task in this log.</p>")
    parts.append("</body></html>")
    index = out / "index.html"
    index.write_text("\n".join(parts), encoding="utf-8")
    return index


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.3f}"
    return "n/a" if v is None else str(v)


def _safe(text: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in text)


def to_json(path: str | Path, vehicle_id: str | None = None) -> str:
    return json.dumps(report(path, vehicle_id), indent=2, default=str)
