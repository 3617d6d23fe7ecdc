"""`aermani eval` with the paper's Table III baseline frameworks (saycan, direct, waypoint, plan-once) on the real
stack through the local OpenAI-compatible stand-in: each variant's episodes run and the report names them. The
stand-in answers with the rules policy's decisions: nothing here is a result."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from aermani.evaluation.records import RESULTS_FILE, EpisodeRecord, ResultsFile
from aermani.evaluation.report import framework_lines
from aermani.evaluation.runner import RunConfig, vehicle_env
from aermani.evaluation.tasks import EvalTask
from shared.messages import BASELINES
from tests.reasoner.fake_vlm import FakeVLMServer

TITLES = {"saycan": "SayCan-style", "direct": "RT-2-style direct action", "waypoint": "UAV-VLN-style waypoints",
          "plan_once": "UAV-VLA-style plan once"}


@pytest.mark.integration
@pytest.mark.slow
def test_eval_runs_every_baseline_framework_against_the_test_server(tmp_path) -> None:
    with FakeVLMServer() as vlm:
        env = {**os.environ, "AERMANI_REASONER_API_KEY": "none", "AERMANI_SIM_FPS": "5"}
        res = subprocess.run([sys.executable, "-m", "aermani.cli", "eval", "--backend", "openai", "--model", "fake-vlm",
                              "--base-url", vlm.openai_base_url, "--variant", "saycan,direct,waypoint,plan-once",
                              "--suites", "localization", "--episodes", "1", "--t-max", "240", "--speed-factor", "4",
                              "--no-progress", "--out", str(tmp_path)], capture_output=True, text=True, env=env,
                             timeout=1500)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    recs = {r.variant: r for r in ResultsFile(tmp_path / RESULTS_FILE).load()}
    assert set(recs) == set(BASELINES)
    for variant, rec in recs.items():
        assert not rec.harness_error and rec.steps, (variant, rec.message)
        assert all(s.variant == variant for s in rec.steps)
    assert all(s.scores for s in recs["saycan"].steps)
    assert recs["plan_once"].steps[0].plan and sum(len(s.calls) for s in recs["plan_once"].steps) == 1
    assert all(s.ste is None or s.ste.skill in ("yaw_left", "yaw_right", "forward", "backward", "left", "right",
                                                "up", "down", "done") for s in recs["waypoint"].steps)
    md = (tmp_path / "report.md").read_text()
    for variant, title in TITLES.items():
        assert f"{title} (openai" in md and f"`{variant}`" in md
    assert "not put beside the paper" in md and "the numbers reflect the test server" in md
    cfg = json.loads((tmp_path / "run_config.json").read_text())
    assert cfg["variants"] == ["saycan", "direct", "waypoint", "plan_once"]
    assert vlm.schema_errors == []


def test_rules_backend_is_refused_for_a_baseline_before_anything_starts(tmp_path) -> None:
    res = subprocess.run([sys.executable, "-m", "aermani.cli", "eval", "--variant", "plan-once", "--out",
                          str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "does not emulate" in res.stdout + res.stderr
    assert not (tmp_path / RESULTS_FILE).exists()


def test_paper_prompt_settings_reach_the_reasoner_and_the_command_line(tmp_path) -> None:
    cfg = RunConfig(out=tmp_path, backend="openai", variants=["react"], paper_history=True, free_text_baselines=True)
    env = vehicle_env(cfg)
    assert env["AERMANI_REASONER_PAPER_HISTORY"] == "true" == env["AERMANI_REASONER_FREE_TEXT_BASELINES"]
    assert "--paper-history --free-text-baselines" in cfg.command_line()
    off = vehicle_env(RunConfig(out=tmp_path))
    assert off["AERMANI_REASONER_PAPER_HISTORY"] == "false" == off["AERMANI_REASONER_FREE_TEXT_BASELINES"]
    assert "--paper-history" not in RunConfig(out=tmp_path).command_line()


def test_framework_rows_put_only_a_remote_model_beside_the_paper() -> None:
    task = EvalTask(command="pick up the red cup", suite="localization", target_object="red cup")
    rec = EpisodeRecord(episode_id="openai/saycan/localization/000-s0", backend="openai:gpt-4o", variant="saycan",
                        suite="localization", task=task, seed=0, state="succeeded", success=True)
    remote = "\n".join(framework_lines([rec], "gpt-4o", "https://api.openai.com/v1"))
    assert "| SayCan | `saycan` | 20.0 |" in remote and "(gpt-4o, N=1)" in remote
    assert remote.count("not run here") == 4  # the other four frameworks
    local = "\n".join(framework_lines([rec], "fake-vlm", "http://127.0.0.1:5000/v1"))
    assert "not put beside the paper" in local and "SR 100.0" in remote and "SR 100.0" not in local
