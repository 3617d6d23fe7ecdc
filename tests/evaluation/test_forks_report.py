"""`aermani eval --fork-from`'s bookkeeping (fast): which noise each fork draws, the per-method success with its
interval, the resume file read back, and the report's plot (the forks themselves: tests/evaluation/test_fork.py)."""

from __future__ import annotations

import json
from dataclasses import asdict

from aermani.evaluation.forks import FORKS_FILE, ForkRow, counted, noise_seed, plot, read_rows, summary


def row(method: str, fork: int, success: bool, skills: list[str], steps: int = 3) -> ForkRow:
    return ForkRow(method=method, backend="rules", variant={"A": "full", "B": "no_drt"}[method], model="", fork=fork,
                   noise_seed=noise_seed(fork),
                   state="succeeded" if success else "failed", success=success, verdict="v", steps=steps,
                   skills=skills, task_s=10.0 * fork)


def test_fork_one_keeps_the_recorded_noise_and_the_others_draw_from_their_seed() -> None:
    assert [noise_seed(n) for n in (1, 2, 5)] == [None, 1, 4]


def test_summary_per_method_with_wilson_intervals_and_first_decisions(tmp_path) -> None:
    rows = [row("A", 1, True, ["forward", "grasp"]), row("A", 2, False, ["yaw_left"]), row("A", 3, True, ["forward"]),
            row("B", 1, False, ["land"], steps=1)]
    with (tmp_path / FORKS_FILE).open("w") as f:
        for r in rows:
            f.write(json.dumps(asdict(r)) + "\n")
    back = read_rows(tmp_path)
    assert back == rows
    a, b = summary(back)
    assert (a["method"], a["forks"], a["successes"]) == ("A", 3, 2) and abs(a["sr"] - 200 / 3) < 1e-9
    assert a["sr_ci"][0] < a["sr"] < a["sr_ci"][1] and a["first_skills"] == ["forward", "yaw_left"]
    assert a["endings"] == ["failed", "succeeded"] and a["mean_task_s"] == 20.0
    assert (b["successes"], b["sr"], b["sr_ci"][0]) == (0, 0.0, 0.0) and b["mean_steps"] == 1.0
    assert plot(back, tmp_path, "title") == ["plots/forks_sr.png"] and (tmp_path / "plots" / "forks_sr.png").is_file()
    assert read_rows(tmp_path / "nothing-here") == []
    # A fork whose stack never reached an end is not the policy's failure: not counted, run again on a rerun (its
    # newer row then counts).
    broken = ForkRow(method="B", backend="rules", variant="no_drt", model="", fork=2, noise_seed=1, state="error",
                     success=False, verdict="no verdict", steps=0)
    assert broken.harness_error and counted([*rows, broken]) == rows
    again = row("B", 2, True, ["forward"])
    assert summary([*rows, broken, again])[1]["forks"] == 2 and summary([*rows, broken, again])[1]["successes"] == 1
