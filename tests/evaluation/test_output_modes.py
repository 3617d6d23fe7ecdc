"""The report shows IAR per answer decoding (schema-constrained vs free text), and `--output-mode both` runs
are compared side by side."""

from __future__ import annotations

from aermani.evaluation.records import EpisodeRecord, ResultsFile
from aermani.evaluation.report import write_mode_comparison, write_report
from aermani.evaluation.runner import RunConfig, vehicle_env
from aermani.evaluation.tasks import load_suites
from shared.messages import ModelCall, ReasoningStep, SkillState, SkillToExecute


def rec(eid: str, calls: list[tuple[bool, bool]]) -> EpisodeRecord:
    """An episode whose one step made `calls` model calls, each (structured, valid)."""
    task = load_suites(["localization"])["localization"][0]
    step = ReasoningStep(task_id="t", step=1, ste=SkillToExecute(skill="done"), valid=True,
                         calls=tuple(ModelCall(raw_answer="{}", valid=v, structured=s, latency_s=0.1)
                                     for s, v in calls),
                         skill_state=SkillState.SUCCEEDED)
    return EpisodeRecord(episode_id=eid, suite="localization", backend="openai", variant="full", task=task, seed=1,
                         state="succeeded", success=True, steps=[step], verdict="ok")


def test_report_splits_iar_by_answer_decoding(tmp_path) -> None:
    rf = ResultsFile(tmp_path / "episodes.jsonl")
    rf.append(rec("openai/full/localization/000", [(True, False), (True, True)]))       # schema: 1 of 2 invalid
    rf.append(rec("openai/full/localization/001", [(False, False), (False, False), (False, True)]))  # text: 2 of 3
    md = write_report(tmp_path, config={"backend": "openai", "output_mode": "auto"})["markdown"].read_text()
    assert "schema-constrained IAR 50.0 % of 2 calls" in md and "free text IAR 66.7 % of 3 calls" in md
    assert "output_mode=auto" in md


def test_both_modes_are_compared_and_reach_the_reasoner(tmp_path) -> None:
    for mode, calls in (("schema", [(True, True)]), ("text", [(False, False), (False, True)])):
        ResultsFile(tmp_path / mode / "episodes.jsonl").append(rec("openai/full/localization/000", calls))
    md = write_mode_comparison(tmp_path, ["schema", "text"]).read_text()
    assert "| [schema](schema/report.md) | AERMANI-VLM (openai) | 1 | 100.0 [20.7, 100.0] | 0.0 | 1 |" in md
    assert "| [text](text/report.md) | AERMANI-VLM (openai) | 1 | 100.0 [20.7, 100.0] | 50.0 | 2 |" in md
    assert vehicle_env(RunConfig(backend="openai", output_mode="text"))["AERMANI_REASONER_OUTPUT_MODE"] == "text"
