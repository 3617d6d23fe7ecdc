"""The evaluation report: report.json (every episode), report.md (the paper's Tables II and V), PNG plots."""

from __future__ import annotations

import json
import time
from collections.abc import Iterable
from ipaddress import ip_address
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from aermani.evaluation.grounding import violation_rate
from aermani.evaluation.metrics import Metrics, compute, iar_by_mode, judged_ok, reasoning_steps
from aermani.evaluation.records import RESULTS_FILE, EpisodeRecord, ResultsFile
from aermani.evaluation.runs import episode_grounding
from aermani.evaluation.tasks import PAPER_RS, PAPER_SUITES, SUITE_TITLES
from shared.messages import VARIANTS
from shared.search import NOT_FOUND_MAX_STEPS, SEARCH_STEPS
from shared.text import plain_text

VARIANT_TITLES = {
    "unstructured": "Unstructured", "no_drt": "No-DRT", "drt_v1": "DRT-V1", "drt_v2": "DRT-V2",
    "drt_v3": "DRT-V3", "full": "AERMANI-VLM", "react": "ReAct Prompting",
    "saycan": "SayCan-style", "direct": "RT-2-style direct action", "waypoint": "UAV-VLN-style waypoints",
    "plan_once": "UAV-VLA-style plan once",
}


def _fmt(v: float | None, digits: int = 1) -> str:
    return "--" if v is None else f"{v:.{digits}f}"


NO_MODEL_BACKENDS = ("rules", "replay")
"""Policies that call no model: their "RT" would be a Python call or a file read, not a model's response time."""


def _rt(m: Metrics, backend: str, digits: int = 3, p95: bool = False) -> str:
    """RT median (or p95), or n/a for a policy that calls no model."""
    if backend.split(":", 1)[0] in NO_MODEL_BACKENDS:
        return "n/a (no model)"
    return _fmt(m.rt_p95 if p95 else m.rt_median, digits)


def _sr(m: Metrics) -> str:
    """SR with its 95 % Wilson score interval: `65.0 [43.3, 81.9]`."""
    if m.sr is None:
        return "--"
    if m.sr_low is None or m.sr_high is None:
        return _sr(m)
    return f"{m.sr:.1f} [{m.sr_low:.1f}, {m.sr_high:.1f}]"


MAX_GROUNDING_LINES = 20


def grounding_doc(r: EpisodeRecord) -> dict[str, Any]:
    """One episode's grounding check for report.json: the rate, and each flagged step with its reasons."""
    checks = [g for g in episode_grounding(r) if g.checked]
    return {"checked_steps": len(checks), "gvr": violation_rate(checks),
            "flagged": [g.as_dict() for g in checks if g.violated]}


def grounding_lines(records: list[EpisodeRecord]) -> list[str]:
    """The flagged steps of the report (the first MAX_GROUNDING_LINES), each with its first reason."""
    flagged = [(r, g) for r in records if not r.harness_error for g in episode_grounding(r) if g.violated]
    if not flagged:
        return []
    lines = ["## Grounding flags", "", f"{len(flagged)} step(s) whose DRT contradicts what the stack measured "
             "(docs/evaluation.md, Grounding); every one is in report.json.", "",
             "| Episode | Step | Statement | Why |", "|---|---|---|---|"]
    for r, g in flagged[:MAX_GROUNDING_LINES]:
        v = g.violations[0]
        more = f" (+{len(g.violations) - 1} more)" if len(g.violations) > 1 else ""
        lines.append(f"| {r.episode_id} | {g.step} | {_cell(v.claim)} | {_cell(v.reason)}{more} |")
    return [*lines, ""]


def _cell(text: str, n: int = 120) -> str:
    """Model text in a markdown table cell: one line, no pipes, clipped."""
    text = " ".join(plain_text(text).split()).replace("|", "/")
    return text if len(text) <= n else text[: n - 1] + "…"


def _gvr(m: Metrics) -> str:
    """GVR with the steps it rests on: `12.5 (3/24)`; -- when no step could be checked."""
    return "--" if m.gvr is None else f"{m.gvr:.1f} ({m.grounding_flagged}/{m.grounding_checked})"


def _suite_order(suites: Iterable[str]) -> list[str]:
    s = set(suites)
    return [x for x in PAPER_SUITES if x in s] + sorted(s - set(PAPER_SUITES))


def _config_order(records: list[EpisodeRecord]) -> list[tuple[str, str]]:
    configs = {(r.backend, r.variant) for r in records}
    rank = {v: i for i, v in enumerate(VARIANTS)}
    return sorted(configs, key=lambda c: (c[0], rank.get(c[1], 99), c[1]))


# The paper's figures (Section IV), as printed; the report lays a run beside them.
PAPER_SR = {"localization": 90.0, "clutter": 80.0, "sequential": 100.0, "search": 80.0}
# "Comparison with baseline frameworks and different VLM backbones" (project name: Table V):
# method -> (SR, ARR, RS, IAR, RT s); `match` finds a run's model among them.
PAPER_BACKBONES: dict[str, tuple[float, float, float, float, float]] = {
    "AERMANI-VLM (Gemini-3-Pro)": (87.5, 2.3, 16.8, 4.1, 0.92),
    "AERMANI-VLM (GPT-4o)": (85.0, 2.6, 18.4, 5.2, 0.88),
    "AERMANI-VLM (Claude-3.5)": (82.5, 3.1, 19.6, 6.4, 0.95),
    "AERMANI-VLM (Qwen2-VL)": (77.5, 4.5, 22.8, 8.7, 0.61),
    "AERMANI-VLM (LLaVA-Next)": (72.5, 5.2, 25.3, 10.1, 0.58),
    "ReAct Prompting (VLM)": (35.0, 12.5, 28.0, 15.0, 0.90),
}
_BACKBONE_KEYS = {"gemini": "AERMANI-VLM (Gemini-3-Pro)", "gpt-4o": "AERMANI-VLM (GPT-4o)",
                  "claude": "AERMANI-VLM (Claude-3.5)", "qwen2-vl": "AERMANI-VLM (Qwen2-VL)",
                  "llava": "AERMANI-VLM (LLaVA-Next)"}
# The paper's Table III baseline rows and the variant that maps each onto this skill interface
# (services/reasoner/baselines.py; ReAct is the `react` variant).
PAPER_FRAMEWORKS: dict[str, tuple[str, tuple[float, float, float, float, float]]] = {
    "direct": ("RT-2", (10.0, 19.0, 42.0, 35.0, 0.85)),
    "saycan": ("SayCan", (20.0, 16.0, 33.0, 28.0, 0.91)),
    "react": ("ReAct Prompting (VLM)", (35.0, 12.5, 28.0, 15.0, 0.90)),
    "waypoint": ("UAV-VLN", (30.0, 16.5, 38.0, 31.0, 0.72)),
    "plan_once": ("UAV-VLA", (45.0, 10.5, 26.0, 18.0, 0.88)),
}
NOT_RUN = "not run here: needs a GPU/API key"
RULES_NAME = "rules (non-VLM baseline)"


def method_name(backend: str, variant: str, multi_backend: bool = True) -> str:
    """The name of a method in every table. The rules baseline is named as what it is, a non-VLM baseline,
    never as AERMANI-VLM; a model backend gets the paper's name of the variant plus the backend."""
    if backend == "rules":
        return RULES_NAME if variant == "full" else f"{RULES_NAME}, {variant} prompt"
    name = VARIANT_TITLES.get(variant, variant)
    return f"{name} ({backend})"


def paper_row_for(model: str) -> str | None:
    """The paper's backbone row a model name belongs to (e.g. Qwen/Qwen2-VL-7B-Instruct -> Qwen2-VL)."""
    m = model.lower()
    return next((row for key, row in _BACKBONE_KEYS.items() if key in m), None)


def _loopback(url: str) -> bool:
    host = urlparse(url).hostname or ""
    if host == "localhost":
        return True
    try:
        return ip_address(host).is_loopback
    except ValueError:
        return False


def backend_note(config: dict[str, Any], records: list[EpisodeRecord]) -> str:
    """What the numbers measure, in one paragraph: the report must never pass off a stand-in as a VLM."""
    backends = sorted({r.backend for r in records}) or [config.get("backend", "rules")]
    parts = []
    for b in backends:
        if b == "rules":
            parts.append("`rules`: the deterministic rule-based policy, not a VLM; the numbers measure the stack "
                         "(simulator, perception, skills, reasoner loop) with a policy that always answers validly")
        elif b == "replay":
            parts.append("`replay`: answers replayed from a recorded log, not live model calls")
        else:
            url = config.get("base_url") or ""
            model = config.get("model") or "(default model)"
            where = f" at {url}" if url else ""
            p = f"`{b}`: model {model}{where}"
            if url and _loopback(url):
                p += (" -- a server on this machine (loopback); when it is the local test server "
                      "(tests/reasoner/fake_vlm.py) the numbers reflect the test server, not a real VLM")
            parts.append(p)
    note = "; ".join(parts) + "."
    note += (f" Perception: {segmenter_text(config)}; simulator: MuJoCo physics, realism "
             f"`{config.get('realism') or 'unrecorded'}`.")
    if config.get("note"):
        note = f"{config['note']} {note}"
    return note


def segmenter_text(config: dict[str, Any]) -> str:
    """Which segmenter perception ran (AERMANI_PERCEPTION_SEGMENTER), and whether that is real perception."""
    seg = config.get("segmenter")
    if not seg:
        return "segmenter unrecorded (runs from before it was recorded used `sim`, the ground-truth oracle)"
    if seg == "sim":
        return "`sim` segmenter -- ORACLE: the simulator's ground-truth masks, not real perception"
    what = {"color": "the colour segmenter (OpenCV colour classes on the rendered pixels + depth)",
            "sam3": "SAM3 (open-vocabulary segmentation on the rendered pixels + depth)"}.get(seg, seg)
    return f"`{seg}` segmenter -- real: {what}"


def _seeds_text(records: list[EpisodeRecord]) -> str:
    seeds = sorted({r.seed for r in records})
    return ", ".join(str(x) for x in seeds) if seeds else "--"


def _freeze_text(config: dict[str, Any]) -> str:
    """The held-out rule's two commits: the last that changed a test line, the last that changed the policy."""
    frozen, policy = config.get("split_frozen"), config.get("policy_changed")
    if not frozen and not policy:
        return "unrecorded (a run before the split's freeze was recorded)"
    text = f"`{str(frozen)[:12]}` / `{str(policy)[:12]}`"
    subject = config.get("policy_changed_subject")
    if subject:
        text += f" (the last policy change: \"{_cell(str(subject), 100)}\""
        files = config.get("policy_changed_files")
        text += f", {_cell(str(files), 160)})" if files else ")"
    after = config.get("policy_changed_after_freeze")
    if after is True:
        text += (" (the policy changed after the split froze: a test figure is held out only if that change was "
                 "not tuned on it)")
    elif after is False:
        text += " (no policy change since the split froze)"
    return text


def configuration_lines(records: list[EpisodeRecord], config: dict[str, Any]) -> list[str]:
    """The configuration table at the top of report.md: everything that produced the numbers."""
    commit = config.get("commit") or "unrecorded"
    dirty = config.get("dirty")
    rev = f"`{commit}`" + (" (dirty: uncommitted changes in the work tree)" if dirty is True
                           else " (clean)" if dirty is False else "")
    backends = sorted({r.backend for r in records}) or [config.get("backend", "")]
    models = sorted({r.model for r in records if r.model}) or [config.get("model") or "--"]
    variants = sorted({r.variant for r in records}) or config.get("variants") or []
    ran = [r for r in records if not r.harness_error]
    rows = [
        ("command (regenerates this report; rerun with a fresh --out)", f"`{config.get('command', 'unrecorded')}`"),
        ("rebuild the report from episodes.jsonl",
         f"`{config.get('report_only_command', 'aermani eval --out DIR --report-only')}`"),
        ("commit", rev),
        ("test split frozen at / last change to the policy stack (reasoner, executor, perception)",
         _freeze_text(config)),
        ("backend", ", ".join(f"{b}" + (" (non-VLM baseline)" if b == "rules" else "") for b in backends)),
        ("model", ", ".join(models)),
        ("variant", ", ".join(variants)),
        ("segmenter", segmenter_text(config)),
        ("simulator realism", f"`{config.get('realism') or 'unrecorded'}`"),
        ("speed factor", str(config.get("speed_factor", "unrecorded"))),
        ("split", f"`{config.get('split') or 'unrecorded'}`" + (f" (task file {config['tasks_file']})"
                                                                if config.get("tasks_file") else "")),
        ("episodes per suite", _episodes_text(config)),
        ("N (episodes in the metrics / recorded)", f"{len(ran)} / {len(records)}"),
        ("seeds", _seeds_text(records)),
        ("T_max, judge criteria", f"{config.get('t_max_s', '?')} s, " + (
            f"a caller's placement tolerance of {config['tolerance']} m (a run before the task criteria)"
            if "tolerance" in config else "each task's (`criteria` in its scenario; docs/evaluation.md)")),
        ("not-found bound (`\"expect\": \"not_found\"` tasks)", _not_found_bound_text(records)),
        ("vehicles", ", ".join(sorted({r.vehicle_id for r in records if r.vehicle_id})) or "--"),
        ("effective settings (as the services read them)", _effective_text(config)),
        ("AERMANI_* variables in the shell", _environment_text(config)),
    ]
    return ["## Configuration", "", "| | |", "|---|---|"] + [f"| {k} | {v} |" for k, v in rows] + [""]


def _episodes_text(config: dict[str, Any]) -> str:
    """How many episodes each suite ran: every line on K layouts, or N cycling through the lines (opt-in)."""
    if config.get("seeds_per_line"):
        return f"every line x {config['seeds_per_line']} layout seeds"
    if config.get("episodes"):
        return (f"{config['episodes']}, cycling through each suite's lines (`--episodes`: with fewer episodes than "
                "lines, some lines never ran)")
    return "each line of the task file once" if config.get("tasks_file") else str(config.get("episodes"))


def _not_found_bound_text(records: list[EpisodeRecord]) -> str:
    """The bound on a not-found task's reasoning steps: the default (from the room search's coverage) and the
    bounds the run's not-found episodes were held to."""
    text = (f"{NOT_FOUND_MAX_STEPS} reasoning steps by default: a whole search of the room ({SEARCH_STEPS} steps, "
            "the rules baseline's search budget), the `done` and 3 steps of slack (shared/search.py)")
    bounds = sorted({r.task.not_found_max_steps for r in records if r.task.expect == "not_found"})
    n = sum(1 for r in records if r.task.expect == "not_found" and not r.harness_error)
    if bounds:
        text += f"; this run's {n} not-found episode(s) held to {', '.join(str(b) for b in bounds)}"
    return text


def not_found_lines(records: list[EpisodeRecord]) -> list[str]:
    """Every not-found episode: its steps against its bound and the verdict (empty when the run has none)."""
    recs = [r for r in records if r.task.expect == "not_found" and not r.harness_error]
    if not recs:
        return []
    lines = ["## Not-found tasks", "", "The world lacks the object: success is the task ending failed with a "
             "not-found reason within the bound, holding nothing.", "",
             "| Episode | Object the world lacks | Steps / bound | Success | Verdict |", "|---|---|---|---|---|"]
    for r in recs:
        lines.append(f"| {r.episode_id} | {r.task.target_object} | {reasoning_steps(r)} / "
                     f"{r.task.not_found_max_steps} | {'yes' if r.success else 'no'} | {_cell(r.verdict)} |")
    return [*lines, ""]


def _effective_text(config: dict) -> str:
    """The effective values of the settings that shape the numbers (run_config.json `effective`)."""
    eff = config.get("effective")
    if not eff:
        return "unrecorded (a run before they were recorded)"
    if "error" in eff:
        return _cell(str(eff["error"]), 300)
    names = {"realism": "realism", "dynamics": "dynamics (AERMANI_SIM_DYNAMICS)", "speed_factor": "speed factor",
             "step_cap": "step cap", "t_max_s": "T_max (s)", "backend": "backend", "output_mode": "output mode",
             "segmenter": "segmenter"}
    return "<br>".join(f"{names.get(k, k)} `{v}`" for k, v in eff.items())


def motion_lines(records: list[EpisodeRecord]) -> list[str]:
    """Every episode whose task asks for motions: whether they happened before the pick (empty: none asks)."""
    recs = [r for r in records if r.task.motions and not r.harness_error]
    if not recs:
        return []
    failed = [r for r in recs if r.motions_ok is False]
    judged = sum(1 for r in failed if judged_ok(r) and r.state == "succeeded")
    lines = ["## Motion checks", "", f"Sequential tasks are scored for the motions they ask for, from the recorded "
             f"trajectory (docs/evaluation.md, Scoring what a task asks): {len(recs) - len(failed)} of {len(recs)} "
             f"episode(s) made them before the pick; {judged} episode(s) that ended succeeded with the judge's "
             "agreement are failures because a commanded motion did not happen.", "",
             "| Episode | Asked | Happened | Success | How |", "|---|---|---|---|---|"]
    for r in recs:
        asked = ", ".join(m.text() for m in r.task.motions)
        ok = {True: "yes", False: "**no**", None: "not checked"}[r.motions_ok]
        lines.append(f"| {r.episode_id} | {_cell(asked, 80)} | {ok} | {'yes' if r.success else 'no'} | "
                     f"{_cell(r.motions_detail, 160)} |")
    return [*lines, ""]


def choice_lines(records: list[EpisodeRecord]) -> list[str]:
    """Every size or conditional task: the simulator's decision, the object chosen, and each success on a guess
    flagged (empty: none)."""
    recs = [r for r in records if r.task.choice is not None and not r.harness_error]
    if not recs:
        return []
    guesses = [r for r in recs if r.success and r.choice is not None and r.choice.informed is False]
    lines = ["## Size and conditional tasks", "", "The simulator decides which object meets the command's criterion "
             "from the world at the start; only that object counts. A success whose object was picked before the "
             "policy had seen what decides the choice (every compared object; the place the condition is about) is "
             f"a **success on a guess**: {len(guesses)} of {sum(r.success for r in recs)} success(es) here.", "",
             "| Episode | Criterion | World's answer (why) | Chosen | Seen before the pick | Success |",
             "|---|---|---|---|---|---|"]
    for r in recs:
        c = r.choice
        if c is None:
            lines.append(f"| {r.episode_id} | {_cell(r.task.choice.text() if r.task.choice else '', 80)} | "
                         "not recorded | -- | -- | " + ("yes" if r.success else "no") + " |")
            continue
        seen = {True: "all", False: "not all", None: "unknown"}[c.informed]
        seen += f" ({', '.join(c.seen) or 'none'} of {', '.join(c.needed) or '--'})"
        ok = "yes" if r.success else "no"
        if r.success and c.informed is False:
            ok = "yes, **on a guess**"
        lines.append(f"| {r.episode_id} | {_cell(c.criterion, 80)} | {' or '.join(c.answer)} ({_cell(c.reason, 100)}) "
                     f"| {c.chosen or '--'} | {seen} | {ok} |")
    return [*lines, ""]


def _environment_text(config: dict) -> str:
    """Every AERMANI_* variable of the shell (run_config.json `environment`), those the run overrode marked, or why
    there are none."""
    env = config.get("environment")
    if env is None:
        return "unrecorded (a run before they were recorded)"
    if not env:
        return "none (every setting at its default or set by the run)"
    over = set(config.get("environment_overridden") or ())
    return "<br>".join(f"`{k}={v}`" + (" (overridden by the run)" if k in over else "") for k, v in env.items())


def incident_lines(records: list[EpisodeRecord]) -> list[str]:
    """Every excluded, retried or restarted episode with its reason."""
    excluded = [r for r in records if r.harness_error]
    restarted = [r for r in records if r.attempts > 1 and not r.harness_error]
    stale = [r for r in records if r.stale_memory]
    lines = ["## Excluded, retried and restarted episodes", ""]
    if not excluded and not restarted and not stale:
        return lines + ["None: every episode ran once, to its end, and is in the metrics.", ""]
    for r in excluded:
        lines.append(f"- excluded (left out of the metrics, retried by the next run of the command): "
                     f"{r.episode_id} on {r.vehicle_id or '?'}: {r.harness_error}")
    for r in restarted:
        why = "; ".join(r.restarts) or "take-off failed before the first reasoning step"
        lines.append(f"- restarted ({r.attempts} trials, the last one is in the metrics): {r.episode_id} on "
                     f"{r.vehicle_id or '?'}: {why}")
    for r in stale:
        lines.append(f"- executor process restarted before the episode (legacy harness): {r.episode_id} on "
                     f"{r.vehicle_id or '?'}: {r.stale_memory}")
    return lines + [""]


def paper_comparison_lines(records: list[EpisodeRecord], config: dict[str, Any]) -> list[str]:
    """The paper's backbone table beside this run: a real model's row gets this run's figures, the others say
    they were not run here."""
    model = (config.get("model") or "") if config.get("backend") not in NO_MODEL_BACKENDS else ""
    mine = paper_row_for(model) if model else None
    lines = ["## Beside the paper (comparison with VLM backbones, averaged over the suites)", "",
             "| Method | paper SR | paper ARR | paper RS | paper IAR | paper RT (s) | real-model run here |",
             "|---|---|---|---|---|---|---|"]
    m = compute(r for r in records if r.variant == "full")  # a backbone row is AERMANI-VLM: the full variant
    for row, (sr, arr, rs, iar, rt) in PAPER_BACKBONES.items():
        if row == PAPER_FRAMEWORKS["react"][0]:
            continue  # in the frameworks table below
        here = NOT_RUN
        if row == mine and m.episodes:
            here = (f"SR {_sr(m)}, ARR {_fmt(m.arr)}, RS {_fmt(m.rs)}, IAR {_fmt(m.iar)}, "
                    f"RT {_fmt(m.rt_median, 2)} ({model}, N={m.episodes})")
        lines.append(f"| {row} | {sr:.1f} | {arr:.1f} | {rs:.1f} | {iar:.1f} | {rt:.2f} | {here} |")
    if mine is None:
        b = sorted({r.backend for r in records}) or [config.get("backend", "?")]
        lines += ["", f"This run ({', '.join(method_name(x, 'full') for x in b)}) is not one of the paper's methods; "
                  "its figures are in the tables above. docs/evaluation.md shows how to run the paper's backbones."]
    return lines + [""] + framework_lines(records, model, config.get("base_url") or "")


def framework_lines(records: list[EpisodeRecord], model: str, base_url: str = "") -> list[str]:
    """The paper's Table III baseline frameworks beside this run's variants that map them: a model backend's run
    only (the rules backend refuses them), and never a loopback server's (it may be the local test server, whose
    answers are the rules policy's: no result to put beside the paper's)."""
    lines = ["## Beside the paper (baseline frameworks on the same skill interface)", "",
             "| Method | variant here | paper SR | paper ARR | paper RS | paper IAR | paper RT (s) | run here |",
             "|---|---|---|---|---|---|---|---|"]
    for variant, (row, (sr, arr, rs, iar, rt)) in PAPER_FRAMEWORKS.items():
        recs = [r for r in records if r.variant == variant and r.backend not in NO_MODEL_BACKENDS]
        here = NOT_RUN
        if recs and base_url and _loopback(base_url):
            here = f"ran on a loopback server (N={len(recs)}): not put beside the paper (see Backend)"
        elif recs and model:
            m = compute(recs)
            here = (f"SR {_sr(m)}, ARR {_fmt(m.arr)}, RS {_fmt(m.rs)}, IAR {_fmt(m.iar)}, "
                    f"RT {_fmt(m.rt_median, 2)} ({model}, N={m.episodes})")
        lines.append(f"| {row} | `{variant}` | {sr:.1f} | {arr:.1f} | {rs:.1f} | {iar:.1f} | {rt:.2f} | {here} |")
    return lines + [""]


def summarize(records: list[EpisodeRecord]) -> dict[str, Any]:
    """Metrics per configuration (backend/variant) and per configuration x suite."""
    by_config: dict[str, Any] = {}
    for backend, variant in _config_order(records):
        recs = [r for r in records if r.backend == backend and r.variant == variant]
        by_config[f"{backend}/{variant}"] = {
            "backend": backend, "variant": variant,
            "overall": compute(recs).model_dump(),
            "suites": {s: compute([r for r in recs if r.suite == s]).model_dump()
                       for s in _suite_order(r.suite for r in recs)},
        }
    return by_config


def _endings_section(records: list[EpisodeRecord], configs: list[tuple[str, str]], multi: bool) -> list[str]:
    """End state, judge and collisions per method: SR needs both the task's end state and the judge."""
    lines = ["", "## End state, judge and collisions", "",
             "SR counts an episode only when both hold: the task's own end state is `succeeded` and the "
             "simulator's ground-truth judge agrees (and a sequential task's motions happened). Collisions: every "
             "incident the physics simulator recorded since the episode's reset, each once, counted by kind: airframe "
             "(the airframe or its gear against furniture, walls or the ceiling), gripper strikes (a finger pad or "
             "arm against furniture, a wall, the ceiling or an object other than the task's target), knocked (an "
             "object not in the gripper tipped over or left what it stood on), dropped (an object let go or "
             "slipping after a lift fell more than 0.1 m).", "",
             "Motions missed: episodes whose commanded motions did not happen before the pick (failures whatever "
             "the judge said); successes on a guess: size or conditional successes picked before what decides the "
             "choice was seen (counted in SR, flagged).", "",
             "| Method | N | ended succeeded | judge success | motions missed | both (SR numerator) | successes on a "
             "guess | collisions | airframe | gripper strikes | knocked | dropped | episodes with a collision | "
             "terminal states |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for b, v in configs:
        recs = [r for r in records if r.backend == b and r.variant == v and not r.harness_error]
        m = compute(recs)
        states: dict[str, int] = {}
        for r in recs:
            states[r.state] = states.get(r.state, 0) + 1
        lines.append(f"| {method_name(b, v, multi)} | {m.episodes} | {m.ended_succeeded} | {m.judged_success} | "
                     f"{m.motions_missed} | {m.successes} | {m.guessed_successes} | {m.collisions} "
                     f"({_fmt(m.collisions_per_episode, 2)} per episode) | "
                     f"{m.vehicle_collisions} | {m.gripper_strikes} | {m.knocked_objects} | {m.dropped_objects} | "
                     f"{m.collision_episodes} | " + ", ".join(f"{k} {n}" for k, n in sorted(states.items())) + " |")
    lines.append("")
    return lines


def _paper_section(records: list[EpisodeRecord], suites: list[str], configs: list[tuple[str, str]],
                   multi: bool) -> list[str]:
    """The full-variant methods beside the paper's AERMANI-VLM by task suite (empty: no paper suite)."""
    paper_suites = [s for s in suites if s in PAPER_RS]
    if not paper_suites:
        return []
    lines = ["## Beside the paper's AERMANI-VLM (by task suite)", "",
             "| Task Suite | Method | SR [95 % CI] | paper SR | RS | paper RS |", "|---|---|---|---|---|---|"]
    for s in paper_suites:
        for b, v in configs:
            recs = [r for r in records if r.suite == s and r.backend == b and r.variant == v]
            if recs and v == "full":
                m = compute(recs)
                lines.append(f"| {SUITE_TITLES.get(s, s)} | {method_name(b, v, multi)} | {_sr(m)} | "
                             f"{PAPER_SR[s]:.1f} | {_fmt(m.rs)} | {PAPER_RS[s]:.1f} |")
    lines.append("")
    return lines


def markdown(records: list[EpisodeRecord], config: dict[str, Any], plots: list[str]) -> str:
    configs = _config_order(records)
    multi = len({b for b, _ in configs}) > 1
    suites = _suite_order(r.suite for r in records)
    lines = ["# aermani evaluation report", "",
             f"Generated {time.strftime('%Y-%m-%d %H:%M:%S %Z')} from `{RESULTS_FILE}` ({len(records)} episodes).", "",
             f"**Backend.** {backend_note(config, records)}", ""]
    if config.get("split") == "dev":
        lines += ["**Dev split.** These figures come from the split the project is built against; headline "
                  "figures come from the test split (docs/evaluation.md).", ""]
    lines += configuration_lines(records, config)
    settings = {k: config.get(k) for k in ("output_mode", "base_url", "suites", "seed", "parallel", "connect")
                if config.get(k) not in (None, "", [])}
    settings |= {k: True for k in ("paper_history", "free_text_baselines") if config.get(k) is True}
    if settings:
        lines += ["Other settings: " + ", ".join(f"{k}={v}" for k, v in settings.items()) + ".", ""]

    lines += ["## Results by task suite (paper Table II layout)", "",
              "| Task Suite | Method | N | SR ↑ [95 % CI] | ARR ↓ | RS ↓ | IAR ↓ | GVR ↓ |",
              "|---|---|---|---|---|---|---|---|"]
    for s in suites:
        for i, (b, v) in enumerate(configs):
            recs = [r for r in records if r.suite == s and r.backend == b and r.variant == v]
            if not recs:
                continue
            m = compute(recs)
            suite_cell = SUITE_TITLES.get(s, s) if i == 0 else ""
            lines.append(f"| {suite_cell} | {method_name(b, v, multi)} | {m.episodes} | {_sr(m)} | "
                         f"{_fmt(m.arr)} | {_fmt(m.rs)} | {_fmt(m.iar)} | {_gvr(m)} |")
    lines += ["", "## Summary per method (paper Table V layout)", "",
              "| Method | N | SR ↑ [95 % CI] | ARR ↓ | RS ↓ | IAR ↓ | GVR ↓ | RT median (s) ↓ | RT p95 (s) ↓ "
              "| TT wall (s) ↓ | TT sim (s) ↓ |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for b, v in configs:
        m = compute(r for r in records if r.backend == b and r.variant == v)
        lines.append(f"| {method_name(b, v, multi)} | {m.episodes} | {_sr(m)} | {_fmt(m.arr)} | {_fmt(m.rs)} | "
                     f"{_fmt(m.iar)} | {_gvr(m)} | {_rt(m, b)} | {_rt(m, b, p95=True)} | {_fmt(m.tt)} | "
                     f"{_fmt(m.tt_sim)} |")
    lines += ["", "IAR by answer decoding (schema-constrained: the request carried the answer's JSON schema; free "
              "text: read by the lenient parser):", ""]
    for b, v in configs:
        modes = iar_by_mode(r for r in records if r.backend == b and r.variant == v)
        lines.append(f"- {method_name(b, v, multi)}: " + ("; ".join(
            f"{'schema-constrained' if m == 'schema' else 'free text'} IAR {100 * bad / n:.1f} % of {n} calls"
            for m, (bad, n) in sorted(modes.items())) or "no model calls"))
    lines += _endings_section(records, configs, multi)
    lines += incident_lines(records)
    lines += not_found_lines(records)
    lines += motion_lines(records)
    lines += choice_lines(records)
    lines += grounding_lines(records)
    lines += _paper_section(records, suites, configs, multi)
    lines += paper_comparison_lines(records, config)
    lines += ["", "Metrics (definitions in docs/evaluation.md): SR = % of episodes where the simulator's ground "
              "truth has the right object placed on the destination (or picked, when the command has no "
              "destination) by the task's criteria before T_max (for a size or conditional task the object the "
              "simulator decided; a sequential task's motions made before the pick), with its 95 % Wilson score "
              "interval in brackets (N episodes); ARR = mean % of redundant actions over successful "
              "episodes; RS = mean reasoning steps per episode; IAR = % of model answers that were invalid; "
              "GVR = % of checked steps whose DRT contradicts what the stack measured (objects said seen but "
              "not detected, a held object the gripper does not hold, positions off; flagged/checked steps in "
              "brackets; for the rules policy the DRT is its own template); "
              "RT = model latency per query; TT = mean end-to-end time of successful episodes, on the wall clock "
              f"(simulator speed factor {config.get('speed_factor', '?')}, plus real waits: model calls, perception) "
              "and in simulated seconds (the simulator's clock; -- for records from before it was kept).", ""]
    failed = [r for r in records if not r.success and not r.harness_error]
    if failed:
        lines += ["## Failed episodes", "", "| Episode | Vehicle | State | Judge | Steps | Collisions | Verdict |",
                  "|---|---|---|---|---|---|---|"]
        for r in failed:
            verdict = (r.verdict or r.message).replace("|", "/")
            lines.append(f"| {r.episode_id} | {r.vehicle_id} | {r.state} | {'ok' if judged_ok(r) else 'no'} | "
                         f"{reasoning_steps(r)} | {', '.join(r.collisions) or '--'} | {verdict} |")
        lines.append("")
    if plots:
        lines += ["## Plots", ""] + [f"![{Path(p).stem}]({p})" for p in plots] + [""]
    return "\n".join(lines)


def plot(records: list[EpisodeRecord], out: Path) -> list[str]:
    """PNG plots next to the report; returns their paths relative to `out`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not records:
        return []
    (out / "plots").mkdir(parents=True, exist_ok=True)
    configs = _config_order(records)
    multi = len({b for b, _ in configs}) > 1
    suites = _suite_order(r.suite for r in records)
    names = [method_name(b, v, multi) for b, v in configs]
    paths = []

    fig, ax = plt.subplots(figsize=(min(12, max(6, 2.2 * len(suites))), 4))
    width = 0.8 / max(1, len(configs))
    for k, (b, v) in enumerate(configs):
        vals = []
        for s in suites:
            m = compute(r for r in records if r.suite == s and r.backend == b and r.variant == v)
            vals.append(m.sr or 0.0)
        ax.bar([i + k * width - 0.4 + width / 2 for i in range(len(suites))], vals, width, label=names[k])
    ax.set_xticks(range(len(suites)), [SUITE_TITLES.get(s, s) for s in suites])
    ax.set_ylabel("success rate (%)")
    ax.set_ylim(0, 105)
    ax.set_title("Success by suite and variant")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(out / "plots" / "success_by_suite.png", dpi=100)
    plt.close(fig)
    paths.append("plots/success_by_suite.png")

    fig, ax = plt.subplots(figsize=(6, 4))
    for k, (b, v) in enumerate(configs):
        lat = [c.latency_s for r in records if r.backend == b and r.variant == v and not r.harness_error
               for s in r.steps for c in s.calls]
        if lat:
            ax.hist(lat, bins=30, alpha=0.6, label=names[k])
    ax.set_xlabel("model response time per query (s)")
    ax.set_ylabel("queries")
    ax.set_title("RT histogram")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "plots" / "rt_histogram.png", dpi=100)
    plt.close(fig)
    paths.append("plots/rt_histogram.png")

    fig, ax = plt.subplots(figsize=(min(14, max(6, 0.6 * len(suites) * max(1, len(configs)))), 4.5))
    data, labels = [], []
    for s in suites:
        for k, (b, v) in enumerate(configs):
            steps = [reasoning_steps(r) for r in records
                     if r.suite == s and r.backend == b and r.variant == v and not r.harness_error]
            if steps:
                data.append(steps)
                labels.append(f"{SUITE_TITLES.get(s, s)}\n{names[k]}" if len(configs) > 1 else SUITE_TITLES.get(s, s))
    if data:
        ax.boxplot(data, showmeans=True)
        ax.set_xticks(range(1, len(labels) + 1), labels, fontsize=6 if len(configs) > 1 else 9,
                      rotation=90 if len(configs) > 1 else 0)
    for s in suites:
        if s in PAPER_RS and len(configs) == 1:
            i = suites.index(s) + 1
            ax.plot([i - 0.4, i + 0.4], [PAPER_RS[s]] * 2, "r--", linewidth=1)
    ax.set_ylabel("reasoning steps per episode")
    ax.set_title("Steps per episode" + (" (red: paper's AERMANI-VLM RS)" if len(configs) == 1 else ""))
    fig.tight_layout()
    fig.savefig(out / "plots" / "steps_per_episode.png", dpi=100)
    plt.close(fig)
    paths.append("plots/steps_per_episode.png")
    return paths


def write_report(out: Path, config: dict[str, Any] | None = None) -> dict[str, Path]:
    """(Re)build report.json, report.md and plots/ from out/episodes.jsonl. The run's settings are kept in
    run_config.json so a report rebuilt later still says what produced the numbers."""
    out = Path(out)
    cfg_path = out / "run_config.json"
    if config is not None:
        cfg_path.write_text(json.dumps(config, indent=2, default=str))
    elif cfg_path.exists():
        config = json.loads(cfg_path.read_text())
    config = config or {}
    records = sorted(ResultsFile(out / RESULTS_FILE).load(), key=lambda r: r.episode_id)
    plots = plot(records, out)
    ran = [r for r in records if not r.harness_error]
    doc = {
        "generated": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "backend_note": backend_note(config, records),
        "command": config.get("command"),
        "commit": config.get("commit"),
        "dirty": config.get("dirty"),
        "split_frozen": config.get("split_frozen"),
        "policy_changed": config.get("policy_changed"),
        "policy_changed_subject": config.get("policy_changed_subject"),
        "policy_changed_after_freeze": config.get("policy_changed_after_freeze"),
        "backend": config.get("backend"),
        "model": config.get("model"),
        "variants": config.get("variants"),
        "segmenter": config.get("segmenter"),
        "segmenter_description": segmenter_text(config),
        "realism": config.get("realism"),
        "speed_factor": config.get("speed_factor"),
        "effective": config.get("effective"),
        "not_found_bound": NOT_FOUND_MAX_STEPS,
        "environment": config.get("environment"),
        "split": config.get("split"),
        "seeds": sorted({r.seed for r in records}),
        "n": len(ran),
        "excluded": [{"episode_id": r.episode_id, "reason": r.harness_error} for r in records if r.harness_error],
        "restarted": [{"episode_id": r.episode_id, "attempts": r.attempts, "reasons": r.restarts}
                      for r in records if r.attempts > 1],
        "config": config,
        "metrics": summarize(records),
        # Every episode with every step; the prompt texts (the bulk) stay in episodes.jsonl only.
        "episodes": [{**r.model_dump(mode="json", exclude={"steps": {"__all__": {"prompt"}}}),
                      "grounding": grounding_doc(r)} for r in records],
    }
    (out / "report.json").write_text(json.dumps(doc, indent=1))
    (out / "report.md").write_text(markdown(records, config, plots))
    return {"json": out / "report.json", "markdown": out / "report.md", "plots": out / "plots"}


def write_mode_comparison(out: Path, modes: list[str]) -> Path:
    """OUT/modes.md: the same episodes run once per answer decoding mode (OUT/<mode>/), side by side."""
    lines = ["# Answer decoding modes compared", "",
             "The same episodes, once with the answer's JSON schema sent with every request (schema) and once as "
             "free text read by the lenient parser (text). Each mode's full report is in its folder.", "",
             "| Mode | Method | N | SR ↑ [95 % CI] | IAR ↓ | model calls | RT median (s) ↓ |",
             "|---|---|---|---|---|---|---|"]
    for mode in modes:
        records = ResultsFile(Path(out) / mode / RESULTS_FILE).load()
        configs = _config_order(records)
        for b, v in configs:
            m = compute(r for r in records if r.backend == b and r.variant == v)
            lines.append(f"| [{mode}]({mode}/report.md) | {method_name(b, v)} | {m.episodes} | {_sr(m)} | "
                         f"{_fmt(m.iar)} | {m.queries} | {_rt(m, b)} |")
    path = Path(out) / "modes.md"
    path.write_text("\n".join(lines) + "\n")
    return path
