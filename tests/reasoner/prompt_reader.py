"""What the fake VLM servers read: a PolicyContext rebuilt from a compiled prompt's text alone.

A test fake playing a VLM reads the prompt as a model would, so it may read text; the policy it then asks
(`RulesPolicy`) decides from the codes, facts and poses this reader finds, never from the prose.
"""

from __future__ import annotations

import json
import math
import re

from services.reasoner.backends.base import PastStep, PolicyContext, Seen
from services.reasoner.backends.rules import RulesPolicy, render_answer
from services.reasoner.backends.rules_parse import APPROACH, parse_command
from services.reasoner.drt import DRT_FIELDS
from shared import skills as S  # noqa: N812
from shared.messages import BASELINES, OutcomeCode, SkillFacts

BASELINE_MARKERS = {
    "saycan": '{"scores": [', "plan_once": '{"plan": [', "direct": "Answer with the skill only",
    "waypoint": "the next waypoint as one motion primitive",
}
"""A phrase of each baseline's Rules (services/reasoner/baselines.py) that tells the reader which one it is."""
_VEC = r"\((-?[\d.]+), (-?[\d.]+), (-?[\d.]+)\)"
_STEP_LINE = re.compile(r"^\s*#(\d+) ([a-z_]+)(?:\((.*?)\))? -> ([a-z]+)(?:; outcome: (.*)|: (.*))?$", re.M)
_OUTCOME = re.compile(r"^([a-z_]+) \((.*)\)$")
_SEEN_ITEM = re.compile(r"^(.+?) \[([a-z]+)(?:, ([\d.]+) x ([\d.]+) x ([\d.]+) m)?(?:, ([\d.]+) m away)?\]$")


def _facts(text: str) -> tuple[OutcomeCode | None, SkillFacts]:
    """The prompt's fixed outcome form back into a code and facts."""
    m = _OUTCOME.match(text.strip())
    if not m:
        return None, SkillFacts()
    kw: dict[str, object] = {}
    for part in m.group(2).split(", "):
        name, _, value = part.partition(" ")
        if name == "target":
            kw["target"] = value
        elif name == "attempts":
            kw["attempts"] = int(value)
        elif name == "holding":
            kw["holding"] = None if value == "none" else value
        elif name in ("distance", "reach", "offset", "gripper"):
            field = {"gripper": "gripper_width_m"}.get(name, f"{name}_m")
            kw[field] = float(value.removesuffix(" m"))
    return OutcomeCode(m.group(1)), SkillFacts(**kw)  # type: ignore[arg-type]


def _step(m: re.Match[str], block: str) -> PastStep:
    outcome, message = m.group(5) or "", m.group(6) or ""
    if not outcome:  # a recent step is written in full: its outcome and executor lines are below it
        om = re.search(r"^\s+outcome: (.*)$", block, re.M)
        outcome = om.group(1) if om else ""
    em = re.search(r"^\s+executor: (.*)$", block, re.M)
    message = em.group(1) if em else message
    code, facts = _facts(outcome)
    pose_m = re.search(_VEC + r", yaw (-?[\d.]+) deg", message)
    pose = (float(pose_m.group(1)), float(pose_m.group(2)), math.radians(float(pose_m.group(4)))) if pose_m else None
    found = re.search(_VEC, message) if m.group(2) in ("obj_localization", "placement_localization", "place") else None
    surface = re.search(r"surface z (-?[\d.]+)", message)
    return PastStep(m.group(2), m.group(3), m.group(4), message, code, facts, pose=pose,
                    found_at=(float(found.group(1)), float(found.group(2)), float(found.group(3))) if found else None,
                    surface_z=float(surface.group(1)) if surface else None)


def context_from_prompt(text: str) -> PolicyContext:
    """Rebuild the PolicyContext from a compiled prompt's text (what an HTTP fake VLM receives)."""
    sections = dict(re.findall(r"^# (Task command|Preamble|History|Skill Library|Rules)\n(.*?)(?=^# |\Z)", text,
                               re.M | re.S))
    if sections:
        command = sections.get("Task command", "").strip()
        lib = sections.get("Skill Library", "")
        rules = sections.get("Rules", "")
        history = sections.get("History", "")
        baseline = next((v for v, marker in BASELINE_MARKERS.items() if marker in rules), None)
        if baseline is not None:
            variant = baseline
        elif "Thought:" in rules:
            variant = "react"
        else:
            present = tuple(f for f in DRT_FIELDS["full"] if f'"{f}"' in rules)
            variant = next((v for v, fs in DRT_FIELDS.items() if fs == present and v not in ("unstructured", "react")),
                           "full")
    else:
        lib, _, command = text.removeprefix("Skills:\n").rpartition("\n\nCommand: ")
        command, rules, history, variant = command.strip(), "", "", "unstructured"
    skills = re.findall(r"^- ([a-z_]+)", lib, re.M)
    matches = list(_STEP_LINE.finditer(history))
    steps = [_step(m, history[m.end(): matches[i + 1].start() if i + 1 < len(matches) else len(history)])
             for i, m in enumerate(matches)]
    held_m = re.search(r"holding: ([^.\n]+)\.", history)
    held = held_m.group(1).strip() if held_m and held_m.group(1).strip() != "nothing" else None
    visible: list[Seen] = []
    seen_m = re.search(r"^Perception sees now: (.*)\.$", history, re.M)
    if seen_m and seen_m.group(1) != "nothing recognised":
        for item in seen_m.group(1).split("; "):
            seen = _SEEN_ITEM.match(item.strip())
            if not seen:
                continue
            vol = float(seen.group(3)) * float(seen.group(4)) * float(seen.group(5)) if seen.group(3) else None
            visible.append(Seen(seen.group(1), seen.group(2), vol, float(seen.group(6)) if seen.group(6) else None))
    objs = re.search(r"localized objects: (.*?)(?:\. |\.$|$)", history, re.M)
    places = re.search(r"placement spots: (.*?)(?:\. |\.$|$)", history, re.M)

    def labels(m: re.Match[str] | None) -> list[str]:
        return [x.split(" at (")[0].strip() for x in m.group(1).split("; ")] if m else []

    positions = {name: (float(px), float(py)) for name, px, py in
                 re.findall(r"(?:^|: |; )([^:;()]+?) at \((-?[\d.]+), (-?[\d.]+), -?[\d.]+\)", history, re.M)}
    pose_m = re.search(r"^Now: position \((-?[\d.]+), (-?[\d.]+), -?[\d.]+\) m, yaw (-?[\d.]+) deg", history, re.M)
    pose = (float(pose_m.group(1)), float(pose_m.group(2)), math.radians(float(pose_m.group(3)))) if pose_m else None
    return PolicyContext(command=command, variant=variant, skills=skills, steps=steps, held=held, visible=visible,
                         known_objects=labels(objs), known_placements=labels(places), pose=pose,
                         positions={k.strip(): v for k, v in positions.items()})


def answer_for_prompt(text: str) -> str:
    """The rules policy's answer to a compiled prompt, as a VLM would send it."""
    ctx = context_from_prompt(text)
    if ctx.variant in BASELINES:
        return baseline_answer(ctx, set(re.findall(r"^- ([a-z_]+)\(<", text, re.M)))
    skill, arg, why = RulesPolicy().decide(ctx)
    return render_answer(ctx, skill, arg, why)


def baseline_answer(ctx: PolicyContext, needs_argument: set[str]) -> str:
    """A Table III baseline's answer from the rules policy's decision on the prompt's context (a stand-in for a
    model in that framework's format, not the framework's behaviour):

    - direct: the decided skill only;
    - waypoint: the decided skill when it is a motion primitive offered, else done (no manipulation offered);
    - saycan: the decided skill and argument rated 0.9, every other offered skill 0.05 (a skill that needs an
      argument gets the command's target or destination);
    - plan_once: the command's motions (an approach as one forward step), then localize and grasp the target,
      localize the destination and place, then done: planned from the command, never re-planned."""
    decided = RulesPolicy().decide_full(ctx)
    if ctx.variant == "direct":
        return json.dumps({"skill": decided.skill, "argument": decided.argument})
    if ctx.variant == "waypoint":
        skill = decided.skill if decided.skill in ctx.skills else S.DONE
        return json.dumps({"ste": {"skill": skill, "argument": None}})
    plan = parse_command(ctx.command, ctx.skills)
    if ctx.variant == "saycan":
        scores = []
        for name in ctx.skills:
            if name == decided.skill:
                scores.append({"skill": name, "argument": decided.argument, "score": 0.9})
                continue
            arg = None
            if name in needs_argument:
                arg = (plan.destination if name == S.PLACEMENT_LOCALIZATION else plan.target) or "object"
            scores.append({"skill": name, "argument": arg, "score": 0.05})
        return json.dumps({"scores": scores})
    steps: list[dict] = [{"skill": S.FORWARD if m.startswith(APPROACH) else m, "argument": None}
                         for m in plan.motions if m.startswith(APPROACH) or m in ctx.skills]
    target = plan.target or (decided.argument if decided.skill == S.OBJ_LOCALIZATION else None)
    if target:
        steps += [{"skill": S.OBJ_LOCALIZATION, "argument": target}, {"skill": S.GRASP, "argument": target}]
        if plan.destination:
            steps += [{"skill": S.PLACEMENT_LOCALIZATION, "argument": plan.destination},
                      {"skill": S.PLACE, "argument": None}]
    steps.append({"skill": S.DONE, "argument": None})
    return json.dumps({"plan": steps})
