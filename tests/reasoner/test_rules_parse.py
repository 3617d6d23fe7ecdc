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


# --------------------------------------------------------------------------- issue 33: the generated dev set


def test_the_generator_is_deterministic_and_covers_every_construction() -> None:
    from benchmarks._phrasing_gen import CONSTRUCTIONS, generate
    from services.sim.layout import OBJECTS, SURFACES

    rows = generate(600, seed=7)
    assert rows == generate(600, seed=7)
    assert rows != generate(600, seed=8)
    assert len(rows) == 600 and len({r["command"] for r in rows}) > 550  # repeats are redrawn
    assert {r["construction"] for r in rows} == set(CONSTRUCTIONS)
    assert all(sum(r["construction"] == k for r in rows) == 60 for k in CONSTRUCTIONS)
    for row in rows:
        assert set(row) == {"command", "kind", "construction", *FIELDS}, row
        assert row["kind"] == row["construction"]
        names = [row["target"], *row["excluded"], *row["choices"]]
        assert all(n in OBJECTS for n in names if n), row  # expected names are the catalogue's, from the slots
        assert row["destination"] is None or row["destination"] in SURFACES, row
    assert any(not r["understood"] for r in rows if r["construction"] == "non_object_noun")
    assert any(r["motions"] and not r["target"] for r in rows if r["construction"] == "motion")


def test_generated_dev_commands_read_exactly() -> None:
    """The issue's bar: >= 98 % of >= 2,000 generated commands exactly (names compared as perception reads them)."""
    from benchmarks._phrasing_gen import generate

    rows = generate(2000, seed=0)
    wrong = [r["command"] for r in rows if not score_line(r, fold=True)[0]]
    assert len(wrong) <= 40, wrong[:10]


def test_accuracy_script_reports_generated_commands_per_construction(tmp_path: Path) -> None:
    from benchmarks._phrasing_gen import CONSTRUCTIONS

    out_json = tmp_path / "p.json"
    out = subprocess.run([sys.executable, "benchmarks/parser_accuracy.py", "--generated", "200", "--seed", "3",
                          "--json", str(out_json)], cwd=REPO, capture_output=True, text=True, check=True).stdout
    assert "generated dev commands: 200 (seed 3)" in out and all(k in out for k in CONSTRUCTIONS)
    figures = json.loads(out_json.read_text())["figures"]
    assert figures["generated"]["overall"]["total"] == 200 and figures["generated_seed"] == 3
    assert set(CONSTRUCTIONS) <= set(figures["generated"])


def test_the_lexicon_holds_the_perception_vocabulary() -> None:
    from services.perception.query import CATALOG, FAMILIES, SYNONYMS
    from services.reasoner.backends.rules_lexicon import PERCEPTION_WORDS, object_noun
    from services.sim.layout import FURNITURE, OBJECTS

    words = {w for name in (*CATALOG, *SYNONYMS, *SYNONYMS.values(), *FAMILIES, *(m for v in FAMILIES.values()
                                                                                  for m in v)) for w in name.split()}
    assert words <= PERCEPTION_WORDS, sorted(words - PERCEPTION_WORDS)
    assert all(object_noun(name.split()[-1]) is True for name in (*OBJECTS, *FURNITURE))
    assert object_noun("unicorn") is True and object_noun("gizmo") is None
    assert object_noun("time") is False and object_noun("happiness") is False and object_noun("metre") is False


def _p(command: str) -> tuple:
    p = parse_command(command)
    return p.target, p.destination, p.motions, p.excluded, p.choices, p.understood


def test_telegraphic_commands_are_read_as_pick_and_place_and_say_so() -> None:
    for cmd in ("red cup to the table", "The red cup on the table please", "red cup onto table", "red cup -> table",
                "the red mug to the desk, thanks"):
        p = parse_command(cmd)
        assert p.understood and p.target in ("red cup", "red mug") and p.destination in ("table", "desk"), cmd
        assert "no task verb" in p.note, cmd
    assert _p("the banana, please")[:2] == ("banana", None)
    assert _p("unicorn to the table")[:2] == ("unicorn", "table")  # unknown object, known destination
    assert not parse_command("Hello there!").understood and not parse_command("the weather to me").understood
    assert parse_command("pick up the red cup").note == ""


def test_passive_and_polite_forms() -> None:
    for cmd in ("the red cup should be put on the table", "The red cup needs to go on the table",
                "the red cup has to be moved to the table", "The red cup belongs on the table",
                "I want the red cup placed on the table", "the red cup is supposed to be on the table",
                "Would you mind transferring the red cup to the table?", "could you possibly take the red cup to "
                "the table for me?", "I'd be grateful if you could carry the red cup to the table",
                "have the red cup put on the table", "make the red cup go to the table",
                "have the red cup taken to the table"):
        assert _p(cmd)[:3] == ("red cup", "table", []), cmd
    assert _p("the coke can be put on the shelf")[:2] == ("coke can", "shelf")  # "can" the noun and the modal
    assert _p("the can of coke can be put on the shelf")[:2] == ("coke can", "shelf")
    assert _p("get the orange in one go")[:2] == ("orange", None)


def test_lists_of_distractors() -> None:
    assert _p("ignore the hammer, the wrench and the apple, then grab the banana")[3] == ["hammer", "wrench", "apple"]
    assert _p("Don't touch the coke can or the soda can; take the green bottle")[::3] == ("green bottle",
                                                                                         ["coke can", "soda can"])
    assert _p("Leave the wrench and the tissue box where they are and snag the orange")[::3] == (
        "orange", ["wrench", "tissue box"])
    assert _p("never mind the apple, grab the hammer")[::3] == ("hammer", ["apple"])
    assert _p("Ignore the tools and pick up the green bottle")[::3] == ("green bottle", ["tool"])


def test_motion_amounts_and_sequences() -> None:
    assert _p("move forward a bit")[2] == ["forward"]
    assert _p("move up a little and turn right")[:3] == (None, None, ["up", "yaw_right"])
    assert _p("fly forward three metres")[2] == ["forward"] * 6
    assert _p("go up 2 m")[2] == ["up"] * 7
    assert _p("move 1.5 meters forward")[2] == ["forward"] * 3
    assert _p("move half a metre right")[2] == ["right"]
    assert _p("yaw ninety degrees to the right")[2] == ["yaw_right"] * 2
    assert _p("spin 180 degrees to the right")[2] == ["yaw_right"] * 4
    assert _p("move down one metre, and snag the cardboard box")[:3] == ("cardboard box", None, ["down"] * 3)
    assert _p("turn left twice, then grab the apple and after that put it on the shelf")[:3] == (
        "apple", "shelf", ["yaw_left", "yaw_left"])
    assert _p("move to the left a bit then lift the coke can and set it down on the wooden table")[:3] == (
        "coke can", "wooden table", ["left"])


def test_conditionals_on_what_is_seen_both_branches() -> None:
    assert _p("if you see the apple, grab it; otherwise grab the banana")[4] == ["apple", "banana"]
    assert _p("if you cannot find the apple, take the banana; otherwise take the apple")[4] == ["apple", "banana"]
    assert _p("If there is a red cup, grab it")[:3] == ("red cup", None, [])
    assert _p("if you see the apple, put it on the table")[:2] == ("apple", "table")


def test_search_forms() -> None:
    for cmd in ("where is the red cup?", "See if you can find the red cup", "do you see the red cup?",
                "is there a red cup anywhere?", "have a look for the red cup", "scan the room for the red cup"):
        assert _p(cmd)[:3] == ("red cup", None, []), cmd


def test_a_noun_that_names_no_object_is_never_the_target() -> None:
    for cmd in ("take your time and grab the apple", "grab the apple with care", "in a minute, grab the apple",
                "grab the apple slowly", "with your gripper, grab the apple", "grab the apple at your convenience"):
        assert _p(cmd)[0] == "apple", cmd
    for cmd in ("pick up the pace", "take a break", "find the answer", "get the idea", "take the initiative",
                "find a solution"):
        p = parse_command(cmd)
        assert not p.understood and p.target is None and not p.motions, cmd
    assert _p("pick up the unicorn")[0] == "unicorn"  # unknown but possibly in a room: searched for
