"""The JSON schema of a valid answer, for schema-constrained decoding (OpenAI-compatible `response_format`,
Anthropic structured outputs, vLLM/Ollama guided decoding).

Generated from the variant's DRT fields and the live skill library the reasoner received from the executor
(`executor/skills`), so a skill added to the executor is in the enum without any change here. Each skill's
argument rule is in the schema: one branch per rule (no argument: null; required: a non-blank string;
optional: string or null). The schema keeps to the subset OpenAI's strict mode accepts (every object closed
with `additionalProperties: false` and all properties required; `enum`, `anyOf`, `pattern`, no `minLength`),
which vLLM, Ollama and Anthropic accept too. The validator (parse.py) still checks every answer: a schema
is a decoding aid, not a trust boundary.
"""

from __future__ import annotations

from typing import Any

from services.reasoner.drt import DRT_FIELDS, FIELD_HELP
from services.reasoner.library import policy_skills
from shared.messages import BASELINES, SkillLibrary

SCHEMA_NAME = "aermani_answer"


def _closed(properties: dict[str, Any], description: str | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"type": "object", "properties": properties, "required": list(properties),
                           "additionalProperties": False}
    if description:
        out["description"] = description
    return out


def ste_schema(library: SkillLibrary) -> dict[str, Any]:
    """The Skill To Execute: one branch per argument rule, each with the enum of the skills that follow it."""
    none: list[str] = []
    required: list[str] = []
    optional: list[str] = []
    for spec in policy_skills(library):
        (none if spec.argument is None else required if spec.argument_required else optional).append(spec.name)
    branches = []
    if none:
        branches.append(_closed({"skill": {"type": "string", "enum": none},
                                 "argument": {"type": "null", "description": "these skills take no argument"}}))
    if required:
        branches.append(_closed({"skill": {"type": "string", "enum": required},
                                 "argument": {"type": "string", "pattern": r"\S",
                                              "description": "the object or surface query, e.g. red cup"}}))
    if optional:
        branches.append(_closed({"skill": {"type": "string", "enum": optional},
                                 "argument": {"type": ["string", "null"],
                                              "description": "optional object label, or null"}}))
    return branches[0] if len(branches) == 1 else {"anyOf": branches}


def answer_schema(variant: str, library: SkillLibrary) -> dict[str, Any]:
    """The schema of one answer in `variant`'s format. ReAct's constrained form is {"thought", "action"}
    (its free-text form is `Thought:` lines then `Action: {...}`); unstructured is a flat {"skill", "argument"}."""
    if variant in BASELINES:
        return baseline_schema(variant, library)
    ste = ste_schema(library)
    if variant == "unstructured":
        return ste if "anyOf" not in ste else _closed({"ste": ste})
    if variant == "react":
        return _closed({"thought": {"type": "string", "description": "your step-by-step reasoning"},
                        "action": ste})
    fields = DRT_FIELDS[variant]
    props: dict[str, Any] = {}
    if fields:
        drt: dict[str, Any] = {}
        for f in fields:
            if f == "action_predictions":
                drt[f] = _closed({s.name: {"type": "string"} for s in policy_skills(library)}, FIELD_HELP[f])
            else:
                drt[f] = {"type": "string", "description": FIELD_HELP[f]}
        props["drt"] = _closed(drt, "Descriptive Reasoning Trace")
    props["ste"] = ste
    return _closed(props)


def _candidate(ste: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    props = {**ste["properties"], **extra}
    return {"type": "object", "properties": props, "required": list(props), "additionalProperties": False}


def baseline_schema(variant: str, library: SkillLibrary) -> dict[str, Any]:
    """The answer schema of a baseline framework (services/reasoner/baselines.py), in the same strict subset."""
    ste = ste_schema(library)
    branches = ste.get("anyOf", [ste])
    if variant in ("direct", "waypoint"):
        return _closed({"ste": ste})
    if variant == "saycan":
        score = {"type": "number", "description": "usefulness of this skill now, 0 to 1"}
        items = [_candidate(b, {"score": score}) for b in branches]
        return _closed({"scores": {"type": "array", "items": items[0] if len(items) == 1 else {"anyOf": items}}})
    if variant == "plan_once":
        return _closed({"plan": {"type": "array", "items": ste}})
    raise ValueError(f"not a baseline variant: {variant!r}")
