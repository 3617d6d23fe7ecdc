"""Wall time of a 12-episode evaluation sweep on one simulated vehicle versus three on one router.

Runs the same 12 episodes (rules backend, 3 per suite) with --parallel 1 and --parallel 3 in fresh output
directories, prints both wall times (stack start-up included, as a user would see it) and the ratio.
Never gates anything on the figures: the machine is shared and timings vary.

    .venv/bin/python benchmarks/eval_parallel.py [--episodes-per-suite 3] [--speed-factor 4]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from aermani.evaluation.metrics import compute  # noqa: E402
from aermani.evaluation.runner import RunConfig, run  # noqa: E402
from benchmarks._figures import add_json_option, write_json  # noqa: E402


def sweep(parallel: int, episodes: int, speed: float, root: Path) -> tuple[float, int, int]:
    out = root / f"parallel{parallel}"
    t0 = time.monotonic()
    summary = run(RunConfig(out=out, backend="rules", episodes=episodes, parallel=parallel, speed_factor=speed,
                            progress=False, extra_env={"AERMANI_SIM_FPS": "5"}))
    wall = time.monotonic() - t0
    m = compute(summary.records)
    return wall, summary.ran, m.successes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes-per-suite", type=int, default=3, help="episodes per suite (4 suites)")
    ap.add_argument("--speed-factor", type=float, default=4.0)
    ap.add_argument("--keep", type=Path, default=None, help="keep the runs (reports, logs) in this directory")
    add_json_option(ap)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="aermani-evalbench-") as tmp:
        root = args.keep or Path(tmp)
        n = 4 * args.episodes_per_suite
        print(f"{n}-episode sweep (rules backend, speed factor {args.speed_factor})")
        w1, ran1, ok1 = sweep(1, args.episodes_per_suite, args.speed_factor, root)
        print(f"  --parallel 1: {w1:7.1f} s wall  ({ran1} episodes, {ok1} successful)")
        w3, ran3, ok3 = sweep(3, args.episodes_per_suite, args.speed_factor, root)
        print(f"  --parallel 3: {w3:7.1f} s wall  ({ran3} episodes, {ok3} successful)")
        print(f"  speed-up parallel 3 vs 1: {w1 / w3:.2f}x (wall-time ratio parallel1/parallel3)")
    write_json(args.json, "eval_parallel", {"episodes": n, "wall_parallel1_s": w1, "wall_parallel3_s": w3,
                                            "speedup": w1 / w3, "ok_parallel1": ok1, "ok_parallel3": ok3,
                                            "ran_parallel1": ran1, "ran_parallel3": ran3}, args)


if __name__ == "__main__":
    main()
