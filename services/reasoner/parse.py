"""Parse and validate a model answer into (DRT, STE) against the live skill library.

Strict JSON first; then what a lenient reader can recover: markdown code fences, text around the JSON,
trailing commas, single-quoted (Python-style) objects, and the case/spacing of skill names ("Yaw Right",
"obj localization"). Anything that still does not name one valid skill with valid arguments raises
InvalidAnswer with one specific sentence that is sent back to the model on re-prompt.

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

from services.reasoner.library import policy_skills
from services.reasoner.prompt import DRT_FIELDS
from shared.errors import InvalidAnswer
from shared.messages import MAX_QUERY_CHARS, DescriptiveReasoningTrace, SkillLibrary, SkillToExecute

_FENCE = re.compile(r"```[a-zA-Z0-9_-]*\s*\n?(.*?)```", re.S)
_TRAILING_COMMA = re.compile(r",\s*([}\]])")
_ALIASES = {"object_localization": "obj_localization", "obj_localisation": "obj_localization",
            "object_localisation": "obj_localization", "placement_localisation": "placement_localization"}


@dataclass(frozen=True)
class ParsedAnswer:
    drt: DescriptiveReasoningTrace
    ste: SkillToExecute
    recovered: bool = False
    """True when the lenient reader was needed (the answer was not strict JSON)."""


def norm_key(key: str) -> str:
    return re.sub(r"[\s\-]+", "_", str(key).strip().lower())


def norm_skill(name: str) -> str:
    """`"Yaw Right"` -> `yaw_right`; `"obj localization"` -> `obj_localization`."""
    s = re.sub(r"[\s\-]+", "_", str(name).strip().strip("`'\".").lower())
    s = re.sub(r"_+", "_", s)
    return _ALIASES.get(s, s)


def _matching_brace(text: str, start: int) -> int:
    """Index of the brace closing the one at `start`, skipping strings; -1 if unbalanced."""
    depth, in_str, quote, esc = 0, False, "", False
    for i in range(start, len(text)):
        c = text[i]
        if in_str:
            if esc:
                esc = False
            elif c == "\\":
                esc = True
            elif c == quote:
                in_str = False
        elif c in "\"'":
            in_str, quote = True, c
        elif c == "{":
            depth += 1
        elif c == "}":
            depth -= 1
            if depth == 0:
                return i
    return -1


def _loads_lenient(text: str) -> dict | None:
    for candidate in (text, _TRAILING_COMMA.sub(r"\1", text)):
        try:
            obj = json.loads(candidate)
            return obj if isinstance(obj, dict) else None
        except ValueError:
            pass
        try:  # single quotes, True/None: a Python literal
            obj = ast.literal_eval(candidate)
            if isinstance(obj, dict):
                return obj
        except (ValueError, SyntaxError, MemoryError, RecursionError):
            pass
    return None


def extract_json(raw: str) -> tuple[dict | None, bool, int]:
    """(object, recovered, start index of the JSON in raw) or (None, True, -1)."""
    text = raw.strip()
    try:
        obj = json.loads(text)
        if isinstance(obj, dict):
            return obj, False, raw.find("{")
    except ValueError:
        pass
    candidates = [m.group(1) for m in _FENCE.finditer(text)]
    for c in candidates:
        obj = _loads_lenient(c.strip())
        if obj is not None:
            return obj, True, raw.find(c)
    # Text around the JSON: try each '{' whose braces balance, outermost first.
    for m in re.finditer(r"\{", text):
        end = _matching_brace(text, m.start())
        if end < 0:
            continue
        obj = _loads_lenient(text[m.start(): end + 1])
        if obj is not None:
            return obj, True, raw.find(text[m.start(): end + 1])
    return None, True, -1


def _bare_skill(raw: str, names: list[str]) -> tuple[str, str | None] | None:
    """For the unstructured variant: the first skill named in free text, with `(arg)` or `: arg`."""
    text = raw.strip().strip("`").strip()
    norm = norm_skill(text.split("\n")[0].split("(")[0].split(":")[0])
    spaced = {n: re.compile(r"\b" + n.replace("_", r"[\s_-]?") + r"\b", re.I) for n in names}
    found: list[tuple[int, str]] = []
    if norm in names:
        found.append((0, norm))
    else:
        for n, rx in spaced.items():
            m = rx.search(text)
            if m:
                found.append((m.start(), n))
    if not found:
        return None
    pos, name = min(found)
    rest = text[pos:].split("\n")[0]
    m = re.search(r"\(([^)]*)\)", rest) or re.search(r":\s*(.+)$", rest)
    arg = m.group(1).strip().strip("'\"") if m else None
    return name, (arg or None)


def parse_answer(raw: str, variant: str, library: SkillLibrary, *, coverage: float = 1.0) -> ParsedAnswer:
    """Parse and validate one raw model answer. Raises InvalidAnswer with the reason."""
    if not raw or not raw.strip():
        raise InvalidAnswer("The answer is empty.")
    specs = {s.name: s for s in policy_skills(library)}
    names = list(specs)
    obj, recovered, start = extract_json(raw)
    thought: str | None = None
    if variant == "react" and start > 0:
        thought = _clean_thought(raw[:start])
    if obj is None:
        if variant == "unstructured":
            bare = _bare_skill(raw, names)
            if bare is None:
                raise InvalidAnswer(f"The answer names no skill; answer with one of: {', '.join(names)}.")
            return _validate(bare[0], bare[1], {}, variant, specs, coverage, True, thought)
        raise InvalidAnswer("No JSON object found in the answer; reply with exactly one JSON object in the "
                            "format given in the Rules.")
    obj = {norm_key(k): v for k, v in obj.items()}
    ste_obj = next((obj[k] for k in ("ste", "skill_to_execute") if isinstance(obj.get(k), dict)), None)
    ste = {norm_key(k): v for k, v in ste_obj.items()} if ste_obj is not None else obj
    drt_obj = next((obj[k] for k in ("drt", "descriptive_reasoning_trace") if isinstance(obj.get(k), dict)), None)
    drt = {norm_key(k): v for k, v in drt_obj.items()} if drt_obj is not None else obj
    skill = ste.get("skill", ste.get("action", ste.get("name")))
    if skill is None:
        raise InvalidAnswer("The answer has no skill: put {\"skill\": <name>, \"argument\": <string or null>} in "
                            "\"ste\".")
    if not isinstance(skill, str):
        raise InvalidAnswer(f"The skill must be a string naming one skill, got {json.dumps(skill)[:60]}.")
    arg = ste.get("argument", ste.get("arg", ste.get("query")))
    if "(" in skill and skill.rstrip().endswith(")") and arg is None:
        skill, _, inner = skill.partition("(")
        arg = inner.rstrip()[:-1].strip().strip("'\"") or None
    if thought and "reasoning" not in drt:
        drt = {**drt, "reasoning": thought}
    return _validate(skill, arg, drt, variant, specs, coverage, recovered, thought)


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
    if arg is not None and not isinstance(arg, str | int | float):
        raise InvalidAnswer(f"The argument of {skill} must be a string, got {type(arg).__name__}.")
    argument = str(arg).strip() if arg is not None else None
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
