"""The speculative next step (issue 27): task time and the model wait per step with AERMANI_REASONER_SPECULATE off
and on, against a local model server that answers after a fixed time.

The model is the local stand-in VLM server (`tests/reasoner/fake_vlm.py`: a real HTTP server speaking the OpenAI
chat-completions API, answering each prompt with the rules policy's answer read from the prompt's text) with
every answer sent `--latency` seconds after its request (1 s: about the paper's median model response time of
0.92 s). It is a stand-in: the figures measure the loop's scheduling of the model's time, not a model's choices.
Each run is the README's demo task on the whole stack (real processes, the built-in MuJoCo simulator and its
camera, the colour segmenter) at speed factor 1 (real time); `--realism ideal` by default, so that runs with
and without speculation fly the same steps and differ in the waiting only (`realistic` adds its gusts, and a
failed grasp changes the task's length).

Per run: task wall time (task accepted to its end), steps, the speculations asked for and used, and the model wait
per step (StepTiming.model_s: what a user waits for the model after the skill before ended; a used speculation
leaves only what remained of its call). The saving is the mean task time off minus on.

    .venv/bin/python benchmarks/speculation.py [--runs 2] [--latency 1.0] [--realism ideal] [--json PATH]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks._figures import add_json_option, write_json  # noqa: E402

COMMAND = "pick up the red cup and place it on the table"


def one_run(speculate: bool, latency: float, realism: str, log_dir: Path) -> dict[str, Any]:
    from aermani.demo import run_demo, scenario_for
    from tests.reasoner.fake_vlm import FakeVLMServer

    scenario, accepted = scenario_for(COMMAND, None, None, 0)
    result: dict[str, Any] = {}
    with FakeVLMServer(latency_s=latency) as vlm:
        env = {"AERMANI_REASONER_BACKEND": "openai", "AERMANI_REASONER_API_KEY": "none",
               "AERMANI_REASONER_BASE_URL": vlm.openai_base_url, "AERMANI_REASONER_MODEL": "fake-vlm",
               "AERMANI_REASONER_SPECULATE": "1" if speculate else "0", "AERMANI_SIM_REALISM": realism,
               "AERMANI_SIM_SPEED_FACTOR": "1"}
        t0 = time.monotonic()
        code = run_demo(COMMAND, scenario, accepted, env=env, t_max=600, log_dir=log_dir,
                        services=("sim", "autopilot_bridge", "perception", "executor", "reasoner"), result=result)
        wall = time.monotonic() - t0
    final, steps = result.get("final"), result.get("steps") or []
    if final is None:
        raise SystemExit(f"the demo did not finish (exit {code}); logs in {log_dir}")
    waits = [s.timing.model_s for s in steps if s.timing is not None]
    return {"speculate": speculate, "success": bool(result.get("success")), "state": final.state.value,
            "task_s": (final.ended_ns - final.started_ns) / 1e9, "wall_with_stack_s": wall, "steps": len(steps),
            "model_calls": final.model_calls, "speculations": final.speculations,
            "speculations_used": final.speculations_used,
            "speculative_steps": sum(1 for s in steps if s.speculative),
            "model_wait_p50_s": statistics.median(waits) if waits else None,
            "model_wait_sum_s": sum(waits)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=2, help="runs with speculation off and as many on, alternating")
    ap.add_argument("--latency", type=float, default=1.0, help="the stand-in model's answer time, seconds")
    ap.add_argument("--realism", default="ideal", choices=("ideal", "realistic", "harsh"))
    add_json_option(ap)
    args = ap.parse_args()
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="aermani-spec-") as tmp:
        for i in range(args.runs):
            for speculate in (False, True):
                r = one_run(speculate, args.latency, args.realism, Path(tmp) / f"run{i}-{int(speculate)}")
                runs.append(r)
                print(f"[{len(runs)}/{2 * args.runs}] speculation {'on ' if speculate else 'off'}: {r['state']}, "
                      f"judge {'ok' if r['success'] else 'FAIL'}, task {r['task_s']:.1f} s, {r['steps']} steps, "
                      f"{r['model_calls']} model calls, speculations used {r['speculations_used']}/"
                      f"{r['speculations']}, model wait p50 {r['model_wait_p50_s']:.2f} s "
                      f"(sum {r['model_wait_sum_s']:.1f} s)", flush=True)
    figures: dict[str, Any] = {"runs": runs}
    for speculate, name in ((False, "off"), (True, "on")):
        rs = [r for r in runs if r["speculate"] is speculate]
        figures[name] = {k: statistics.mean(r[k] for r in rs) for k in
                         ("task_s", "steps", "model_calls", "speculations", "speculations_used", "model_wait_sum_s")}
        figures[name]["successes"] = sum(r["success"] for r in rs)
    off, on = figures["off"], figures["on"]
    figures["saved_s"] = off["task_s"] - on["task_s"]
    figures["saved_ratio"] = figures["saved_s"] / off["task_s"] if off["task_s"] else None
    figures["use_rate"] = on["speculations_used"] / on["speculations"] if on["speculations"] else None
    figures["use_rate_pct"] = 100 * figures["use_rate"] if figures["use_rate"] is not None else None
    figures["used_per_step"] = on["speculations_used"] / on["steps"] if on["steps"] else None
    print(f"\nmodel: local stand-in answering after {args.latency:.1f} s (rules answers read from the prompt); "
          f"world: {args.realism}, speed factor 1; {args.runs} run(s) each")
    print(f"task time  off {off['task_s']:.1f} s   on {on['task_s']:.1f} s   saved {figures['saved_s']:.1f} s "
          f"({100 * (figures['saved_ratio'] or 0):.0f} %)")
    print(f"model wait per task  off {off['model_wait_sum_s']:.1f} s   on {on['model_wait_sum_s']:.1f} s")
    if figures["use_rate"] is not None:
        print(f"speculations used {on['speculations_used']:.1f} of {on['speculations']:.1f} asked per task "
              f"({100 * figures['use_rate']:.0f} %); steps decided speculatively "
              f"{100 * (figures['used_per_step'] or 0):.0f} %; discarded (extra model calls) per task "
              f"{on['speculations'] - on['speculations_used']:.1f}")
    write_json(args.json, "speculation", figures, args)


if __name__ == "__main__":
    main()
