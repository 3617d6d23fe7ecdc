"""Suites parse, user task files validate, episodes expand deterministically, the report renders."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from aermani.evaluation.records import EpisodeRecord, ResultsFile
from aermani.evaluation.report import backend_note, write_report
from aermani.evaluation.runner import RunConfig, episode_specs
from aermani.evaluation.tasks import PAPER_SUITES, derive_seed, expand, load_jsonl, load_suites
from services.sim.layout import OBJECTS, SURFACES
from shared.errors import ConfigError
from shared.messages import JudgeCriteria, ModelCall, ReasoningStep, SkillState, SkillToExecute


def test_builtin_suites_parse_and_name_only_things_the_simulator_has():
    suites = load_suites(split=None)
    assert list(suites) == list(PAPER_SUITES)
    for name, tasks in suites.items():
        assert tasks, name
        for t in tasks:
            assert t.suite == name
            for obj in (*t.accepted, *(t.distractors or ()), *t.extra_objects):
                assert obj in OBJECTS, (name, t.command, obj)
            assert t.destination is None or t.destination in SURFACES, (name, t.destination)
            for obj, surface in (t.placements or {}).items():
                assert obj in OBJECTS and surface in SURFACES, (name, t.command, obj, surface)
                assert t.scenario(1).placements == t.placements
    assert all(t.target_out_of_view for t in suites["search"] if t.expect == "success")  # not_found: no target
    # The conditional's outcome is decided by the layout: the orange (or, otherwise, the banana) is on the counter.
    counter = [t for t in suites["sequential"] if "If you see an orange" in t.command]
    assert {t.target_object for t in counter} == {"orange", "banana"}
    assert all(t.placements == {t.target_object: "counter"} for t in counter)
    assert all("orange" not in (*t.extra_objects, *(t.distractors or ()))
               for t in counter if t.target_object == "banana")
    commands = {t.command for ts in suites.values() for t in ts}
    # the paper's Table I commands are all there
    for c in ("Pick up the red cup and place it on the table.", "Of the two boxes, pick up the larger one.",
              "Ignore the tools and pick up the green bottle.", "Move forward twice, turn right, and pick up the "
              "tissue box.", "Find the purple cup and place it on the round table.",
              "Locate the cardboard box and bring it to the sink."):
        assert c in commands


def _norm(command: str) -> str:
    return " ".join("".join(ch for ch in command.lower() if ch.isalnum() or ch.isspace()).split())


def test_splits_have_ten_distinct_commands_per_suite_and_share_none():
    dev, test = load_suites(split="dev"), load_suites(split="test")
    assert list(dev) == list(test) == list(PAPER_SUITES)
    for suite in PAPER_SUITES:
        d = {_norm(t.command) for t in dev[suite]}
        t = {_norm(x.command) for x in test[suite]}
        assert len(d) >= 10 and len(t) >= 10, suite
        assert not d & t, (suite, d & t)
        assert {x.split for x in dev[suite]} == {"dev"} and {x.split for x in test[suite]} == {"test"}
    # the paper's templates are dev commands: the project was built against them
    assert any(x.command == "Pick up the red cup and place it on the table." for x in dev["localization"])
    with pytest.raises(ConfigError, match="unknown split"):
        load_suites(split="val")


def test_split_seeds_come_from_disjoint_ranges():
    dev = expand(load_suites(split="dev"), episodes=10, backends=["rules"], variants=["full"])
    test = expand(load_suites(split="test"), episodes=10, backends=["rules"], variants=["full"])
    assert len(dev) == len(test) == 40
    dev_seeds, test_seeds = {s.seed for s in dev}, {s.seed for s in test}
    assert len(dev_seeds) == len(test_seeds) == 40  # 10 layouts per suite, none shared between suites
    assert max(dev_seeds) < 2**30 <= min(test_seeds) and max(test_seeds) < 2**31
    assert all(derive_seed(b, "search", i, "dev") < 2**30 <= derive_seed(b, "search", i, "test")
               for b in range(3) for i in range(50))
    # 10 episodes of a suite are 10 distinct tasks (a conditional command has one task line per branch)
    assert all(len({s.task.model_dump_json() for s in dev if s.task.suite == suite}) == 10 for suite in PAPER_SUITES)


def test_run_config_names_the_split_and_the_command_that_reproduces_it(tmp_path):
    cfg = RunConfig(out=tmp_path / "ev", split="test", episodes=3, suites=["search"])
    specs = episode_specs(cfg)
    assert len(specs) == 3 and {s.task.split for s in specs} == {"test"}
    line = cfg.command_line()
    assert line.startswith("aermani eval --split test --backend rules --variant full ")
    assert "--segmenter color --realism realistic --speed-factor 4 " in line and "--suites search" in line
    import inspect

    from aermani.evaluation.cli import eval_command  # the line's options are the CLI's own
    params = set(inspect.signature(eval_command).parameters)
    opts = [a[2:].replace("-", "_") for a in line.split() if a.startswith("--")]
    assert set(opts) <= params | {"t_max"}, set(opts) - params


def test_user_task_file(tmp_path):
    f = tmp_path / "mine.jsonl"
    f.write_text("# my tasks\n"
                 + json.dumps({"command": "Pick up the apple and place it on the shelf.", "suite": "fruit",
                               "target_object": "apple", "destination": "shelf", "seed": 7}) + "\n\n"
                 + json.dumps({"command": "Grab the banana.", "suite": "fruit", "target_object": "banana",
                               "destination": None, "seed": 8}) + "\n")
    tasks = load_jsonl(f)
    assert [t.seed for t in tasks] == [7, 8]
    specs = episode_specs(RunConfig(tasks_file=f, episodes=None))
    assert [(s.task.suite, s.seed) for s in specs] == [("fruit", 7), ("fruit", 8)]
    assert specs[0].task.scenario(specs[0].seed).destination == "shelf"


def test_the_judges_criteria_are_the_tasks_and_travel_with_its_scenario(tmp_path):
    """A task line's own criteria (or the defaults when it says none) are laid out with its scenario at reset;
    nothing run-wide (no RunConfig field, no option on the command line) can set them."""
    f = tmp_path / "strict.jsonl"
    f.write_text(json.dumps({"command": "Put the red cup on the table.", "target_object": "red cup",
                             "destination": "table", "criteria": {"rest_s": 5.0, "upright_tolerance_deg": 10}})
                 + "\n" + json.dumps({"command": "Grab the banana.", "target_object": "banana"}) + "\n")
    strict, plain = load_jsonl(f)
    assert strict.scenario(3).criteria == JudgeCriteria(rest_s=5.0, upright_tolerance_deg=10.0)
    assert plain.scenario(3).criteria == JudgeCriteria()
    c = JudgeCriteria()
    assert (c.lift_m, c.hold_s, c.rest_s, c.upright_tolerance_deg, c.top_tolerance_m) == (0.03, 1.0, 2.0, 20.0, 0.02)
    f.write_text(json.dumps({"command": "x", "target_object": "apple", "criteria": {"rest_s": -1}}) + "\n")
    with pytest.raises(ConfigError, match=r"strict.jsonl:1"):
        load_jsonl(f)
    assert "tolerance" not in RunConfig.model_fields
    assert "--tolerance" not in RunConfig(out=tmp_path / "ev").command_line()


def test_a_deprecated_tolerance_option_is_ignored_with_a_warning(tmp_path):
    """The option stays so the commands in older reports still run; its value loosens nothing."""
    import typer
    from typer.testing import CliRunner

    from aermani.evaluation.cli import register

    app = typer.Typer()
    app.callback()(lambda: None)
    register(app)
    (tmp_path / "episodes.jsonl").write_text("")
    res = CliRunner().invoke(app, ["eval", "--tolerance", "0.5", "--out", str(tmp_path), "--report-only"])
    assert res.exit_code == 0, res.output
    assert "--tolerance 0.5 is ignored" in " ".join(res.output.split()), res.output


def test_bad_task_file_names_the_line(tmp_path):
    f = tmp_path / "bad.jsonl"
    f.write_text('{"command": "x", "target_object": "apple"}\n{"command": "y"}\n')
    with pytest.raises(ConfigError, match=r"bad.jsonl:2"):
        load_jsonl(f)
    with pytest.raises(ConfigError, match="unknown suites"):
        load_suites(["nope"])


def test_expand_is_deterministic_and_shares_layouts_across_variants():
    suites = load_suites(["localization", "search"])
    a = expand(suites, episodes=4, backends=["rules"], variants=["full", "no_drt"], base_seed=3)
    b = expand(suites, episodes=4, backends=["rules"], variants=["full", "no_drt"], base_seed=3)
    assert [s.episode_id for s in a] == [s.episode_id for s in b]
    assert len(a) == 16 and len({s.episode_id for s in a}) == 16
    full = [s.seed for s in a if s.variant == "full"]
    nodrt = [s.seed for s in a if s.variant == "no_drt"]
    assert full == nodrt
    assert derive_seed(3, "search", 1) != derive_seed(3, "search", 2)


def _rec(eid: str, success: bool, variant: str = "full", backend: str = "openai") -> EpisodeRecord:
    task = load_suites(["localization"])["localization"][0]
    steps = [ReasoningStep(task_id="t", step=1, calls=(ModelCall(raw_answer="{}", valid=True, latency_s=0.2),),
                           ste=SkillToExecute(skill="obj_localization", argument="red cup"), valid=True,
                           skill_state=SkillState.SUCCEEDED)]
    return EpisodeRecord(episode_id=eid, suite="localization", backend=backend, variant=variant, task=task, seed=1,
                         state="succeeded" if success else "failed", success=success, steps=steps,
                         verdict="red cup rests on the table" if success else "red cup is in the gripper")


def test_results_file_resume_and_torn_line(tmp_path):
    rf = ResultsFile(tmp_path / "episodes.jsonl")
    rf.append(_rec("a", True))
    with open(rf.path, "a") as f:
        f.write('{"episode_id": "torn", "suit')  # killed mid-write
    rf.append(_rec("b", False))
    broken = _rec("c", False).model_copy(update={"harness_error": "sim/reset timed out"})
    rf.append(broken)
    assert {r.episode_id for r in rf.load()} == {"a", "b", "c"}
    assert rf.finished_ids() == {"a", "b"}  # the one the harness could not run is retried


def test_report_states_the_backend_and_has_both_tables(tmp_path):
    rf = ResultsFile(tmp_path / "episodes.jsonl")
    for i, v in enumerate(["full", "no_drt", "full"]):
        rf.append(_rec(f"openai/{v}/localization/{i:03d}", success=(i != 1), variant=v))
    cfg = {"backend": "openai", "base_url": "http://127.0.0.1:5555/v1", "model": "fake-vlm", "speed_factor": 4}
    paths = write_report(tmp_path, config=cfg)
    md = paths["markdown"].read_text()
    assert "reflect the test server, not a real VLM" in md
    assert "| Localization | No-DRT (openai) | 1 | 0.0 [0.0, 79.3] |" in md
    assert "| AERMANI-VLM (openai) | 2 | 100.0 [34.2, 100.0] | 0.0 | 1.0 | 0.0 | -- | 0.200 | 0.200 |" in md
    doc = json.loads(paths["json"].read_text())
    assert len(doc["episodes"]) == 3 and doc["metrics"]["openai/full"]["overall"]["sr"] == 100.0
    for png in ("success_by_suite", "rt_histogram", "steps_per_episode"):
        assert (tmp_path / "plots" / f"{png}.png").stat().st_size > 1000
    # rebuilding later from the saved run settings keeps the note
    write_report(tmp_path)
    assert "not a real VLM" in paths["markdown"].read_text()
    assert "not a VLM" in backend_note({"backend": "rules"}, [])


def test_report_states_the_configuration_names_the_rules_baseline_and_lists_every_incident(tmp_path):
    rf = ResultsFile(tmp_path / "episodes.jsonl")
    rf.append(_rec("rules/full/localization/000-s11", True, backend="rules").model_copy(
        update={"seed": 11, "collisions": ("vehicle-shelf",), "judge_success": True}))
    rf.append(_rec("rules/full/localization/001-s12", False, backend="rules").model_copy(
        update={"seed": 12, "attempts": 2, "judge_success": True, "restarts": [
            "attempt 1: failed before the first reasoning step: takeoff failed: no climb"]}))
    rf.append(_rec("rules/full/localization/002-s13", False, backend="rules").model_copy(
        update={"seed": 13, "harness_error": "sim/reset refused the scenario: no room"}))
    cfg = RunConfig(out=tmp_path, split="dev", episodes=3)
    from aermani.evaluation.runner import run_config_of
    doc_cfg = run_config_of(cfg)
    paths = write_report(tmp_path, config=doc_cfg)
    md = paths["markdown"].read_text()
    assert "AERMANI-VLM (rules)" not in md and "| rules (non-VLM baseline) | 2 | 50.0 [9.5, 90.5] |" in md
    # the rules policy calls no model: its RT is not a response time (issue 26)
    assert "| n/a (no model) | n/a (no model) |" in md
    for needle in (f"`{cfg.command_line()}`", f"`{doc_cfg['commit']}`", "segmenter -- real: the colour segmenter",
                   "| simulator realism | `realistic` |", "| speed factor | 4.0 |", "| split | `dev` |",
                   "| seeds | 11, 12, 13 |", "| N (episodes in the metrics / recorded) | 2 / 3 |",
                   "| T_max, judge criteria | 600.0 s, each task's (`criteria` in its scenario",
                   "excluded (left out of the metrics, retried by the next run of the command): "
                   "rules/full/localization/002-s13 on ?: sim/reset refused the scenario: no room",
                   "restarted (2 trials, the last one is in the metrics): rules/full/localization/001-s12",
                   "takeoff failed: no climb",
                   "| rules (non-VLM baseline) | 2 | 1 | 2 | 0 | 1 | 0 | 1 (0.50 per episode) | 1 | 0 | 0 | 0 "
                   "| 1 |",
                   "| AERMANI-VLM (Qwen2-VL) | 77.5 | 4.5 | 22.8 | 8.7 | 0.61 | not run here: needs a GPU/API key |"):
        assert needle in md, needle
    doc = json.loads(paths["json"].read_text())
    assert doc["split"] == "dev" and doc["seeds"] == [11, 12, 13] and doc["n"] == 2
    assert doc["command"] == cfg.command_line() and doc["commit"] == doc_cfg["commit"]
    assert isinstance(doc["dirty"], bool) and doc["segmenter"] == "color" and doc["realism"] == "realistic"
    assert doc["excluded"][0]["reason"].startswith("sim/reset refused")
    assert doc["restarted"][0]["reasons"][0].startswith("attempt 1")
    saved = json.loads((tmp_path / "run_config.json").read_text())
    assert saved["command"] == cfg.command_line() and "dirty" in saved
    # the oracle is named as such
    assert "ORACLE" in backend_note({"backend": "rules", "segmenter": "sim"}, [])


def test_report_puts_a_real_model_run_in_its_paper_row(tmp_path):
    rf = ResultsFile(tmp_path / "episodes.jsonl")
    rf.append(_rec("openai/full/localization/000", True))
    md = write_report(tmp_path, config={"backend": "openai", "model": "Qwen/Qwen2-VL-7B-Instruct",
                                        "base_url": "http://gpu-box:8000/v1"})["markdown"].read_text()
    row = next(x for x in md.splitlines() if x.startswith("| AERMANI-VLM (Qwen2-VL) |"))
    assert "SR 100.0" in row and "Qwen/Qwen2-VL-7B-Instruct, N=1" in row
    # 4 other backbones, then the 5 baseline frameworks (ReAct's row among them, once), none run
    assert "| AERMANI-VLM (GPT-4o) | 85.0 |" in md and md.count("not run here: needs a GPU/API key") == 4 + 5
    assert md.count("| ReAct Prompting (VLM) |") == 1


def test_shell_settings_reach_the_run_config_and_the_report_without_secrets(tmp_path) -> None:
    """Issue 26: every AERMANI_* variable in the shell changes what the services do (or would, but for the run's
    own setting), so the run's record names them all, marks those the run overrides, and states the effective
    values of the settings that shape the numbers as the services' own settings classes read them; a secret's
    value never reaches a file."""
    import os
    from unittest import mock

    from aermani.evaluation.report import _effective_text, _environment_text
    from aermani.evaluation.runner import RunConfig, run_config_of, shell_settings

    env = {"AERMANI_EXECUTOR_MAX_SPEED": "0.8", "AERMANI_REASONER_API_KEY": "sk-secret-value",
           "AERMANI_GATEWAY_TOKEN": "t0k3n", "AERMANI_SIM_SPEED_FACTOR": "9", "AERMANI_SIM_DYNAMICS": "multirotor",
           "AERMANI_REASONER_MAX_STEPS": "55", "HOME": "/root"}
    got = shell_settings(env)
    assert got == {"AERMANI_EXECUTOR_MAX_SPEED": "0.8", "AERMANI_GATEWAY_TOKEN": "(set, not recorded)",
                   "AERMANI_REASONER_API_KEY": "(set, not recorded)", "AERMANI_REASONER_MAX_STEPS": "55",
                   "AERMANI_SIM_DYNAMICS": "multirotor", "AERMANI_SIM_SPEED_FACTOR": "9"}, got
    with mock.patch.dict(os.environ, env):
        doc = run_config_of(RunConfig(out=tmp_path, speed_factor=3.0, segmenter="sim", realism="harsh"))
    assert doc["environment"]["AERMANI_EXECUTOR_MAX_SPEED"] == "0.8"
    assert "AERMANI_SIM_SPEED_FACTOR" in doc["environment_overridden"]  # the run's --speed-factor wins
    assert "AERMANI_SIM_DYNAMICS" not in doc["environment_overridden"]
    assert doc["effective"] == {"realism": "harsh", "dynamics": "multirotor", "speed_factor": 3.0, "step_cap": 55,
                                "t_max_s": 600.0, "backend": "rules", "output_mode": "auto", "segmenter": "sim"}
    assert doc["run_environment"]["AERMANI_SIM_SPEED_FACTOR"] == "3.0"
    assert "sk-secret-value" not in str(doc) and "t0k3n" not in str(doc)
    text = _environment_text(doc)
    assert "`AERMANI_EXECUTOR_MAX_SPEED=0.8`" in text and "`AERMANI_SIM_SPEED_FACTOR=9` (overridden by the run)" in text
    eff = _effective_text(doc)
    assert "dynamics (AERMANI_SIM_DYNAMICS) `multirotor`" in eff and "step cap `55`" in eff
    assert "speed factor `3.0`" in eff and "segmenter `sim`" in eff
    with mock.patch.dict(os.environ, {"AERMANI_SIM_DYNAMICS": "rocket"}):
        assert "would refuse" in run_config_of(RunConfig(out=tmp_path))["effective"]["error"]
    assert _environment_text({}).startswith("unrecorded") and _environment_text({"environment": {}}).startswith("none")
    assert _effective_text({}).startswith("unrecorded")


def test_a_not_found_task_lays_out_a_world_without_its_object_and_is_scored_for_saying_so() -> None:
    """Issue 26: `"expect": "not_found"` names an object the world lacks; the episode succeeds when the task ends
    failed with a not-found reason within a bounded number of steps, holding nothing."""
    from pydantic import ValidationError

    from aermani.evaluation.runner import not_found_verdict
    from aermani.evaluation.tasks import EvalTask

    task = EvalTask(command="Find the green bottle and place it on the table.", target_object="green bottle",
                    destination="table", distractors=("red cup", "apple"), expect="not_found")
    sc = task.scenario(7)
    assert sc.target_object is None and sc.distractors == ("red cup", "apple")
    with pytest.raises(ValidationError, match="lists its distractors"):
        EvalTask(command="Pick up the hammer.", target_object="hammer", expect="not_found")
    with pytest.raises(ValidationError, match="must lack"):
        EvalTask(command="Pick up the hammer.", target_object="hammer", distractors=("hammer",), expect="not_found")
    ok, why = not_found_verdict("failed", "not found: the green bottle was not detected", 12, 40, None)
    assert ok and "12 reasoning steps" in why
    assert not not_found_verdict("succeeded", "the policy declared the task complete", 12, 40, None)[0]
    assert not not_found_verdict("failed", "model unavailable, vehicle held", 3, 40, None)[0]
    assert not not_found_verdict("failed", "not found: the green bottle", 41, 40, None)[0]
    assert not not_found_verdict("failed", "not found: the green bottle", 10, 40, "red cup")[0]
    assert not not_found_verdict("timeout", "", 80, 40, None)[0]


def test_the_built_in_suites_have_not_found_tasks_on_the_dev_split() -> None:
    tasks = [t for suite in load_suites().values() for t in suite]
    absent = [t for t in tasks if t.expect == "not_found"]
    assert absent and all(t.split == "dev" for t in absent)
    assert {t.suite for t in absent} >= {"localization", "search"}


def test_seeds_per_line_runs_every_line_on_distinct_layouts():
    from aermani.evaluation.runner import RunConfig, episode_specs

    suites = load_suites(["search"], split="test")
    specs = episode_specs(RunConfig(out=Path("."), split="test", suites=["search"], seeds_per_line=3, episodes=None))
    lines = suites["search"]
    assert len(specs) == 3 * len(lines)
    for task in lines:
        seeds = [s.seed for s in specs if s.task == task]
        assert len(seeds) == 3 and len(set(seeds)) == 3, task.command  # each line on three different layouts
    assert "--seeds-per-line 3" in RunConfig(out=Path("."), seeds_per_line=3).command_line()
    assert "--episodes" not in RunConfig(out=Path("."), seeds_per_line=3).command_line()


def test_the_report_names_the_split_freeze_and_the_last_policy_change():
    from aermani.evaluation.report import configuration_lines
    from aermani.evaluation.runner import source_revision

    rev = source_revision()
    if rev["commit"].startswith("unknown"):
        pytest.skip("not a git checkout")
    assert len(rev["split_frozen"]) == 40 and len(rev["policy_changed"]) == 40
    text = "\n".join(configuration_lines([], {**rev, "policy_changed_after_freeze": True}))
    assert f"`{rev['split_frozen'][:12]}` / `{rev['policy_changed'][:12]}`" in text
    assert "the policy changed after the split froze" in text
    text = "\n".join(configuration_lines([], {**rev, "policy_changed_after_freeze": False}))
    assert "no policy change since the split froze" in text


def test_the_not_found_bound_comes_from_the_room_search_and_the_report_shows_it() -> None:
    """One number for the rules baseline's search budget and the not-found bound (issue 26: 60 vs 40): the bound
    allows the whole search, the reasoner's step cap does not end such a task first, no suite line sets a bound
    below it, and the report names it with each not-found episode's steps."""
    from aermani.evaluation.report import configuration_lines, not_found_lines
    from aermani.evaluation.tasks import EvalTask
    from services.reasoner.backends.rules import EXPLORE_BUDGET
    from services.reasoner.settings import ReasonerSettings
    from shared.search import NOT_FOUND_MAX_STEPS, SEARCH_STEPS

    assert EXPLORE_BUDGET == SEARCH_STEPS and NOT_FOUND_MAX_STEPS > SEARCH_STEPS
    assert ReasonerSettings().max_steps >= NOT_FOUND_MAX_STEPS
    absent = [t for s in load_suites(split=None).values() for t in s if t.expect == "not_found"]
    assert absent and all(t.not_found_max_steps >= NOT_FOUND_MAX_STEPS for t in absent)
    task = EvalTask(command="Pick up the hammer.", target_object="hammer", distractors=("apple",),
                    expect="not_found", suite="localization")
    assert task.not_found_max_steps == NOT_FOUND_MAX_STEPS
    rec = EpisodeRecord(episode_id="rules/full/localization/000-s1", suite="localization", backend="rules",
                        variant="full", task=task, seed=1, state="failed", success=True,
                        verdict="said not found after 72 reasoning steps (bound 80): not found: the hammer")
    text = "\n".join(configuration_lines([rec], {}))
    assert f"{NOT_FOUND_MAX_STEPS} reasoning steps by default" in text and f"({SEARCH_STEPS} steps" in text
    assert "1 not-found episode(s) held to 80" in text
    table = "\n".join(not_found_lines([rec]))
    assert "| rules/full/localization/000-s1 | hammer | 0 / 80 | yes |" in table
    assert not_found_lines([rec.model_copy(update={"task": task.model_copy(update={"expect": "success",
                                                                                   "distractors": None})})]) == []


def test_by_default_every_line_of_every_suite_runs_on_two_layouts(tmp_path) -> None:
    """Issue 26: `--episodes 10` ran 10 of the 12 lines of a suite; with no count given every line runs, each on
    DEFAULT_SEEDS_PER_LINE layouts, and the reproduce line says so. --episodes stays an opt-in; a task file runs
    each of its lines once."""
    import typer
    from typer.testing import CliRunner

    from aermani.evaluation import cli as evaluation_cli
    from aermani.evaluation.report import _episodes_text
    from aermani.evaluation.tasks import DEFAULT_SEEDS_PER_LINE

    cfg = RunConfig(out=tmp_path, split="dev")
    assert cfg.seeds_per_line == DEFAULT_SEEDS_PER_LINE == 2 and cfg.episodes is None
    suites = load_suites(split="dev")
    specs = episode_specs(cfg)
    assert len(specs) == 2 * sum(len(t) for t in suites.values())
    for name, tasks in suites.items():
        for task in tasks:
            assert len({s.seed for s in specs if s.task == task and s.task.suite == name}) == 2, task.command
    assert "--seeds-per-line 2" in cfg.command_line() and "--episodes" not in cfg.command_line()
    assert _episodes_text(run_config_of_dict(cfg)) == "every line x 2 layout seeds"
    opt_in = RunConfig(out=tmp_path, episodes=3)
    assert opt_in.seeds_per_line is None and len(episode_specs(opt_in)) == 3 * len(suites)
    assert "some lines never ran" in _episodes_text({"episodes": 3})
    f = tmp_path / "mine.jsonl"
    f.write_text('{"command": "Pick up the red cup.", "target_object": "red cup", "seed": 4}\n')
    assert len(episode_specs(RunConfig(out=tmp_path, tasks_file=f))) == 1
    # the CLI passes no count of its own (the run itself is replaced: it would start the stack)
    from unittest import mock

    from aermani.evaluation.runner import RunSummary

    seen: list[RunConfig] = []
    app = typer.Typer()
    evaluation_cli.register(app)

    def fake_run(c: RunConfig) -> RunSummary:
        seen.append(c)
        return RunSummary(c.out, planned=0, skipped=0, ran=0, records=[])

    import signal

    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}  # the CLI sets its own
    with mock.patch("aermani.evaluation.runner.run", fake_run), mock.patch("signal.signal"):
        res = CliRunner().invoke(app, ["eval", "--out", str(tmp_path / "x"), "--no-progress"])
        assert res.exit_code == 0, res.output
        res = CliRunner().invoke(app, ["eval", "--out", str(tmp_path / "y"), "--episodes", "3", "--no-progress"])
        assert res.exit_code == 0, res.output
    assert handlers == {sig: signal.getsignal(sig) for sig in handlers}
    assert (seen[0].seeds_per_line, seen[0].episodes) == (2, None)
    assert (seen[1].seeds_per_line, seen[1].episodes) == (None, 3)


def run_config_of_dict(cfg: RunConfig) -> dict:
    return cfg.model_dump(mode="json")


def test_every_suite_line_says_how_it_is_scored_consistently_with_its_layout() -> None:
    """Both splits (their lines, never their episodes): every sequential line names its motions, an approach goes
    to a surface the simulator has, and each conditional's lines lay out the branch they expect: the `then` line
    puts the object on the place the condition is about, the `otherwise` line lacks it."""
    from aermani.evaluation.tasks import ConditionalChoice, SizeChoice

    for split in ("dev", "test"):
        suites = load_suites(split=split)
        assert all(t.motions for t in suites["sequential"] if t.expect == "success"), split
        assert any(isinstance(t.choice, SizeChoice) for t in suites["clutter"]), split
        for t in (t for ts in suites.values() for t in ts):
            for m in t.motions:
                assert m.skill != "approach" or m.to in SURFACES, (t.command, m)
            c = t.choice
            if isinstance(c, ConditionalChoice):
                laid_out = {t.target_object, *t.extra_objects, *(t.distractors or ())}
                if t.target_object == c.then:
                    assert (t.placements or {}).get(c.if_present) == c.on, t.command
                else:
                    assert t.target_object == c.otherwise and c.if_present not in laid_out, t.command
            elif isinstance(c, SizeChoice):
                assert set(c.among) <= {t.target_object, *t.extra_objects, *(t.distractors or ())}, t.command
