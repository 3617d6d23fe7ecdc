"""What a user waits for on every reasoning step besides the model and the skill (issue 27), from the recorded
steps of real runs.

Each reasoning step the reasoner records carries `timing` (shared.messages.StepTiming): from the previous
skill's end to this step's first model call (`to_model_s`: the observation's frame, detection and state waits,
the link gate and the prompt's compilation), the model calls, from sending the skill to the executor's
acceptance, the skill as the executor timed it, and from the skill's end to the reasoner holding its status.
The non-model, non-skill time of a step, what the loop itself makes a user wait for whatever the model, is
`to_model_s + accept_s + report_s`.

Two runs, real processes on this machine, the `rules` baseline (a rule-based policy: its model time is a
Python call, so the figures are the loop's own) with the real colour segmenter on the `realistic` MuJoCo
simulator and its 15 fps camera:
- a demo (`aermani demo`, the README's main job) at speed factor 1 (real time, as a user runs it in the field:
  the camera's frame period is a real 67 ms), its steps read from the recorder's MCAP log;
- an evaluation run (`aermani eval`, dev split, one episode of each suite) at the evaluation's default speed
  factor, its steps read from episodes.jsonl.

    .venv/bin/python benchmarks/step_breakdown.py [--episodes 1] [--out runs/bench/steps] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks._figures import add_json_option, write_json  # noqa: E402
from shared.mcaplog import reasoning_steps  # noqa: E402
from shared.messages import StepTiming  # noqa: E402

COMMAND = "pick up the red cup and place it on the table"
PARTS = ("to_model_s", "frame_wait_s", "detections_wait_s", "state_wait_s", "link_wait_s", "prompt_s", "model_s",
         "accept_s", "skill_s", "report_s")
AERMANI = str(Path(sys.executable).with_name("aermani"))


def non_model_s(t: StepTiming) -> float:
    """What the loop makes a user wait for on a step besides the model and the skill."""
    return t.to_model_s + t.accept_s + t.report_s


def pct(values: list[float], q: float) -> float:
    """Nearest-rank percentile (q in 0..100) of a non-empty list."""
    s = sorted(values)
    return s[min(len(s) - 1, max(0, round(q / 100 * len(s) + 0.5) - 1))]


def summary(timings: list[StepTiming]) -> dict[str, Any]:
    """p50 and p95 in milliseconds of every part and of the non-model time, over the steps that ran a skill."""
    out: dict[str, Any] = {"steps": len(timings)}
    if not timings:
        return out
    rows = {p: [getattr(t, p) for t in timings] for p in PARTS}
    rows["non_model_s"] = [non_model_s(t) for t in timings]
    for name, vals in rows.items():
        key = name.removesuffix("_s")
        out[f"{key}_p50_ms"] = 1000 * statistics.median(vals)
        out[f"{key}_p95_ms"] = 1000 * pct(vals, 95)
    return out


def run(cmd: list[str], env: dict[str, str], timeout: float) -> None:
    print("$", " ".join(cmd), flush=True)
    t0 = time.monotonic()
    proc = subprocess.run(cmd, env=env, cwd=ROOT, timeout=timeout, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True)
    tail = "\n".join(proc.stdout.splitlines()[-8:])
    print(f"  exit {proc.returncode} after {time.monotonic() - t0:.0f} s\n{tail}", flush=True)
    if proc.returncode not in (0, 1):  # 1: the task or an episode failed, its steps still count
        raise SystemExit(f"{cmd[1]} failed (exit {proc.returncode})")


def demo_steps(out: Path, timeout: float) -> list[StepTiming]:
    rec = out / "demo" / "recordings"
    env = {**os.environ, "AERMANI_RECORDER_OUT_DIR": str(rec)}
    run([AERMANI, "demo", COMMAND, "--speed-factor", "1", "--log-dir", str(out / "demo" / "logs")], env, timeout)
    steps = [s for f in sorted(rec.glob("*.mcap")) for s in reasoning_steps(f)]
    return [s.timing for s in steps if s.timing is not None and s.skill_state is not None]


def eval_steps(out: Path, episodes: int, timeout: float) -> list[StepTiming]:
    dest = out / "eval"
    run([AERMANI, "eval", "--split", "dev", "--episodes", str(episodes), "--out", str(dest), "--no-progress"],
        dict(os.environ), timeout)
    timings = []
    for line in (dest / "episodes.jsonl").read_text().splitlines():
        for step in json.loads(line).get("steps") or ():
            if step.get("timing") and step.get("skill_state"):
                timings.append(StepTiming.model_validate(step["timing"]))
    return timings


def show(name: str, s: dict[str, Any]) -> None:
    print(f"\n{name}: {s['steps']} steps")
    if not s["steps"]:
        return
    for key in ("non_model", *(p.removesuffix("_s") for p in PARTS)):
        print(f"  {key:18s} p50 {s[key + '_p50_ms']:8.1f} ms   p95 {s[key + '_p95_ms']:8.1f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=1, help="evaluation episodes per suite (dev split)")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "bench" / "steps")
    ap.add_argument("--no-eval", action="store_true", help="only the demo")
    ap.add_argument("--timeout", type=float, default=1500.0)
    add_json_option(ap)
    args = ap.parse_args()
    # A fresh directory each run: an evaluation resumes from an earlier episodes.jsonl and a demo adds its log
    # beside earlier ones, so stale steps would be measured again.
    shutil.rmtree(args.out, ignore_errors=True)
    args.out.mkdir(parents=True, exist_ok=True)
    figures: dict[str, Any] = {"demo": summary(demo_steps(args.out, args.timeout))}
    show("demo (speed factor 1)", figures["demo"])
    if not args.no_eval:
        figures["eval"] = summary(eval_steps(args.out, args.episodes, args.timeout))
        show("evaluation (dev split)", figures["eval"])
    print("\nnon-model time per step = to_model + accept + report; target p95 <= 150 ms (issue 27)")
    write_json(args.json, "step_breakdown", figures, args)


if __name__ == "__main__":
    main()
