"""Parse and validate a model answer into (DRT, STE) against the live skill library.

Strict JSON first; then what a lenient reader can recover: markdown code fences, text around the JSON,
trailing commas, single-quoted (Python-style) objects, and the case/spacing of skill names ("Yaw Right",
"obj localization"). Anything that still does not name one valid skill with valid arguments raises
InvalidAnswer with one specific sentence that is sent back to the model on re-prompt.

Bounded: at most MAX_ANSWER_CHARS characters, MAX_STRUCTURE brackets/quotes/backslashes and MAX_NESTING
bracket levels are read, one pass finds the candidate objects, each distinct candidate is decoded once, at
most MAX_DECODES candidates and MAX_LITERAL_CHARS characters of Python literals are read: the total work per
answer has a fixed ceiling (about 30 ms of CPU for the worst answer found, benchmarks/reasoner.py), not only a
linear one. Every failure, whatever the input, is an InvalidAnswer (re-prompted), never another exception.

Exact: ReAct takes the object after the last `Action:` line (never one quoted in the Thought); the
unstructured variant takes the skill the answer commits to, not the first one it mentions.

Decisions (documented in docs/reasoner.md):
- an argument given to a skill that takes none is ignored (dropped), not rejected: it cannot change
  what the skill does, and rejecting it would only inflate IAR;
- DRT fields the variant does not ask for are accepted and kept;
- action predictions must cover `coverage` (default 1.0: every skill, as the paper says) of the
  available skills; the error names the missing ones so one re-prompt usually fixes it;
- the unstructured variant may answer with a bare skill name (`yaw_left`, `obj_localization(red cup)`).
"""

from __future__ import annotations

import ast
import json
import re
from dataclasses import dataclass
from typing import Any

from services.reasoner.drt import DRT_FIELDS
from services.reasoner.library import policy_skills
from shared.errors import InvalidAnswer
from shared.messages import MAX_QUERY_CHARS, DescriptiveReasoningTrace, SkillLibrary, SkillToExecute
from shared.text import well_formed, well_formed_tree

_TRAILING_COMMA = re.compile(r",\s*([}\]])")
_ALIASES = {"object_localization": "obj_localization", "obj_localisation": "obj_localization",
            "object_localisation": "obj_localization", "placement_localisation": "placement_localization"}

MAX_ANSWER_CHARS = 32_000
"""Longest answer read: a full DRT/STE answer is 1-4 kB; anything longer is rejected with the reason."""
MAX_STRUCTURE = 4_000
"""Brackets, quotes and backslashes read per answer: a full answer has 100-300; each costs the bracket scan a
step of Python, so 32 kB of nothing but `{}` would cost 50-100 ms to scan."""
MAX_DECODES = 48
"""Candidate objects the lenient reader decodes per answer before it gives up (a real answer has a handful)."""
MAX_LITERAL_CHARS = 16_000
"""Characters the Python-literal reader (single quotes, True/None) is given per answer, over all candidates:
it costs about 1.5 us a character, against a few ns for the JSON decoder, so without this one 32 kB literal
read in both quoting modes and with and without its trailing commas took 0.2-0.4 s."""
MAX_MENTIONS = 256
"""Skill mentions the unstructured reader weighs per answer (each is a few regular-expression searches)."""
MAX_NESTING = 16
"""Deepest bracket nesting read: the answer format needs 3 levels (drt -> action_predictions -> value)."""
_SPECIAL = re.compile(r"[{}\[\]\"'\\]")
_STRUCTURE = "{}[]\"'\\"
_PYTHON_WORDS = re.compile(r"\b(True|False|None)\b")
_ACTION_LINE = re.compile(r"^[ \t>*#_`-]*action[ \t*_`]*:", re.I | re.M)


class Work:
    """Characters the parser examined for one answer (scans plus decoder input): the property test bounds
    it by a constant times the answer's length, which is what "linear time" means without a clock."""

    def __init__(self) -> None:
        self.chars = 0
        self.decodes = 0
        """Candidate objects handed to the lenient decoders: bounded by MAX_DECODES, since each decoder call
        has a fixed cost that thousands of tiny fragments (`{x:1} {x:1} ...`) would multiply."""
        self.literal_chars = 0
        """Characters given to the Python-literal reader so far: bounded by MAX_LITERAL_CHARS."""
        self.spans: dict[tuple[str, str], list[tuple[int, int]]] = {}
        """`_object_spans` results by (text, quoting mode): the depth check and the reader scan a text once."""
        self.decoded: dict[str, dict | None] = {}
        """`_loads_lenient` results by candidate text: a candidate met again (in the other quoting mode, or in a
        fenced block and then in the whole answer) is not decoded again."""


@dataclass(frozen=True)
class ParsedAnswer:
    """A model answer read into its reasoning trace (DRT) and the skill to execute (STE)."""

    drt: DescriptiveReasoningTrace
    ste: SkillToExecute
    recovered: bool = False
    """True when the lenient reader was needed (the answer was not strict JSON)."""
    scores: tuple[tuple[str, str | None, float], ...] = ()
    """SayCan-style variant: every (skill, argument, score) the model rated; `ste` is the top-rated one."""
    plan: tuple[SkillToExecute, ...] = ()
    """Plan-once variant: the whole plan; `ste` is its first step."""


def norm_key(key: str) -> str:
    return re.sub(r"[\s\-]+", "_", str(key).strip().lower())


def norm_skill(name: str) -> str:
    """`"Yaw Right"` -> `yaw_right`; `"obj localization"` -> `obj_localization`."""
    s = re.sub(r"[\s\-]+", "_", str(name).strip().strip("`'\".").lower())
    s = re.sub(r"_+", "_", s)
    return _ALIASES.get(s, s)


def _object_spans(text: str, quotes: str, work: Work) -> list[tuple[int, int]]:
    """Outermost balanced `{...}` spans of `text`, in order, found in one pass with a bracket stack.

    Quotes open strings only inside brackets (prose apostrophes are not strings); an unclosed `{` in the
    prose does not hide a later object, because every matched pair is recorded and the outermost ones kept.
    Raises InvalidAnswer when brackets nest deeper than MAX_NESTING."""
    known = work.spans.get((text, quotes))
    if known is not None:
        return known
    spans = work.spans[(text, quotes)] = _scan_spans(text, quotes, work)
    return spans


def _scan_spans(text: str, quotes: str, work: Work) -> list[tuple[int, int]]:
    stack: list[tuple[str, int]] = []
    pairs: list[tuple[int, int]] = []
    quote = ""
    skip = 0  # inside a string, the character after a backslash is escaped
    work.chars += len(text)
    for m in _SPECIAL.finditer(text):  # visits only brackets, quotes and backslashes
        i = m.start()
        c = text[i]
        if quote:
            if i < skip:
                continue
            if c == "\\":
                skip = i + 2
            elif c == quote:
                quote = ""
            continue
        if c == "{" or (c == "[" and stack):
            stack.append((c, i))
            if len(stack) > MAX_NESTING:
                raise InvalidAnswer(f"The answer nests brackets deeper than {MAX_NESTING} levels; reply with one "
                                    "flat JSON object in the format given in the Rules.")
        elif c == "}":
            while stack:  # a `[` left open inside an object is dropped with it
                kind, start = stack.pop()
                if kind == "{":
                    pairs.append((start, i + 1))
                    break
        elif c == "]":
            if stack and stack[-1][0] == "[":
                stack.pop()
        elif stack and c in quotes:
            quote = c
    return _outermost(pairs)


def _outermost(pairs: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """The outermost of matched `(start, end)` bracket pairs given in closing order, in text order."""
    # `pairs` is in closing order and brackets nest, so walking it backwards a pair is outermost exactly when it
    # ends before the start of the last outermost one kept (otherwise that one contains it): linear, no sort.
    out: list[tuple[int, int]] = []
    for start, end in reversed(pairs):
        if not out or end <= out[-1][0]:
            out.append((start, end))
    out.reverse()
    return out


def _loads_lenient(text: str, work: Work) -> dict | None:
    if ":" not in text:  # an object with no key-value pair (or `{x}`) is no answer: not worth a decoder call
        return None
    work.decodes += 1
    if work.decodes > MAX_DECODES:
        raise InvalidAnswer(f"The answer holds more than {MAX_DECODES} JSON-like fragments; reply with exactly one "
                            "JSON object in the format given in the Rules.")
    if text not in work.decoded:
        work.decoded[text] = _decode(text, work)
    return work.decoded[text]


def _decode(text: str, work: Work) -> dict | None:
    """The object `text` holds as JSON (trailing commas dropped if need be) or else as a Python literal."""
    for candidate in dict.fromkeys((text, _TRAILING_COMMA.sub(r"\1", text))):
        work.chars += len(candidate)
        try:
            obj = json.loads(candidate, strict=False)
            return obj if isinstance(obj, dict) else None
        except (ValueError, RecursionError):
            pass
    # Single quotes, True/None: a Python literal (which may end in trailing commas). Without a single quote or
    # one of those words JSON's failure is the literal's too, and the costly reader is not called.
    if "'" not in text and not _PYTHON_WORDS.search(text):
        return None
    work.chars += len(text)
    work.literal_chars += len(text)
    if work.literal_chars > MAX_LITERAL_CHARS:
        raise InvalidAnswer(f"The answer holds more than {MAX_LITERAL_CHARS} characters of objects that are not "
                            "JSON; reply with exactly one JSON object (double quotes) in the format given in the "
                            "Rules.")
    try:
        obj = ast.literal_eval(text)
    except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError):
        return None
    return obj if isinstance(obj, dict) else None


def _ste_of(obj: dict) -> tuple[Any, Any]:
    """(skill, argument) of an answer object whose keys are normalised: from the nested `ste` (or
    `skill_to_execute`, `action`) object, else from the answer itself (a flat `{"skill": ...}`)."""
    ste_obj = next((obj[k] for k in ("ste", "skill_to_execute", "action") if isinstance(obj.get(k), dict)), None)
    ste = {norm_key(k): v for k, v in ste_obj.items()} if ste_obj is not None else obj
    return ste.get("skill", ste.get("action", ste.get("name"))), ste.get("argument", ste.get("arg", ste.get("query")))


def _named_skill(obj: dict) -> tuple[str, str] | None:
    """(skill, argument) an object names the way `_parse` reads it, normalised for comparison; None if none."""
    skill, arg = _ste_of({norm_key(k): v for k, v in obj.items()})
    if not isinstance(skill, str):
        return None
    return norm_skill(skill), str(arg).strip().lower() if arg is not None else ""


def _first_object(text: str, work: Work) -> tuple[dict | None, int]:
    """The answer object among the outermost objects of `text` and its start, or (None, -1): the first object
    that names a skill (an object before it that names none, such as an example of a field, is passed over),
    else the first decodable one. When several name different skills the answer is ambiguous and rejected
    (never guessed: the model is asked for one object); several naming the same skill are one answer. Each
    character is in at most one outermost span, so the decoders read at most 2 x 2 x len(text) characters per
    quoting mode."""
    # 2nd pass: an apostrophe in an object is prose. Without one the modes scan alike: one scan (the depth check's).
    for quotes in ("\"'", "\"") if "'" in text else ("\"'",):
        first: tuple[dict, int] | None = None
        answer: tuple[dict, int] | None = None
        named: dict[tuple[str, str], None] = {}
        for start, end in _object_spans(text, quotes, work):
            obj = _loads_lenient(text[start:end], work)
            if obj is None:
                continue
            first = first or (obj, start)
            skill = _named_skill(obj)
            if skill is not None:
                named[skill] = None
                answer = answer or (obj, start)
        if len(named) > 1:
            which = ", ".join(f"{k}({a})" if a else k for k, a in named)
            raise InvalidAnswer(f"The answer holds {len(named)} JSON objects naming different skills ({which}); "
                                "reply with exactly one JSON object for the one skill to execute now.")
        chosen = answer or first
        if chosen is not None:
            return chosen
    return None, -1


def extract_json(raw: str, work: Work | None = None) -> tuple[dict | None, bool, int]:
    """(object, recovered, start index of the JSON in raw) or (None, True, -1). Linear in len(raw)."""
    work = work or Work()
    text = raw.strip()
    work.chars += len(raw)
    if text.startswith("{"):
        _object_spans(text, "\"'", work)  # depth check first: the decoders must never see deep nesting
        try:
            obj = json.loads(text)
            if isinstance(obj, dict):
                return obj, False, raw.find("{")
        except (ValueError, RecursionError):
            pass
    # Fenced blocks first (```json ... ```): the odd pieces of a split on the fence.
    pieces = text.split("```")
    for n in range(1, len(pieces) - 1, 2):
        obj, _ = _first_object(pieces[n], work)  # a language tag (json) before the object is prose
        if obj is not None:
            return obj, True, raw.find(pieces[n])
    obj, start = _first_object(text, work)
    if obj is None:
        return None, True, -1
    return obj, True, raw.index(text) + start


# ---------------------------------------------------------------- the unstructured variant: a skill in prose

# Cues in the words just before a mention. Strong cues state the answer; weak ones state an intention.
_STRONG = re.compile(r"(final answer|answer\s*(is)?\s*:?|action\s*:|skill\s*:|choice\s*:|decision\s*:|next skill"
                     r"( is)?\s*:?)\s*[`'\"*]*\s*$", re.I)
_WEAK = re.compile(r"\b(i\s*(will|'ll|shall|would|am going to|'m going to)( now)?( (choose|select|pick|use|execute|"
                   r"run|go with|do|perform))?|i (choose|select|pick|execute|run|go with)|let's|let me|(so|therefore"
                   r"|thus|hence)|next(,)?( i)?|(best|right|next) (skill|action|step)( is| would be)?|should|"
                   r"choose|select|execute|->|=>)\b[^.;!?\n]{0,24}$", re.I)
_NEG_BEFORE = re.compile(r"\b(not|no|never|instead of|rather than|avoid|n't|without|before|after|than)\s*[`'\"*]*$",
                         re.I)
_NEG_AFTER = re.compile(r"^[`'\"*)]*\s*(would|will|could|might|may|is|isn't|can't|cannot|won't|wouldn't)?\s*(be\s+)?"
                        r"(not|fail|fails|failed|hit|crash|collide|useless|pointless|impossible|blocked|premature|"
                        r"too early|unsafe|wrong|won't work|isn't possible)\b", re.I)
_INSTEAD_AFTER = re.compile(r"^[`'\"*)]*\s*instead\b", re.I)


def _skill_pattern(names: list[str]) -> re.Pattern[str]:
    """One alternation over every skill name and alias, longest first, spaces/hyphens for underscores."""
    spelled = {n: n for n in names}
    spelled.update({a: n for a, n in _ALIASES.items() if n in names})
    alts = sorted(spelled, key=len, reverse=True)
    return re.compile(r"(?<![\w-])(" + "|".join(a.replace("_", r"[\s_-]?") for a in alts) + r")(?![\w-])", re.I)


def _argument_after(text: str, end: int) -> str | None:
    """`(red cup)` or `: red cup` right after a mention (same line)."""
    rest = text[end: end + 2 * MAX_QUERY_CHARS].split("\n", 1)[0]
    m = re.match(r"\s*[`'\"]*\s*\(([^)]*)\)", rest) or re.match(r"\s*[`'\"]*\s*:\s*([^.;\n]+)", rest)
    if not m:
        return None
    return m.group(1).strip().strip("`'\"") or None


def _bare_skill(raw: str, names: list[str], work: Work) -> tuple[str, str | None]:
    """The skill an unstructured answer commits to: a first line that is a skill call; else the skill a
    strong cue names ("Final answer: yaw_left", last one wins); else the first skill an intention names
    ("... so I will yaw_left"), skipping negated mentions ("grasp would fail", "not grasp"); else the only
    skill mentioned. Several skills without a commitment is an invalid answer, never a guess."""
    text = raw.strip()
    work.chars += 4 * len(text)
    first_line = text.split("\n", 1)[0].strip().strip("`*").strip()
    head = re.match(r"[\w\s-]+", first_line)
    if head and norm_skill(head.group(0)) in names and len(first_line) <= len(head.group(0)) + MAX_QUERY_CHARS + 4:
        rest = first_line[head.end():].strip().rstrip(".")
        if not rest or rest.startswith(("(", ":")):
            return norm_skill(head.group(0)), _argument_after(first_line, head.end())
    mentions = []
    prev_end = 0
    for m in _skill_pattern(names).finditer(text):
        before = text[max(prev_end, m.start() - 80): m.start()]
        after = text[m.end(): m.end() + 40]
        negated = bool(_NEG_BEFORE.search(before[-24:]) or _NEG_AFTER.search(after))
        strong = bool(_STRONG.search(before[-40:]))
        weak = bool(_WEAK.search(before) or _INSTEAD_AFTER.search(after))
        mentions.append((norm_skill(m.group(0)), m.end(), negated, strong, weak))
        prev_end = m.end()
        if len(mentions) > MAX_MENTIONS:
            raise InvalidAnswer(f"The answer mentions skills more than {MAX_MENTIONS} times; answer with exactly "
                                "one skill, e.g. yaw_left or obj_localization(red cup).")
    if not mentions:
        raise InvalidAnswer(f"The answer names no skill; answer with one of: {', '.join(names)}.")
    live = [x for x in mentions if not x[2]]
    chosen = ([x for x in live if x[3]][-1:] or [x for x in live if x[4]][:1]
              or (live[:1] if len({x[0] for x in live}) == 1 else []))
    if not chosen:
        distinct = list(dict.fromkeys(x[0] for x in mentions))
        raise InvalidAnswer(f"The answer mentions {', '.join(distinct)} without committing to one; answer with "
                            "exactly one skill, e.g. yaw_left or obj_localization(red cup).")
    name, end = chosen[0][0], chosen[0][1]
    return name, _argument_after(text, end)


def _react_action(raw: str, work: Work) -> tuple[dict, str | None, bool]:
    """(the JSON object after the last `Action:` line, the Thought text before it, whether the lenient reader
    was needed). A JSON object inside the Thought is never taken for the action."""
    work.chars += len(raw)
    marks = list(_ACTION_LINE.finditer(raw))
    if not marks:
        obj, recovered, _ = extract_json(raw, work)
        if obj is not None and not recovered:
            return obj, None, False  # a bare JSON object is an action without thoughts
        raise InvalidAnswer("No 'Action:' line found; end with one line 'Action: {\"skill\": <name>, "
                            "\"argument\": <string or null>}'.")
    mark = marks[-1]
    tail = raw[mark.end():].strip()
    _object_spans(tail, "\"'", work)  # depth check first: the decoders must never see deep nesting
    try:  # the format asked for: nothing but the object after `Action:`
        strict = json.loads(tail)
        if isinstance(strict, dict):
            return strict, _clean_thought(raw[: mark.start()]), False
    except (ValueError, RecursionError):
        pass
    obj, _ = _first_object(tail, work)
    if obj is None:
        raise InvalidAnswer("The 'Action:' line has no JSON object; write 'Action: {\"skill\": <name>, "
                            "\"argument\": <string or null>}'.")
    return obj, _clean_thought(raw[: mark.start()]), True


def recorded_answer(raw: str) -> str:
    """A model's answer as a step records it (`ModelCall.raw_answer`): well formed (a lone surrogate would fail
    the step's publish) and at most the MAX_ANSWER_CHARS the parser reads, with the count of the rest, so that
    a step with every re-prompt's answer stays far below a message's 1 MiB cap (a larger one is dropped by every
    subscriber: the step would be missing from the log and the store)."""
    text = well_formed(raw)
    if len(text) > MAX_ANSWER_CHARS:
        text = f"{text[:MAX_ANSWER_CHARS]}\n[... {len(text) - MAX_ANSWER_CHARS} more characters not recorded]"
    return text


def parse_answer(raw: str, variant: str, library: SkillLibrary, *, coverage: float = 1.0,
                 work: Work | None = None) -> ParsedAnswer:
    """Parse and validate one raw model answer. Raises InvalidAnswer with the reason, and nothing else."""
    if not isinstance(raw, str) or not raw.strip():
        raise InvalidAnswer("The answer is empty.")
    raw = well_formed(raw)
    if len(raw) > MAX_ANSWER_CHARS:
        raise InvalidAnswer(f"The answer is {len(raw)} characters long, more than the {MAX_ANSWER_CHARS} read; "
                            "reply with one short answer in the format given in the Rules.")
    structure = sum(raw.count(c) for c in _STRUCTURE)
    if structure > MAX_STRUCTURE:
        raise InvalidAnswer(f"The answer holds {structure} brackets, quotes and backslashes, more than the "
                            f"{MAX_STRUCTURE} read (one answer needs a few hundred); reply with one flat JSON object "
                            "in the format given in the Rules.")
    work = work or Work()
    try:
        return _parse(raw, variant, library, coverage, work)
    except InvalidAnswer:
        raise
    except (RecursionError, MemoryError, ValueError, TypeError) as exc:  # a reader bug must not end the task
        raise InvalidAnswer(f"The answer could not be read ({type(exc).__name__}); reply with one JSON object "
                            "in the format given in the Rules.") from exc


def _parse(raw: str, variant: str, library: SkillLibrary, coverage: float, work: Work) -> ParsedAnswer:
    specs = {s.name: s for s in policy_skills(library)}
    names = list(specs)
    thought: str | None = None
    obj: dict | None
    if variant == "react":
        obj, thought, recovered = _react_action(raw, work)
    else:
        obj, recovered, _start = extract_json(raw, work)
    if variant in ("saycan", "plan_once"):
        if obj is None:
            raise InvalidAnswer("No JSON object found in the answer; reply with exactly one JSON object in the "
                                "format given in the Rules.")
        return _parse_baseline(well_formed_tree(obj), variant, specs, recovered)
    if obj is None:
        if variant == "unstructured":
            bare_skill, arg = _bare_skill(raw, names, work)
            return _validate(bare_skill, arg, {}, variant, specs, coverage, True, thought)
        raise InvalidAnswer("No JSON object found in the answer; reply with exactly one JSON object in the "
                            "format given in the Rules.")
    obj = {norm_key(k): v for k, v in well_formed_tree(obj).items()}  # its depth was bounded before decoding
    if variant == "react" and isinstance(obj.get("thought"), str) and not thought:
        thought = obj["thought"].strip() or None  # the schema-constrained form {"thought", "action"}
    skill, arg = _ste_of(obj)
    drt_obj = next((obj[k] for k in ("drt", "descriptive_reasoning_trace") if isinstance(obj.get(k), dict)), None)
    drt = {norm_key(k): v for k, v in drt_obj.items()} if drt_obj is not None else obj
    if skill is None:
        raise InvalidAnswer("The answer has no skill: put {\"skill\": <name>, \"argument\": <string or null>} in "
                            "\"ste\".")
    if not isinstance(skill, str):
        raise InvalidAnswer(f"The skill must be a string naming one skill, got {json.dumps(skill)[:60]}.")
    if "(" in skill and skill.rstrip().endswith(")") and arg is None:
        skill, _, inner = skill.partition("(")
        arg = inner.rstrip()[:-1].strip().strip("'\"") or None
    if thought and "reasoning" not in drt:
        drt = {**drt, "reasoning": thought}
    if variant == "direct":
        drt = {}  # RT-2-style: the skill only; any reasoning the model wrote anyway is not a trace
    return _validate(skill, arg, drt, variant, specs, coverage, recovered, thought)


def _parse_baseline(obj: dict, variant: str, specs: dict, recovered: bool) -> ParsedAnswer:
    """A SayCan answer (scores of every skill) or a plan-once answer (the plan), each skill checked like an STE."""
    from services.reasoner import baselines

    obj = {norm_key(k): v for k, v in obj.items()}

    def check(skill: object, arg: object) -> tuple[str, str | None]:
        if not isinstance(skill, str):
            raise InvalidAnswer(f"Each skill must be a string naming one skill, got {json.dumps(skill)[:60]}.")
        ste = _validate(skill, arg, {}, "no_drt", specs, 1.0, recovered, None).ste
        return ste.skill, ste.argument

    empty = DescriptiveReasoningTrace()
    if variant == "saycan":
        scores = baselines.read_scores(obj, check)
        lacking = [n for n in specs if n not in {s for s, _, _ in scores}]
        if lacking:
            raise InvalidAnswer(f"scores must rate every available skill; missing: {', '.join(lacking)}.")
        best = max(scores, key=lambda c: c[2])
        return ParsedAnswer(empty, SkillToExecute(skill=best[0], argument=best[1]), recovered, scores=tuple(scores))
    plan = tuple(SkillToExecute(skill=s, argument=a) for s, a in baselines.read_plan(obj, check))
    return ParsedAnswer(empty, plan[0], recovered, plan=plan)


def _clean_thought(text: str) -> str | None:
    lines = [re.sub(r"^\s*(thought|action)\s*:\s*", "", ln, flags=re.I) for ln in text.strip().splitlines()]
    out = " ".join(ln.strip() for ln in lines if ln.strip())
    return out or None


def _validate(skill_raw: str, arg: object, drt: dict, variant: str, specs: dict, coverage: float,
              recovered: bool, thought: str | None) -> ParsedAnswer:
    skill = norm_skill(skill_raw)
    recovered = recovered or skill != skill_raw
    spec = specs.get(skill)
    if spec is None:
        raise InvalidAnswer(f"Unknown skill {skill_raw!r}; choose exactly one of: {', '.join(specs)}.")
    if arg is not None and not isinstance(arg, str) and spec.argument is not None:
        # A number or a boolean is not a name of something to find: the docs promise a string or null.
        raise InvalidAnswer(f"The argument of {skill} must be a string or null, got {type(arg).__name__} "
                            f"{repr(arg)[:40]}.")
    argument = str(arg).strip() if isinstance(arg, str) else None
    if argument is not None and argument.lower() in ("", "null", "none", "n/a"):
        argument = None
    if spec.argument is None:
        argument = None  # a no-argument skill ignores one (see module docstring)
    elif spec.argument_required and not argument:
        raise InvalidAnswer(f"Skill {skill} needs an argument ({spec.argument}), e.g. "
                            f"{{\"skill\": \"{skill}\", \"argument\": \"red cup\"}}.")
    if argument and len(argument) > MAX_QUERY_CHARS:
        raise InvalidAnswer(f"The argument of {skill} is longer than {MAX_QUERY_CHARS} characters; give a short "
                            "query.")
    required = DRT_FIELDS.get(variant, ())
    missing = [f for f in required if not drt.get(f)]
    if missing:
        raise InvalidAnswer(f"Missing DRT field(s) required by the Rules: {', '.join(missing)}; put them in "
                            "\"drt\".")
    predictions = drt.get("action_predictions")
    preds: dict[str, str] | None = None
    if predictions is not None:
        preds = _predictions(predictions)
        if preds is None and "action_predictions" in required:
            raise InvalidAnswer("action_predictions must be an object mapping each skill name to its predicted "
                                "outcome.")
    if "action_predictions" in required and preds is not None:
        covered = {norm_skill(k) for k in preds} & set(specs)
        lacking = [n for n in specs if n not in covered]
        if len(covered) < coverage * len(specs) - 1e-9:
            raise InvalidAnswer(f"action_predictions must cover every available skill; missing: "
                                f"{', '.join(lacking)}.")

    def text(key: str) -> str | None:
        v = drt.get(key)
        if v is None:
            return None
        return v if isinstance(v, str) else json.dumps(v)

    trace = DescriptiveReasoningTrace(image_description=text("image_description"), summary=text("summary"),
                                      action_predictions=preds, reasoning=text("reasoning") or thought)
    return ParsedAnswer(trace, SkillToExecute(skill=skill, argument=argument), recovered)


def _predictions(value: object) -> dict[str, str] | None:
    if isinstance(value, dict):
        return {str(k): v if isinstance(v, str) else json.dumps(v) for k, v in value.items()}
    if isinstance(value, list):  # [{"skill": ..., "prediction": ...}] is a common alternative shape
        out = {}
        for item in value:
            if not isinstance(item, dict):
                return None
            item = {norm_key(k): v for k, v in item.items()}
            name = item.get("skill") or item.get("name")
            pred = item.get("prediction") or item.get("outcome") or item.get("predicted_outcome") or ""
            if not name:
                return None
            out[str(name)] = pred if isinstance(pred, str) else json.dumps(pred)
        return out
    return None
