"""The parser/validator: strict JSON, lenient recovery, specific rejection reasons."""

from __future__ import annotations

import contextlib
import json

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from services.reasoner.library import default_library
from services.reasoner.parse import parse_answer
from shared.errors import InvalidAnswer

LIB = default_library()
NAMES = [s.name for s in LIB.skills if s.policy_visible]
FULL_DRT = {"image_description": "a red cup on a table", "summary": "nothing yet",
            "action_predictions": dict.fromkeys(NAMES, "x"), "reasoning": "the cup is visible"}


def full(skill: str = "obj_localization", argument: str | None = "red cup", **drt: object) -> str:
    return json.dumps({"drt": {**FULL_DRT, **drt}, "ste": {"skill": skill, "argument": argument}})


def test_strict_full() -> None:
    p = parse_answer(full(), "full", LIB)
    assert p.ste.skill == "obj_localization" and p.ste.argument == "red cup" and not p.recovered
    assert p.drt.reasoning == "the cup is visible" and set(p.drt.action_predictions) == set(NAMES)


@pytest.mark.parametrize("raw", [
    "```json\n" + full() + "\n```",
    "Sure! Here is my answer:\n" + full() + "\nHope this helps.",
    full()[:-1] + ",}",
    full().replace('"', "'"),
])
def test_lenient_recovery(raw: str) -> None:
    p = parse_answer(raw, "full", LIB)
    assert p.ste.skill == "obj_localization" and p.ste.argument == "red cup" and p.recovered


@pytest.mark.parametrize(("given", "expected"), [("Yaw Right", "yaw_right"), ("obj localization", "obj_localization"),
                                                 ("FORWARD", "forward"), ("object_localization", "obj_localization"),
                                                 ("placement-localization", "placement_localization")])
def test_skill_name_case_and_spacing(given: str, expected: str) -> None:
    arg = "table" if "placement" in expected else "cup"
    assert parse_answer(full(given, arg), "full", LIB).ste.skill == expected


def test_flat_shape_and_skill_call_syntax() -> None:
    p = parse_answer('{"skill": "obj_localization(red cup)"}', "no_drt", LIB)
    assert (p.ste.skill, p.ste.argument) == ("obj_localization", "red cup")


@pytest.mark.parametrize(("raw", "variant", "reason"), [
    ("", "full", "empty"),
    ("I think we should fly up", "full", "No JSON object"),
    (full("fly_up", None), "full", "Unknown skill 'fly_up'"),
    (full("obj_localization", None), "full", "needs an argument (object query)"),
    (json.dumps({"drt": {"summary": "x"}, "ste": {"skill": "up"}}), "drt_v1", "Missing DRT field(s) required by the "
                                                                            "Rules: image_description"),
    (json.dumps({"drt": {k: v for k, v in FULL_DRT.items() if k != "reasoning"}, "ste": {"skill": "up"}}), "full",
     "reasoning"),
    (full(action_predictions={"up": "climbs"}), "full", "missing: yaw_left"),
    (full(action_predictions="all good"), "full", "must be an object"),
    (json.dumps({"drt": FULL_DRT}), "full", "has no skill"),
    ('{"ste": {"skill": ["up"]}}', "no_drt", "must be a string"),
    ('{"ste": {"skill": "takeoff"}}', "no_drt", "Unknown skill 'takeoff'"),
])
def test_rejections_are_specific(raw: str, variant: str, reason: str) -> None:
    with pytest.raises(InvalidAnswer) as exc:
        parse_answer(raw, variant, LIB)
    assert reason in str(exc.value)


def test_argument_to_no_argument_skill_is_ignored() -> None:
    assert parse_answer('{"ste": {"skill": "forward", "argument": "2 m"}}', "no_drt", LIB).ste.argument is None


def test_prediction_coverage_setting() -> None:
    partial = dict.fromkeys(NAMES[:-1], "x")
    with pytest.raises(InvalidAnswer):
        parse_answer(full(action_predictions=partial), "full", LIB)
    assert parse_answer(full(action_predictions=partial), "full", LIB, coverage=0.9).ste.skill == "obj_localization"


def test_react_thought_then_json() -> None:
    p = parse_answer('Thought: the cup is on my left.\nThought: turn.\nAction: {"skill": "yaw_left", "argument": null}',
                     "react", LIB)
    assert p.ste.skill == "yaw_left" and "cup is on my left" in (p.drt.reasoning or "")


@pytest.mark.parametrize(("raw", "skill", "arg"), [("yaw_left", "yaw_left", None),
                                                   ("obj_localization(red cup)", "obj_localization", "red cup"),
                                                   ("I would choose Yaw Right.", "yaw_right", None),
                                                   ("placement_localization: table", "placement_localization",
                                                    "table")])
def test_unstructured_bare_names(raw: str, skill: str, arg: str | None) -> None:
    p = parse_answer(raw, "unstructured", LIB)
    assert (p.ste.skill, p.ste.argument) == (skill, arg)


def test_no_drt_accepts_extra_drt_fields() -> None:
    assert parse_answer(full("up", None), "no_drt", LIB).drt.summary == "nothing yet"


# --------------------------------------------------------------------------- exact: the skill the answer chose


@pytest.mark.parametrize(("raw", "skill", "arg"), [
    ("grasp would fail, so I will yaw_left", "yaw_left", None),
    ("The cup is not localized yet, so grasp is pointless. I will use obj_localization(red cup).",
     "obj_localization", "red cup"),
    ("Forward would hit the wall; yaw right instead.", "yaw_right", None),
    ("I should not grasp yet. Next skill: obj_localization(red cup)", "obj_localization", "red cup"),
    ("Placing needs a spot; rather than place, I choose placement_localization: table",
     "placement_localization", "table"),
    ("After forward and yaw_left the cup is visible.\nFinal answer: grasp", "grasp", None),
])
def test_unstructured_takes_the_committed_skill(raw: str, skill: str, arg: str | None) -> None:
    p = parse_answer(raw, "unstructured", LIB)
    assert (p.ste.skill, p.ste.argument) == (skill, arg)


@pytest.mark.parametrize("raw", ["forward or backward, both look fine", "up, down, left: hard to say"])
def test_unstructured_several_skills_without_commitment_is_invalid(raw: str) -> None:
    with pytest.raises(InvalidAnswer, match="without committing to one"):
        parse_answer(raw, "unstructured", LIB)


def test_react_takes_the_action_not_json_quoted_in_the_thought() -> None:
    raw = ('Thought: answering {"skill": "grasp", "argument": "red cup"} now would fail: nothing is localized.\n'
           'Thought: localize first.\nAction: {"skill": "obj_localization", "argument": "red cup"}')
    p = parse_answer(raw, "react", LIB)
    assert (p.ste.skill, p.ste.argument) == ("obj_localization", "red cup")
    assert "would fail" in (p.drt.reasoning or "")


def test_react_without_action_line_is_invalid_even_with_json_in_the_thought() -> None:
    with pytest.raises(InvalidAnswer, match="No 'Action:' line"):
        parse_answer('Thought: maybe {"skill": "grasp"} is right.', "react", LIB)
    with pytest.raises(InvalidAnswer, match="'Action:' line has no JSON"):
        parse_answer('Thought: {"skill": "grasp"}\nAction: grasp', "react", LIB)
    # a bare JSON object is an action without thoughts
    assert parse_answer('{"skill": "up", "argument": null}', "react", LIB).ste.skill == "up"


def test_json_after_an_unclosed_brace_in_prose_is_found() -> None:
    p = parse_answer('Let me think { about it. I\'ll answer: {"ste": {"skill": "up", "argument": null}}', "no_drt", LIB)
    assert p.ste.skill == "up" and p.recovered


# --------------------------------------------------------------------------- bounded: size, depth, linear work


@pytest.mark.parametrize(("raw", "reason"), [
    ("{" * 20_000, "20000 brackets, quotes and backslashes"),
    ("{" * 200_000, "characters long"),
    ('{"a": ' * 1000 + "1" + "}" * 1000, "deeper than"),
    ('{"ste": {"skill": "up", "argument": ' + "[" * 1000 + "]" * 1000 + "}}", "deeper than"),
    ("[" * 5000 + "]" * 5000, "10000 brackets"),
    ("[" * 1900 + "]" * 1900, "No JSON object"),
    ('{"ste": {"skill": "' + "9" * 5000 + '"}}', "Unknown skill"),
    ("{'ste': {'skill': " + "(" * 500 + "'up'" + ")" * 500 + "}}", "No JSON object"),
])
@pytest.mark.parametrize("variant", ["full", "react", "unstructured"])
def test_pathological_answers_are_invalid_with_a_reason(raw: str, reason: str, variant: str) -> None:
    """Each is rejected with a reason (the unstructured variant may still read a lone skill name in it)."""
    try:
        p = parse_answer(raw, variant, LIB)
    except InvalidAnswer as exc:
        assert reason in str(exc) or variant != "full"
    else:
        assert variant == "unstructured" and p.ste.skill in NAMES


class _Counting:
    """Wraps the decoders the parser calls and sums the characters they are given."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        import ast as _ast
        import json as _json
        import types

        from services.reasoner import parse as mod

        self.chars = 0

        def loads(s, *a, **k):
            self.chars += len(s)
            return _json.loads(s, *a, **k)

        def literal_eval(s):
            self.chars += len(s)
            return _ast.literal_eval(s)

        monkeypatch.setattr(mod, "json", types.SimpleNamespace(loads=loads, dumps=_json.dumps))
        monkeypatch.setattr(mod, "ast", types.SimpleNamespace(literal_eval=literal_eval))


_PIECES = st.sampled_from(["{", "}", "[", "]", '"', "'", "\\", ":", ",", "\n", " ", "Action:", "Thought:", "```",
                           "```json\n", '"ste"', '"skill"', '"drt"', "yaw_left", "grasp", "obj_localization",
                           " so I will ", " would fail", "null", "1", "true", "(red cup)"])
_JSONISH = st.recursive(st.none() | st.booleans() | st.integers() | st.text(max_size=8),
                        lambda kids: (st.lists(kids, max_size=4)
                                      | st.dictionaries(st.text(max_size=6), kids, max_size=4)),
                        max_leaves=40)


@given(pieces=st.lists(_PIECES, max_size=400), text=st.text(max_size=200), nested=_JSONISH,
       depth=st.integers(0, 60), variant=st.sampled_from(["full", "react", "unstructured", "no_drt"]))
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_any_text_is_parsed_or_rejected_with_linear_work(pieces, text, nested, depth, variant) -> None:
    """Arbitrary text and nesting: the only failure is InvalidAnswer, and the characters scanned and handed to
    the decoders are bounded by a constant times the answer's length (no clock involved)."""
    from services.reasoner.parse import Work

    raw = "".join(pieces) + text + "{" * depth + json.dumps({"ste": nested}) + "}" * depth
    mp = pytest.MonkeyPatch()
    try:
        counting = _Counting(mp)
        work = Work()
        with contextlib.suppress(InvalidAnswer):
            parse_answer(raw, variant, LIB, work=work)
    finally:
        mp.undo()
    n = len(raw) + 1
    # strict read 1n, fenced blocks and then the whole text each <= 2 quoting modes x 2 texts x 2 decoders = 8n
    assert counting.chars <= 17 * n, (counting.chars, n)
    assert work.chars <= 24 * n, (work.chars, n)


def test_vlm_check_reads_the_whole_file_past_pathological_lines(tmp_path) -> None:
    """`aermani vlm check` (a real process) reports every line, the hostile ones as rejected with a reason."""
    import subprocess
    import sys

    lines = [full(), "{" * 20_000, '{"a": ' * 1000 + "1" + "}" * 1000, "x" * 40_000, full("yaw_left", None)]
    f = tmp_path / "answers.jsonl"
    f.write_text("".join(json.dumps(x) + "\n" for x in lines))
    res = subprocess.run([sys.executable, "-m", "aermani.cli", "vlm", "check", str(f), "--offline"],
                         capture_output=True, text=True, timeout=120)
    out = res.stdout
    assert res.returncode == 1, res.stderr
    assert "1: accepted: obj_localization(red cup)" in out and "5: accepted: yaw_left" in out
    assert "2: rejected: The answer holds 20000 brackets, quotes and backslashes" in out
    assert "3: rejected: The answer nests brackets deeper than 16" in out
    assert "4: rejected: The answer is 40000 characters long" in out
    assert "2/5 accepted, 3 rejected" in out


def test_vlm_check_reads_baseline_answers_against_the_library_the_variant_offers(tmp_path) -> None:
    """`aermani vlm check --variant waypoint` checks against the motion primitives only; plan-once plans too."""
    import subprocess
    import sys

    f = tmp_path / "answers.jsonl"
    f.write_text("".join(json.dumps(x) + "\n" for x in ['{"ste": {"skill": "forward", "argument": null}}',
                                                         '{"ste": {"skill": "grasp", "argument": null}}']))
    res = subprocess.run([sys.executable, "-m", "aermani.cli", "vlm", "check", str(f), "--offline", "--variant",
                          "waypoint"], capture_output=True, text=True, timeout=120)
    assert "1: accepted: forward" in res.stdout and "2: rejected: Unknown skill 'grasp'" in res.stdout, res.stderr
    plan = json.dumps({"plan": [{"skill": "yaw_left", "argument": None}, {"skill": "done", "argument": None}]})
    f.write_text(json.dumps(plan) + "\n")
    res = subprocess.run([sys.executable, "-m", "aermani.cli", "vlm", "check", str(f), "--offline", "--variant",
                          "plan-once"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and "1: accepted: yaw_left" in res.stdout, res.stdout + res.stderr


def test_braces_and_escaped_quotes_inside_strings_do_not_split_the_object() -> None:
    raw = 'Sure: {"ste": {"skill": "obj_localization", "argument": "the \\"red\\" cup {left} \\\\"}} ok'
    p = parse_answer(raw, "no_drt", LIB)
    assert (p.ste.skill, p.ste.argument) == ("obj_localization", 'the "red" cup {left} \\')


@pytest.mark.parametrize("arg", [1, 2.5, True, False, ["red cup"], {"name": "red cup"}])
def test_a_non_string_argument_is_rejected_as_the_docs_say(arg: object) -> None:
    raw = json.dumps({"drt": FULL_DRT, "ste": {"skill": "obj_localization", "argument": arg}})
    with pytest.raises(InvalidAnswer, match="must be a string or null"):
        parse_answer(raw, "full", LIB)


def test_a_non_string_argument_to_a_skill_without_one_is_ignored() -> None:
    p = parse_answer(json.dumps({"drt": FULL_DRT, "ste": {"skill": "yaw_left", "argument": 3}}), "full", LIB)
    assert (p.ste.skill, p.ste.argument) == ("yaw_left", None)


def test_of_several_objects_the_one_naming_a_skill_is_the_answer() -> None:
    """An object that names no skill (an example of a field) is passed over; two objects naming the same skill
    are one answer; two naming different skills are refused as ambiguous, never guessed."""
    answer = json.dumps({"drt": FULL_DRT, "ste": {"skill": "obj_localization", "argument": "red cup"}})
    p = parse_answer(f'For example {{"argument": "a cup"}} is an argument. My answer: {answer}', "full", LIB)
    assert (p.ste.skill, p.ste.argument) == ("obj_localization", "red cup")
    p = parse_answer(f"{answer}\nAgain, to be sure: {answer}", "full", LIB)
    assert p.ste.skill == "obj_localization"
    other = json.dumps({"drt": FULL_DRT, "ste": {"skill": "yaw_left", "argument": None}})
    for raw in (f"Either {answer} or {other}", f"```json\n{other}\n{answer}\n```"):
        with pytest.raises(InvalidAnswer, match=r"2 JSON objects naming different skills \(yaw_left, obj_loc"
                                                r"alization\(red cup\)\)|2 JSON objects naming different skills "
                                                r"\(obj_localization\(red cup\), yaw_left\)"):
            parse_answer(raw, "full", LIB)


def test_thousands_of_tiny_fragments_cost_a_bounded_number_of_decodes() -> None:
    """The decoders have a fixed cost per call: an answer of many `{k:v}` fragments (as many as the structure
    cap lets through) is rejected after MAX_DECODES candidates, and `{x}` fragments (no key-value pair) never
    reach a decoder."""
    from services.reasoner.parse import MAX_DECODES, MAX_STRUCTURE, Work

    for fragment, decodes in (("{x:1} ", MAX_DECODES + 1), ("{x} ", 0), ("{'a': 1} ", MAX_DECODES + 1)):
        specials = sum(fragment.count(c) for c in "{}'")
        raw = fragment * (MAX_STRUCTURE // specials)
        work = Work()
        with pytest.raises(InvalidAnswer):
            parse_answer(raw, "full", LIB, work=work)
        assert work.decodes == decodes, (fragment, work.decodes)


def test_the_work_per_answer_has_a_ceiling_not_only_a_linear_bound() -> None:
    """Linear is not enough at 32 kB (17 decoder passes over it took 0.2-0.4 s): the structure scanned, the
    text the Python-literal reader gets and the skill mentions weighed are capped per answer, each candidate is
    decoded once, and a cap reached is an InvalidAnswer saying so (benchmarks/reasoner.py times the worst)."""
    from services.reasoner.parse import MAX_ANSWER_CHARS, MAX_LITERAL_CHARS, MAX_MENTIONS, MAX_STRUCTURE, Work

    with pytest.raises(InvalidAnswer, match=f"32000 brackets, quotes and backslashes, more than the {MAX_STRUCTURE}"):
        parse_answer("{}" * (MAX_ANSWER_CHARS // 2), "full", LIB)
    # A literal that fails at its very end, fenced: met in the fence and in the whole answer, in both quoting
    # modes, and read once.
    lit = "{'a': [" + "1," * 3000 + "], 'b': x}"
    work = Work()
    with pytest.raises(InvalidAnswer, match="No JSON object"):
        parse_answer(f"```\n{lit}\n```", "full", LIB, work=work)
    assert work.literal_chars == len(lit), work.literal_chars
    # No single quote and no True/False/None: JSON's failure is the literal's too, the costly reader is skipped.
    work = Work()
    with pytest.raises(InvalidAnswer, match="No JSON object"):
        parse_answer('{"a": [' + "1 " * 3000 + "]}", "full", LIB, work=work)
    assert work.literal_chars == 0
    big = "{'a': [" + "1," * (MAX_LITERAL_CHARS // 2) + "], 'b': x}"
    with pytest.raises(InvalidAnswer, match=f"more than {MAX_LITERAL_CHARS} characters of objects that are not JSON"):
        parse_answer(big, "full", LIB)
    with pytest.raises(InvalidAnswer, match=f"mentions skills more than {MAX_MENTIONS} times"):
        parse_answer("so I will grasp " * (MAX_MENTIONS + 1), "unstructured", LIB)
    p = parse_answer("grasp is premature " * 10 + "so I will yaw_left", "unstructured", LIB)
    assert p.ste.skill == "yaw_left"


def test_an_answer_is_recorded_and_echoed_well_formed_and_bounded() -> None:
    """What a step records of an answer and what a re-prompt repeats of it can always be encoded, and a huge
    answer is cut (a step over a message's 1 MiB cap would be dropped by every subscriber)."""
    from services.reasoner.backends.base import ECHO_CHARS, echoed
    from services.reasoner.parse import MAX_ANSWER_CHARS, recorded_answer

    assert recorded_answer("x \ud83d") == echoed("x \ud83d") == "x \ufffd"
    huge = "y" * (3 * MAX_ANSWER_CHARS)
    assert recorded_answer(huge).startswith("y" * MAX_ANSWER_CHARS)
    assert recorded_answer(huge).endswith(f"[... {2 * MAX_ANSWER_CHARS} more characters not recorded]")
    assert len(echoed(huge)) < ECHO_CHARS + 80 and echoed("") == "(empty)"
