"""`aermani diff` and the grounding check on real logs: two runs of the real reasoner process recorded by the real
recorder, one with the rules policy, one with the local model server answering deliberately wrong descriptions
(a green bottle nobody detected at step 1, a red cup held while the gripper is empty at step 2) and a different
skill at step 3."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import numpy as np
import pytest

from aermani.evaluation.diff import diff_runs
from aermani.evaluation.records import RESULTS_FILE, EpisodeRecord
from aermani.evaluation.report import write_report
from aermani.evaluation.runs import load_run
from aermani.evaluation.tasks import EvalTask
from shared.bus import query_ready
from shared.mcaplog import reasoning_steps
from shared.messages import TaskRequest, TaskState, TaskStatus
from shared.sensors import color_message
from shared.tasks import recorded_end
from tests.helpers import bus_for, run_stack
from tests.reasoner.fake_vlm import FakeVLMServer
from tests.reasoner.fake_world import MiniWorld, Thing, serve_executor
from tests.recorder.samples import K
from tests.recorder.test_recording import aermani

pytestmark = pytest.mark.integration

CMD = "Pick up the red cup and place it on the table"
RULES = ["obj_localization", "grasp", "placement_localization", "place", "done"]
WRONG = ["obj_localization", "grasp", "yaw_left", "placement_localization", "place", "done"]


async def camera(bus) -> None:
    rgb = np.zeros((60, 80, 3), dtype=np.uint8)
    while True:
        bus.publish(K.camera_color, color_message(rgb, time.time_ns()))
        await asyncio.sleep(0.1)


async def record_task(stack) -> TaskStatus:
    # the table is in view from every heading, so a turn does not lose it
    world = MiniWorld([Thing("red cup"), Thing("table", "surface", headings=tuple(range(8)), size=(1.2, 0.8, 0.75))])
    async with bus_for(stack) as bus:
        health = bus.subscribe(K.health("recorder"), maxsize=10)
        await health.recv(timeout=60)  # the recorder is subscribed
        ticker = await serve_executor(bus, world, K, skill_delay=0.2)
        cam = asyncio.create_task(camera(bus))
        statuses = bus.subscribe(K.task_status, maxsize=100)
        try:
            await asyncio.sleep(0.5)
            accept = await query_ready(bus, K.start_task, TaskRequest(command=CMD), timeout=10)
            assert accept.accepted, accept.reason
            while True:
                st = await statuses.recv(timeout=120)
                if st.state.terminal:
                    break
            _path, ended = await recorded_end(health, st.task_id, st.steps, timeout=30)
            assert ended, "the recorder never took the task's end"
            return st
        finally:
            ticker.cancel()
            cam.cancel()


async def record(tmp_path: Path, name: str, env: dict[str, str]) -> Path:
    out = tmp_path / name
    env = {**env, "AERMANI_RECORDER_OUT_DIR": str(out / "rec"), "AERMANI_RECORDER_HEALTH_PERIOD_S": "0.5"}
    with run_stack(["reasoner", "recorder"], out, env=env) as stack:
        final = await record_task(stack)
    assert final.state is TaskState.SUCCEEDED, final.message
    [log] = sorted((out / "rec").glob("*.mcap"))
    return log


def evaluation_dir(tmp_path: Path, name: str, log: Path, backend: str) -> Path:
    """An evaluation directory holding the logged task as its one episode (the steps as the harness keeps them)."""
    steps = reasoning_steps(log)
    rec = EpisodeRecord(episode_id=f"{backend}/full/localization/000-s1", suite="localization", backend=backend,
                        variant="full", task=EvalTask(command=CMD, suite="localization", target_object="red cup",
                                                      destination="table"),
                        seed=1, task_id=steps[0].task_id, state="succeeded", success=True, steps=steps)
    out = tmp_path / name
    out.mkdir()
    (out / RESULTS_FILE).write_text(rec.model_dump_json() + "\n")
    return out


async def test_diff_and_grounding_on_two_recorded_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rules_log = await record(tmp_path, "rules", {"AERMANI_REASONER_BACKEND": "rules"})
    with FakeVLMServer() as vlm:
        vlm.faults.extend(["phantom_object", "phantom_hold", "detour"])
        wrong_log = await record(tmp_path, "vlm", {
            "AERMANI_REASONER_BACKEND": "openai", "AERMANI_REASONER_API_KEY": "none",
            "AERMANI_REASONER_MODEL": "fake-vlm", "AERMANI_REASONER_BASE_URL": vlm.openai_base_url})

    # The grounding check flags exactly the two deliberately wrong steps, each for what it got wrong.
    [rules_task] = load_run(rules_log).tasks
    [wrong_task] = load_run(wrong_log).tasks
    assert [s.step.ste.skill for s in rules_task.steps] == RULES
    assert [s.step.ste.skill for s in wrong_task.steps] == WRONG
    assert all(s.grounding.checked for s in rules_task.steps + wrong_task.steps)
    assert [s.step.step for s in rules_task.steps if s.grounding.violated] == []
    flagged = {s.step.step: [v.kind for v in s.grounding.violations] for s in wrong_task.steps
               if s.grounding.violated}
    assert flagged == {1: ["not_detected"], 2: ["holds_nothing", "holds_nothing"]}, flagged
    assert "'green bottle'" in wrong_task.steps[0].grounding.violations[0].reason
    # the check had something to say of every step: the rules' own words are statements too
    assert all(s.grounding.claims > 0 for s in rules_task.steps)

    # `aermani diff`: the divergence at step 3 (skill), every differing step after it, the flags.
    res = diff_runs(str(rules_log), str(wrong_log))
    [t] = res.tasks
    assert t.first_divergence == 3
    assert [(p.step, p.differs, p.why) for p in t.steps] == [
        (1, False, ""), (2, False, ""), (3, True, "skill"), (4, True, "skill"), (5, True, "skill"),
        (6, True, "only in B")]
    out = aermani("diff", str(rules_log), str(wrong_log), "--json")
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    [task] = doc["tasks"]
    assert task["first_divergence"] == 3 and task["b"]["grounding_flagged_steps"] == [1, 2]
    assert [s["step"] for s in task["steps"] if s["divergence"]] == [3]
    assert task["steps"][0]["a"]["observation"]["detections"] == ["red cup", "table"]
    # every observation rebuilt from the log reproduces the History text the policy was shown
    assert all(s[side]["observation"]["verified"] for s in task["steps"] for side in "ab" if s[side])
    assert task["steps"][2]["b"]["skill"] == "yaw_left" and task["steps"][2]["a"]["outcome"] == "succeeded"
    monkeypatch.setenv("COLUMNS", "200")  # the table's cells wide enough to find a reason on one line
    text = aermani("diff", str(rules_log), str(wrong_log))
    assert text.returncode == 0, text.stderr
    assert "DIVERGES (skill)" in text.stdout and "first divergence at step 3" in text.stdout
    assert "grounding flags: A steps none, B steps [1, 2]" in text.stdout
    assert "! grounding (image_description): says it sees 'green bottle'" in text.stdout
    assert text.stdout.count("! grounding (") == 3

    # The same runs as evaluation directories: measurements read from the prompts, the same flags, and the
    # report's GVR column per method.
    rules_dir = evaluation_dir(tmp_path, "eval-rules", rules_log, "rules")
    wrong_dir = evaluation_dir(tmp_path, "eval-vlm", wrong_log, "openai:fake-vlm")
    [wrong_eval] = load_run(wrong_dir).tasks
    assert {s.step.step: [v.kind for v in s.grounding.violations] for s in wrong_eval.steps
            if s.grounding.violated} == flagged
    out = aermani("diff", str(rules_dir), str(wrong_dir), "--json")
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["tasks"][0]["first_divergence"] == 3
    write_report(rules_dir)
    write_report(wrong_dir)
    assert "| 0.0 (0/5) |" in (rules_dir / "report.md").read_text()
    report = (wrong_dir / "report.md").read_text()
    assert "GVR ↓" in report and "| 33.3 (2/6) |" in report and "## Grounding flags" in report
    episode = json.loads((wrong_dir / "report.json").read_text())["episodes"][0]
    assert [f["step"] for f in episode["grounding"]["flagged"]] == [1, 2]


def test_diff_says_what_is_wrong_with_its_inputs(tmp_path: Path) -> None:
    missing = aermani("diff", str(tmp_path / "nope.mcap"), str(tmp_path / "nope2.mcap"))
    assert missing.returncode == 2 and "no such file or directory" in missing.stderr
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not a log at all")
    bad = aermani("diff", str(junk), str(junk))
    assert bad.returncode == 2 and "is not an MCAP log" in bad.stderr
    empty = tmp_path / "eval"
    empty.mkdir()
    no_eval = aermani("diff", str(empty), str(empty))
    assert no_eval.returncode == 2 and "no episodes.jsonl" in no_eval.stderr
