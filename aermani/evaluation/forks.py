"""`aermani eval --fork-from LOG --step K`: from one moment of a recorded flight, N live forks per method, and
their success rates (issue 29: "from this hard moment, which model recovers").

Every fork starts the whole stack from the fork point (`aermani fork`, aermani/fork.py): the world as it was when
step K-1's skill ended, the recorded working memory and the History of steps 1..K-1; the method (backend,
variant, model) decides from step K on and the simulator's judge says whether the task then succeeded. Fork 1 of
every method continues the recorded noise (the same draws for every method, so a difference is the policy's);
forks 2..N draw the vehicle's and the camera's noise afresh from seeds 1..N-1 (`AERMANI_SIM_RESTORE_SEED`), the
same seeds for every method, so N forks sample how the moment can go on, not one realisation of it.

Output, in OUT: `forks.jsonl` (one line per fork; a rerun with the same OUT resumes, keeping finished forks),
`forks.md` and `forks.json` (the report), `plots/forks_sr.png`, and each fork's MCAP log and service logs under
`forks/<method>-<n>/`.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from aermani.evaluation.metrics import wilson
from aermani.evaluation.report import method_name, segmenter_text

FORKS_FILE = "forks.jsonl"


@dataclass(frozen=True)
class Method:
    """A policy the forks are run with: backend, prompt variant, model."""

    backend: str
    variant: str
    model: str = ""

    @property
    def tag(self) -> str:
        return "-".join(x for x in (self.backend, self.variant, self.model.replace("/", "_")) if x)


@dataclass
class ForkRow:
    """One fork's outcome, as `forks.jsonl` keeps it."""

    method: str
    backend: str
    variant: str
    model: str
    fork: int
    """1..N; fork 1 continues the recorded noise, fork n > 1 draws it from seed n - 1."""
    noise_seed: int | None
    state: str
    """The task's final state (succeeded, failed, aborted, timed_out...) or `error` when no final status came."""
    success: bool
    """The task ended succeeded and the simulator's judge agrees."""
    verdict: str
    steps: int
    """Reasoning steps after the fork point."""
    skills: list[str] = field(default_factory=list)
    task_s: float | None = None
    log: str | None = None
    exit_code: int = 1
    parent: str = ""
    """The fork point, `<log name>:<task id>:<step>`: a resumed OUT must be of the same one."""

    @property
    def harness_error(self) -> bool:
        """The fork never got a final status (the stack or the restore failed): not a policy's failure, so
        not counted in its success rate, and run again on a rerun."""
        return self.state == "error"


class ForkRunError(ValueError):
    """OUT holds forks of another fork point."""


def parent_of(point) -> str:
    return f"{point.log.name}:{point.task_id}:{point.step}"


def method_label(m: Method, multi_backend: bool) -> str:
    name = method_name(m.backend, m.variant, multi_backend)
    return f"{name} [{m.model}]" if m.model else name


def counted(rows: list[ForkRow]) -> list[ForkRow]:
    """The forks that ran to an end, the newest of each (method, fork): what success rates are computed on."""
    latest: dict[tuple[str, str, str, int], ForkRow] = {}
    for r in rows:
        if not r.harness_error:
            latest[(r.backend, r.variant, r.model, r.fork)] = r
    return list(latest.values())


def noise_seed(fork: int) -> int | None:
    return None if fork == 1 else fork - 1


def read_rows(out: Path) -> list[ForkRow]:
    path = out / FORKS_FILE
    if not path.is_file():
        return []
    rows = []
    for line in path.read_text().splitlines():
        if line.strip():
            rows.append(ForkRow(**json.loads(line)))
    return rows


def row_of(method: Method, fork: int, code: int, result: dict[str, Any], multi_backend: bool,
           parent: str = "") -> ForkRow:
    final, steps = result.get("final"), result.get("steps") or []
    task_s = None
    if final is not None and final.started_ns and final.ended_ns:
        task_s = round((final.ended_ns - final.started_ns) / 1e9, 2)
    skills = [s.ste.call if s.ste else "(no answer)" for s in steps]
    return ForkRow(method=method_label(method, multi_backend), backend=method.backend, parent=parent,
                   variant=method.variant, model=method.model, fork=fork, noise_seed=noise_seed(fork),
                   state=final.state.value if final is not None else "error",
                   success=bool(result.get("success")) and final is not None and final.state.value == "succeeded",
                   verdict=str(result.get("verdict") or "no verdict (the fork did not finish)"), steps=len(steps),
                   skills=skills, task_s=task_s, log=result.get("log"), exit_code=code)


def run_forks(point, methods: list[Method], forks: int, out: Path, *, base_url: str | None, segmenter: str | None,
              speed_factor: float, t_max: float, key_env: dict[str, str], progress: bool = True) -> list[ForkRow]:
    """Run what `out` does not hold yet; returns every row (finished earlier ones included)."""
    from rich.console import Console

    from aermani.fork import run_fork

    console = Console()
    out.mkdir(parents=True, exist_ok=True)
    rows = read_rows(out)
    parent = parent_of(point)
    others = sorted({r.parent for r in rows if r.parent != parent})
    if others:
        raise ForkRunError(f"{out / FORKS_FILE} holds forks of {', '.join(others)}, not of {parent}: use another "
                           "--out")
    multi = len({m.backend for m in methods}) > 1
    done = {(r.backend, r.variant, r.model, r.fork) for r in counted(rows)}
    todo = [(m, n) for m in methods for n in range(1, forks + 1) if (m.backend, m.variant, m.model, n) not in done]
    if len(todo) < len(methods) * forks:
        console.print(f"{len(methods) * forks - len(todo)} forks already in {out / FORKS_FILE}: resuming")
    t0 = time.monotonic()
    for i, (m, n) in enumerate(todo, 1):
        seed = noise_seed(n)
        elapsed = time.monotonic() - t0
        eta = f", about {elapsed / (i - 1) * (len(todo) - i + 1) / 60:.0f} min left" if i > 1 else ""
        if progress:
            console.rule(f"fork {i}/{len(todo)}: {method_label(m, multi)}, fork {n} of {forks} "
                         f"({'recorded noise' if seed is None else f'noise seed {seed}'}){eta}")
        where = out / "forks" / f"{m.tag}-{n}"
        env = dict(key_env)
        if seed is not None:
            env["AERMANI_SIM_RESTORE_SEED"] = str(seed)
        result: dict[str, Any] = {}
        code = run_fork(point, backend=m.backend, variant=m.variant, model=m.model, base_url=base_url,
                        segmenter=segmenter, speed_factor=speed_factor, t_max=t_max, log_dir=where / "logs",
                        out_dir=where, extra_env=env, result=result)
        if code == 130:  # interrupted: what finished is kept, the rest runs on a rerun
            break
        row = row_of(m, n, code, result, multi, parent)
        rows.append(row)
        with (out / FORKS_FILE).open("a") as f:
            f.write(json.dumps(asdict(row)) + "\n")
    return rows


def summary(rows: list[ForkRow]) -> list[dict[str, Any]]:
    """Per method, in the order first run: forks, successes, SR with its 95 % Wilson interval, mean steps and time."""
    by: dict[str, list[ForkRow]] = {}
    for r in counted(rows):
        by.setdefault(r.method, []).append(r)
    table = []
    for method, rs in by.items():
        ok = sum(r.success for r in rs)
        lo, hi = wilson(ok, len(rs))
        times = [r.task_s for r in rs if r.task_s is not None]
        first = sorted({r.skills[0] for r in rs if r.skills})
        table.append({"method": method, "forks": len(rs), "successes": ok, "sr": 100.0 * ok / len(rs),
                      "sr_ci": [round(lo, 1), round(hi, 1)], "mean_steps": sum(r.steps for r in rs) / len(rs),
                      "mean_task_s": sum(times) / len(times) if times else None, "first_skills": first,
                      "endings": sorted({r.state for r in rs})})
    return table


def markdown(point, rows: list[ForkRow], config: dict[str, Any], plots: list[str]) -> str:
    world = point.world
    table = summary(rows)
    n = int(config.get("forks") or max((r.fork for r in rows), default=0))
    lines = [f"# Forks of {point.log.name}, task {point.task_id}, before step {point.step}", "",
             f"Task: \"{point.command}\". Each fork starts the whole stack from the world recorded when step "
             f"{point.state.step}'s skill ({point.state.skill or '?'}) ended, the recorded working memory and the "
             f"History of steps 1..{point.step - 1}; the method decides from step {point.step} on and the "
             "simulator's judge says whether the task succeeded.", "",
             "## Configuration", "",
             f"- parent: {point.log.name} (recorded policy {point.backend or '?'}, variant {point.variant})",
             f"- simulator: MuJoCo, realism {world['realism']}, dynamics {world['dynamics']}, scenario seed "
             f"{world['scenario'].get('seed')}; speed factor {config.get('speed_factor')}",
             f"- perception: {segmenter_text(config)}",
             f"- forks per method: {n}: fork 1 continues the recorded draws of the vehicle's noise (the camera's "
             "noise restarts from seed 0 in every process), "
             + ("fork 2 draws the vehicle's and the camera's noise afresh from seed 1" if n == 2 else
                f"forks 2..{n} draw the vehicle's and the camera's noise afresh from seeds 1..{n - 1}")
             + " (the same for every method)" if n > 1 else
             "- forks per method: 1, continuing the recorded draws of the vehicle's noise",
             f"- T_max per fork: {config.get('t_max')} s; commit {config.get('commit', 'unrecorded')}"
             + (" (with uncommitted changes)" if config.get("dirty") else ""), ""]
    if config.get("note"):
        lines[2:2] = [str(config["note"]), ""]
    lines += ["## Success from the fork point", "",
              "| method | forks | succeeded (judge agrees) | SR % [95 % CI] | mean steps | mean task time s | "
              "first decision | endings |", "|---|---|---|---|---|---|---|---|"]
    for t in table:
        tt = "-" if t["mean_task_s"] is None else f"{t['mean_task_s']:.1f}"
        lines.append(f"| {t['method']} | {t['forks']} | {t['successes']} | {t['sr']:.0f} [{t['sr_ci'][0]:.0f}, "
                     f"{t['sr_ci'][1]:.0f}] | {t['mean_steps']:.1f} | {tt} | {', '.join(t['first_skills'])} | "
                     f"{', '.join(t['endings'])} |")
    recorded = [s.ste.skill if s.ste else "(no answer)" for s in point.recorded]
    errors = [r for r in rows if r.harness_error]
    if errors:
        lines += ["", f"{len(errors)} fork(s) never reached an end (the stack or the restore failed: see their "
                  "service logs); they are not counted above and run again when the command is rerun."]
    lines += ["", f"What the parent did from step {point.step}: {', '.join(recorded) or '(nothing)'}.", ""]
    lines += [f"![success rate per method]({p})" for p in plots]
    lines += ["", "## Every fork", "", "| method | fork | noise | ended | judge | steps | skills | log |",
              "|---|---|---|---|---|---|---|---|"]
    for r in counted(rows) + errors:
        noise = "recorded" if r.noise_seed is None else f"seed {r.noise_seed}"
        skills = ", ".join(r.skills[:12]) + (" ..." if len(r.skills) > 12 else "")
        verdict = r.verdict.replace("|", "/")[:120]
        lines.append(f"| {r.method} | {r.fork} | {noise} | {r.state} | {'ok' if r.success else 'no'}: {verdict} | "
                     f"{r.steps} | {skills} | {Path(r.log).name if r.log else '-'} |")
    lines += ["", f"Compare two forks step by step: `aermani diff {rows[0].log or 'A.mcap'} B.mcap`." if rows else ""]
    return "\n".join(lines) + "\n"


def plot(rows: list[ForkRow], out: Path, title: str = "") -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table = summary(rows)
    if not table:
        return []
    (out / "plots").mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(max(5, 1.6 * len(table)), 3.6))
    xs = range(len(table))
    srs = [t["sr"] for t in table]
    err = [[t["sr"] - t["sr_ci"][0] for t in table], [t["sr_ci"][1] - t["sr"] for t in table]]
    ax.bar(xs, srs, yerr=err, capsize=6, color="#4c72b0", width=0.6 if len(table) > 1 else 0.4)
    for x, t in zip(xs, table, strict=True):
        ax.text(x, 2, f"{t['successes']}/{t['forks']}", ha="center", va="bottom", color="white")
    ax.set_xticks(list(xs), [t["method"] for t in table], rotation=15, ha="right", fontsize=8)
    ax.set_ylim(0, 105)
    ax.set_ylabel("success from the fork point, % (95 % CI)")
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    path = out / "plots" / "forks_sr.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [str(path.relative_to(out))]


def write_report(point, rows: list[ForkRow], out: Path, config: dict[str, Any]) -> Path:
    plots = plot(rows, out, f"{point.log.name}, before step {point.step}")
    (out / "forks.json").write_text(json.dumps({"parent": {"log": point.log.name, "task_id": point.task_id,
                                                           "step": point.step, "command": point.command},
                                                "config": config, "methods": summary(rows),
                                                "forks": [asdict(r) for r in rows]}, indent=1))
    path = out / "forks.md"
    path.write_text(markdown(point, rows, config, plots))
    return path
