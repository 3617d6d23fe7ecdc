"""The rules baseline's command reader against the dev set of phrasings (one test per line, grouped by kind of
phrasing), the known failures it was rebuilt for, and the accuracy script that scores any phrasing set."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.parser_accuracy import FIELDS, norm, score_line
from services.reasoner.backends.rules import parse_command as parse_command_from_rules
from services.reasoner.backends.rules_parse import parse_command

DEV = Path(__file__).parent / "data" / "phrasings_dev.jsonl"
ROWS = [json.loads(line) for line in DEV.read_text().splitlines() if line.strip()]
KINDS = ("synonym_verbs", "prepositions", "polite_indirect", "relative_clause", "counts_motion", "conditional",
         "negation_distractor", "size_comparison", "category", "refuse")
REPO = Path(__file__).resolve().parents[2]


def test_dev_set_format_and_coverage() -> None:
    assert len(ROWS) >= 60
    for row in ROWS:
        assert set(row) == {"command", *FIELDS, "kind"}, row
        assert row["kind"] in KINDS
        assert isinstance(row["motions"], list) and isinstance(row["excluded"], list)
        assert isinstance(row["choices"], list) and isinstance(row["understood"], bool)
    assert {r["kind"] for r in ROWS} == set(KINDS)
    assert all(sum(r["kind"] == k for r in ROWS) >= 6 for k in KINDS)


@pytest.mark.parametrize("row", ROWS, ids=[f"{r['kind']}-{i}" for i, r in enumerate(ROWS)])
def test_dev_phrasing(row: dict) -> None:
    ok, fields, got = score_line(row)
    wrong = {f: (row[f], got[f]) for f, good in fields.items() if not good}
    assert ok, f"{row['command']!r}: (expected, parsed) {wrong}"


def test_parse_command_is_importable_from_the_backend() -> None:
    assert parse_command_from_rules is parse_command


def test_known_failures_of_the_old_parser() -> None:
    p = parse_command("Put the red cup onto the counter next to the sink")
    assert (p.target, p.destination) == ("red cup", "counter")
    for cmd in ("bring the apple over to the table", "Bring the apple across to the table",
                "could you bring the apple over to the table please"):
        p = parse_command(cmd)
        assert (p.target, p.destination) == ("apple", "table"), cmd
    p = parse_command("I have lost my purple cup somewhere in this room. Could you search around for it and put it "
                      "on the round table?")
    assert (p.target, p.destination) == ("purple cup", "round table")
    p = parse_command("Can you look around the room and find the purple cup for me?")
    assert p.target == "purple cup" and p.destination is None


def test_refusal_says_why() -> None:
    p = parse_command("What's the weather like?")
    assert not p.understood and "no object" in p.reason and "no motion" in p.reason
    p = parse_command("Pick up")
    assert not p.understood and "names no object" in p.reason
    assert not parse_command("   ").understood


def test_amounts_of_motion_use_the_step_sizes() -> None:
    assert parse_command("turn right 90 degrees").motions == ["yaw_right"] * 2
    assert parse_command("rotate 180 degrees").motions == ["yaw_left"] * 4
    assert parse_command("move left 1.5 meters").motions == ["left"] * 3
    assert parse_command("go up 60 cm").motions == ["up"] * 2
    assert parse_command("fly forward 100 times").motions == ["forward"] * 10  # clipped


def test_a_registered_skill_named_outright_is_sequenced() -> None:
    p = parse_command("descend to inspect, then pick up the red cup", ["descend_to_inspect", "grasp"])
    assert p.motions == ["descend_to_inspect"] and p.target == "red cup"


def test_norm_for_scoring() -> None:
    assert norm("The Red Cups") == "red cup"
    assert norm(["approach:the Counters"]) == ["approach:counter"]
    assert norm("") is None and norm(None) is None


def test_accuracy_script_on_dev_and_on_an_unseen_format(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, "benchmarks/parser_accuracy.py", str(DEV)], cwd=REPO,
                         capture_output=True, text=True, check=True).stdout
    assert "OVERALL" in out and all(k in out for k in KINDS) and "destination" in out
    # Unknown kinds, a missing field, a broken line and a wrong expectation: scored, reported, not a crash.
    other = tmp_path / "other.jsonl"
    other.write_text("\n".join([
        json.dumps({"command": "grab the apple", "kind": "brand_new_kind", "target": "apple", "understood": True}),
        json.dumps({"command": "grab the apple", "target": "banana"}),
        "{not json",
        "",
        json.dumps({"command": "sing", "kind": "refuse", "understood": False, "target": "x"}),
    ]))
    res = subprocess.run([sys.executable, "benchmarks/parser_accuracy.py", str(other), "--show-errors"], cwd=REPO,
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert "brand_new_kind" in res.stdout and "(no kind)" in res.stdout and "unreadable" in res.stdout
    assert "OVERALL                         2      4" in res.stdout, res.stdout
