"""The evaluation on the real stack: services as processes, the simulator as the world, rules backend."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from aermani.evaluation.records import RESULTS_FILE, ResultsFile
from aermani.evaluation.runner import PER_VEHICLE_SERVICES, RunConfig, run, vehicle_env
from aermani.launcher import Stack, free_port

pytestmark = pytest.mark.integration

# Short T_max and a faster simulator keep CI short; the verdicts are still the simulator's ground truth.
FAST = {"speed_factor": 4.0, "t_max_s": 240.0, "progress": False, "extra_env": {"AERMANI_SIM_FPS": "5"}}
TERMINAL = {"succeeded", "failed", "aborted", "timeout"}


def _check_episode(rec) -> None:
    assert not rec.harness_error, rec.harness_error
    assert rec.state in TERMINAL
    assert rec.status is not None and rec.status.task_id == rec.task_id
    assert rec.steps, "no reasoning step recorded"
    assert [s.step for s in rec.steps] == sorted(s.step for s in rec.steps)
    assert len(rec.steps) == rec.status.steps
    assert rec.judge is not None and rec.verdict and rec.judge_success is not None
    # success is the task's own end state AND the simulator's ground truth (AND the motions the task asks for, from
    # the trajectory), never the reasoner's claim alone
    assert rec.success == (rec.state == "succeeded" and rec.judge_success and rec.motions_ok is not False)
    # every verdict says why: its reason and each check with the measured number, by the task's criteria
    assert rec.judge.checks and rec.judge.scenario is not None
    assert rec.judge.scenario.criteria == rec.task.criteria
    if rec.judge_success:
        assert rec.judge.ok and all(c.ok for c in rec.judge.checks), rec.judge
        assert rec.task.destination or rec.held in rec.task.accepted


def test_each_episode_is_scored_for_what_it_asks_on_the_real_stack(tmp_path):
    """A sequential line with its motions and a size comparison (issue 26): the runner reads the simulator's world
    and clock before and after the task, checks the motions from the recorded trajectory and records the
    simulator's decision of the choice; the report lists both, with TT in simulated seconds."""
    from aermani.evaluation.tasks import load_suites

    suites = load_suites(["sequential", "clutter"], split="dev")
    go_up = next(t for t in suites["sequential"] if t.command.startswith("Go up a bit, then forward once"))
    larger = next(t for t in suites["clutter"] if t.command == "Of the two boxes, pick up the larger one.")
    tasks = tmp_path / "tasks.jsonl"
    # the pick first: done, it ends with a box in the fingers, and the next episode starts from that used vehicle
    tasks.write_text("".join(t.model_copy(update={"seed": 7}).model_dump_json(exclude_defaults=False) + "\n"
                             for t in (larger, go_up)))
    summary = run(RunConfig(out=tmp_path / "eval", tasks_file=tasks, **FAST))
    assert summary.ran == 2
    recs = {r.task.command: r for r in ResultsFile(tmp_path / "eval" / RESULTS_FILE).load()}
    for rec in recs.values():
        _check_episode(rec)
        assert rec.sim_started_s is not None and rec.sim_ended_s is not None and rec.sim_duration_s
        assert rec.sim_duration_s > 1.0
    up = recs[go_up.command]
    assert up.motions_ok is not None and up.motions_detail, up
    assert up.motions_ok == ("up x1: step" in up.motions_detail), up.motions_detail
    if up.state == "succeeded" and up.judge_success:
        assert up.success == up.motions_ok
    box = recs[larger.command]
    assert box.choice is not None and box.choice.answer == ("cardboard box",), box.choice
    assert "cardboard box 5.28 L, cracker box 2.35 L" in box.choice.reason
    assert box.choice.informed is not None
    if box.held == "cracker box":
        assert not box.success  # only the simulator's answer counts
    md = (tmp_path / "eval" / "report.md").read_text()
    assert "## Motion checks" in md and "## Size and conditional tasks" in md and "TT sim (s)" in md
    print(up.motions_detail, box.choice, sep="\n")


def test_two_suites_on_parallel_vehicles_with_no_cross_talk(tmp_path):
    """Two suites, one episode each, on two vehicles at once; the report names the run. (One vehicle running
    episodes one after another, the second from the vehicle the first pick left, is the scored test.)"""
    cfg = RunConfig(out=tmp_path, suites=["localization", "clutter"], episodes=1, parallel=2, **FAST)
    summary = run(cfg)
    assert (summary.planned, summary.ran, summary.skipped) == (2, 2, 0)
    recs = ResultsFile(tmp_path / RESULTS_FILE).load()
    assert sorted(r.suite for r in recs) == ["clutter", "localization"]
    assert {r.vehicle_id for r in recs} == {"ev1", "ev2"}
    assert len({r.task_id for r in recs}) == 2
    for rec in recs:
        _check_episode(rec)
        assert rec.foreign_samples == 0
        assert rec.status.vehicle_id == rec.vehicle_id
        for s in rec.steps:
            assert (s.vehicle_id, s.task_id) == (rec.vehicle_id, rec.task_id)
    md = (tmp_path / "report.md").read_text()
    assert "| Localization | rules (non-VLM baseline) | 1 |" in md
    assert "| Pick from Clutter | rules (non-VLM baseline) | 1 |" in md
    assert "not a VLM" in md and "AERMANI-VLM (rules)" not in md
    assert f"`{cfg.command_line()}`" in md and "| split | `dev` |" in md
    doc = json.loads((tmp_path / "report.json").read_text())
    assert len(doc["episodes"]) == 2 and doc["episodes"][0]["steps"]
    assert (tmp_path / "plots" / "steps_per_episode.png").exists()


def test_interrupted_run_resumes_without_rerunning_finished_episodes(tmp_path):
    # What is tested is the bookkeeping across a Ctrl-C, not the flight: a short T_max ends each episode as a
    # timeout (a verdict like any other) in about 15 s of wall time instead of a whole pick and place.
    t_max = 60.0
    out = tmp_path / "eval"
    args = [sys.executable, "-m", "aermani.cli", "eval", "--suites", "localization", "--episodes", "2",
            "--out", str(out), "--speed-factor", "4", "--t-max", f"{t_max:g}", "--no-progress"]
    env = {**os.environ, "AERMANI_SIM_FPS": "5"}
    proc = subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            cwd=Path(__file__).resolve().parents[2])
    results = ResultsFile(out / RESULTS_FILE)
    try:
        deadline = time.monotonic() + 400
        while not results.finished_ids():
            assert proc.poll() is None, proc.stdout.read().decode(errors="replace")
            assert time.monotonic() < deadline, "no episode finished"
            time.sleep(0.5)
        proc.send_signal(signal.SIGINT)  # Ctrl-C while the second episode runs
        proc.wait(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    first = results.load()
    assert len(first) == 1
    first_id = first[0].episode_id
    first_line = (out / RESULTS_FILE).read_text().splitlines()[0]

    summary = run(RunConfig(out=out, suites=["localization"], episodes=2, **{**FAST, "t_max_s": t_max}))
    assert (summary.planned, summary.skipped, summary.ran) == (2, 1, 1)
    assert first_id not in {r.episode_id for r in summary.records}
    lines = (out / RESULTS_FILE).read_text().splitlines()
    assert lines[0] == first_line and sum(first_id in ln for ln in lines) == 1
    assert len(results.load()) == 2


def test_episodes_spread_over_vehicles_behind_two_linked_routers(tmp_path):
    """`aermani eval --connect` on two hosts' worth of vehicles: ev1 behind router A, ev2 behind router B, B
    linked to A (as a vehicle host's router joins the ground's); the harness connects to A only."""
    cfg = RunConfig(out=tmp_path / "eval", suites=["clutter"], episodes=2, **FAST)
    a = Stack(PER_VEHICLE_SERVICES, vehicle_id="ev1", env=vehicle_env(cfg), log_dir=tmp_path / "logs-a")
    b = Stack(PER_VEHICLE_SERVICES, vehicle_id="ev2", env=vehicle_env(cfg), log_dir=tmp_path / "logs-b",
              port=free_port(), link=[a.endpoint])
    try:
        a.start(wait=False)
        b.start(wait=True, timeout=240)
        a.wait_alive(timeout=240)
        # router A sees ev2's services through the link
        assert {("ev2", n) for n in PER_VEHICLE_SERVICES} <= a.alive()
        summary = run(cfg.model_copy(update={"connect": a.endpoint, "vehicles": ["ev1", "ev2"]}))
    except BaseException:
        for p in (*a.procs, *b.procs):
            print(f"--- log of {p.label} ---\n{p.tail(30)}")
        raise
    finally:
        b.stop()
        a.stop()
    assert (summary.planned, summary.ran) == (2, 2)
    recs = ResultsFile(cfg.out / RESULTS_FILE).load()
    assert {r.vehicle_id for r in recs} == {"ev1", "ev2"}
    assert len({r.task_id for r in recs}) == 2
    for rec in recs:
        _check_episode(rec)
        assert rec.foreign_samples == 0 and rec.status.vehicle_id == rec.vehicle_id
    run_config = json.loads((cfg.out / "run_config.json").read_text())
    assert f"--connect {a.endpoint} --vehicles ev1,ev2" in run_config["command"]
