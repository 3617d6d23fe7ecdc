"""Grounding check: what a step's Descriptive Reasoning Trace states, set against what the stack measured at
that step (docs/evaluation.md, "Grounding").

Three kinds of statement are read from the DRT's text fields (image description, summary, reasoning; the action
predictions are predictions, not statements about now):

- **seen**: an object the DRT says is in view (any object named in the image description; in the summary and the
  reasoning, an object named in a clause with a word of seeing: see, visible, in view, detected, spot). A clause
  with a negation ("I do not see the red cup", "no bottle in view") states the object's absence instead. Checked
  against the step's detections with the perception service's own query matching (services/perception/query.py:
  synonyms, plurals, colour words, families such as "snack"), so "mug" matches a detected cup and "red cup" does
  not match a purple one. The object the gripper holds counts as seen (it may be out of the camera's view).
- **held**: what the DRT says the gripper holds ("holding the red cup", "Holding: nothing", "the gripper is
  empty"), in a clause that speaks of now (no will, once, after, if, was...). Checked against the gripper's
  telemetry (contact sensing: holding or not) and the executor's working memory (which object).
- **position**: a named object placed at coordinates ("the red cup at (1.20, 0.30, 0.80)", or (x, y)). Checked
  against every position measured for that object (detection centroids, working-memory objects, placements and
  earlier sightings): a violation when none lies within `POSITION_TOL_M`. A position of an object with no
  measured position is not checked.

A step is checked when it has a DRT and something was measured; its violations each say which statement, which
measurement and why. Everything here is a pure function of the recorded step and observation.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

from services.perception.query import CATALOG, BadQuery, Candidate, match, parse, words
from shared.messages import Detection, ReasoningStep, Vec3

POSITION_TOL_M = 0.5
"""How far a stated position may lie from the nearest measured one (detection centroids are coarse)."""

# Object names that perception never reports as a detection: a statement about them cannot be checked.
UNCHECKED_NAMES = frozenset({"floor"})
# Head nouns that are also common verbs: an object only with a name word before them ("coke can", not "I can").
VERB_HEADS = frozenset({"can"})
FIELDS = ("image_description", "summary", "reasoning")
SEEING = frozenset({"see", "sees", "seeing", "saw", "visible", "view", "detected", "detect", "detects",
                    "spotted", "observe", "observed", "perception", "shows", "showing"})
NEGATIONS = frozenset({"no", "not", "nothing", "cannot", "can't", "don't", "doesn't", "isn't", "aren't", "never",
                       "without", "neither", "nor", "none", "missing", "absent", "lost"})
# A clause with one of these speaks of another time than now (a plan, a condition, the past).
NOT_NOW = frozenset({"will", "would", "should", "could", "once", "after", "before", "until", "if", "when", "then",
                     "need", "needs", "next", "was", "were", "had", "previously", "earlier", "going", "want",
                     "try", "able", "may", "might", "released", "placed", "dropped"})
_CLAUSE_SPLIT = re.compile(r"[.;!?,]\s|[.;!?]$|\s(?:and|but|so|while|whereas|although|though)\s", re.I)
_WORD = re.compile(r"[a-z']+")
_HOLD = re.compile(r"\b(?:holding|carrying|grasping|gripping|(?:gripper|i|it|drone|vehicle)\s+(?:holds|has|carries|"
                   r"contains|hold|carry))\b\s*:?\s*(?P<obj>.*)", re.I)
_HELD_BY = re.compile(r"(?P<obj>.+?)\s+(?:is|are)\s+(?:held|in\s+the\s+gripper|grasped)\b", re.I)
_EMPTY = re.compile(r"\b(?:gripper\s+(?:is\s+)?empty|empty[- ]handed|not\s+(?:holding|carrying)|"
                    r"(?:holding|holds|carrying)\s*:?\s*(?:nothing|none)\b|nothing\s+(?:is\s+)?"
                    r"(?:held|in\s+the\s+gripper))", re.I)
# Statements of absence, each with the object's phrase: "no red cup is in view", "I do not see a bottle", "the
# table is not detected". A negation elsewhere in a clause ("no spot on the visible table") states nothing about it.
_SEEN_WORD = r"(?:visible|in\s+view|detected|seen|recogni[sz]ed)"
_ABSENT = (
    re.compile(rf"^\s*(?:there\s+is\s+|there\s+are\s+)?no\s+(?P<obj>[a-z ]+?)\s+(?:is\s+|are\s+)?(?:yet\s+)?"
               rf"{_SEEN_WORD}", re.I),
    re.compile(r"\b(?:do|does|did|can)\s*(?:not|n't)\s+(?:see|detect|spot)\s+(?P<obj>[a-z ]+)", re.I),
    re.compile(r"\bcannot\s+(?:see|detect|spot)\s+(?P<obj>[a-z ]+)", re.I),
    re.compile(rf"(?P<obj>[a-z ]+?)\s+(?:is|are)\s+not\s+(?:yet\s+)?{_SEEN_WORD}", re.I),
)
_NUM = r"(-?\d+(?:\.\d+)?)"
_COORDS = re.compile(rf"\(\s*{_NUM}\s*,\s*{_NUM}\s*(?:,\s*{_NUM}\s*)?\)")

Kind = Literal["not_detected", "detected_but_denied", "holds_nothing", "holds_other", "holds_something",
               "position"]


@dataclass(frozen=True)
class StepObservation:
    """What the stack measured when a step observed (None: not measured, or not in the log)."""

    detections: tuple[Detection, ...] | None = None
    """The detections the step's decision saw."""
    held_object: str | None = None
    """What the executor's working memory says the gripper holds."""
    memory_known: bool = False
    """Whether the working memory was there (else `held_object` None means unknown, not empty)."""
    gripper_holding: bool | None = None
    """The gripper's own telemetry (contact sensing): holding something or not; None when not reported."""
    position: Vec3 | None = None
    """The vehicle's position."""
    positions: tuple[tuple[str, float, float, float], ...] = ()
    """(label, x, y, z) of every measured object position: detection centroids and working memory."""
    source: str = ""
    """Where these measurements come from (the log's streams, or the prompt the model was shown)."""


@dataclass(frozen=True)
class Violation:
    """One DRT statement that contradicts a measurement."""

    kind: Kind
    field: str
    """The DRT field the statement is in."""
    claim: str
    """The statement's words (model text: data, escape it when rendering)."""
    reason: str


@dataclass
class StepGrounding:
    """The grounding check of one step: whether it could be checked, how many statements, which contradict."""

    step: int
    checked: bool
    claims: int = 0
    violations: list[Violation] = field(default_factory=list)

    @property
    def violated(self) -> bool:
        return bool(self.violations)

    def as_dict(self) -> dict[str, Any]:
        return {"step": self.step, "checked": self.checked, "claims": self.claims,
                "violations": [asdict(v) for v in self.violations]}


@dataclass(frozen=True)
class _Mention:
    phrase: str
    clause: str


def _clauses(text: str) -> list[str]:
    return [c.strip() for c in _CLAUSE_SPLIT.split(text) if c and c.strip()]


def _raw_words(clause: str) -> set[str]:
    return set(_WORD.findall(clause.lower()))


class _Names:
    """The object names a statement may use (the simulator's catalogue, the detections, the working memory), with
    their folded words for finding them in free text."""

    def __init__(self, names: Iterable[str]) -> None:
        self.names = sorted({n for n in (*CATALOG, *names) if n})
        self.label_words = {n: words(n) for n in self.names}
        self.heads = {lw[-1] for lw in self.label_words.values() if lw}
        from services.perception.query import COLOR_WORDS, FAMILIES, SIZE_WORDS

        self.heads |= set(FAMILIES)
        self.modifiers = set(COLOR_WORDS) | set(SIZE_WORDS) | {w for lw in self.label_words.values() for w in lw}

    def mentions(self, clause: str) -> list[str]:
        """The object phrases of a clause: each head noun with the name and colour words before it."""
        toks = words(clause)
        out: list[str] = []
        for i, tok in enumerate(toks):
            # a head noun followed by another ("soda can", "orange box") is a modifier of the later one
            if tok not in self.heads or (i + 1 < len(toks) and toks[i + 1] in self.heads):
                continue
            j = i
            while j > 0 and i - j < 3 and toks[j - 1] in self.modifiers:
                j -= 1
            if j == i and tok in VERB_HEADS:
                continue
            out.append(" ".join(toks[j:i + 1]))
        return out

    def matches(self, phrase: str, labels: Sequence[str], strict: bool = False) -> bool | None:
        """Whether `phrase` names one of `labels` by the perception's matching (ambiguous counts: it names
        several), or names one less precisely ("table" for a detected "round table"); None when the phrase
        names nothing perception knows. `strict`: the perception's matching alone (for statements of absence:
        "no table" is true when only a "round table" is detected, as perception would answer a "table" query)."""
        said = set(words(phrase))
        if not strict and any(said <= set(self.label_words.get(lab) or words(lab)) for lab in labels):
            return True
        try:
            q = parse(phrase)
        except BadQuery:
            return None
        cands = [Candidate(i, lab, "object") for i, lab in enumerate(labels)]
        try:
            m = match(q, cands, self.names, categories=("object",))
        except BadQuery:
            return None
        return m.reason in ("ok", "ambiguous")

    def unchecked(self, phrase: str) -> bool:
        return set(phrase.split()) <= UNCHECKED_NAMES


def _texts(step: ReasoningStep) -> list[tuple[str, str]]:
    drt = step.drt
    if drt is None:
        return []
    return [(f, v) for f in FIELDS if (v := getattr(drt, f, None))]


def _is_hold_clause(clause: str) -> bool:
    return bool(_HOLD.search(clause) or _HELD_BY.search(clause) or _EMPTY.search(clause))


def _seen_violations(names: _Names, texts: list[tuple[str, str]], obs: StepObservation) -> tuple[int, list[Violation]]:
    if obs.detections is None:
        return 0, []
    detected = [d.label for d in obs.detections]
    present = [*detected, *([obs.held_object] if obs.held_object else [])]
    claims = 0
    out: list[Violation] = []
    for fld, text in texts:
        for clause in _clauses(text):
            raw = _raw_words(clause)
            if _is_hold_clause(clause) or (fld != "image_description" and not raw & SEEING):
                continue
            absent = next((m for rx in _ABSENT if (m := rx.search(clause))), None)
            if absent is not None:
                for phrase in names.mentions(absent.group("obj")):
                    found = names.matches(phrase, detected, strict=True)
                    if found is None or names.unchecked(phrase):
                        continue
                    claims += 1
                    if found:
                        out.append(Violation("detected_but_denied", fld, clause,
                                             f"says no '{phrase}' is in view; perception detects "
                                             f"{_list(detected)}"))
                continue
            if raw & NEGATIONS or (fld != "image_description" and raw & NOT_NOW):
                continue  # a negation that states no absence, or another time than now
            for phrase in names.mentions(clause):
                if names.unchecked(phrase):
                    continue
                found = names.matches(phrase, present)
                if found is None:
                    continue
                claims += 1
                if not found:
                    out.append(Violation("not_detected", fld, clause,
                                         f"says it sees '{phrase}'; perception detects {_list(detected)}"))
    return claims, out


def _measured_holding(obs: StepObservation) -> bool | None:
    if obs.gripper_holding is not None:
        return obs.gripper_holding
    if obs.memory_known:
        return obs.held_object is not None
    return None


def _measured_text(obs: StepObservation) -> str:
    parts = []
    if obs.gripper_holding is not None:
        parts.append(f"gripper telemetry: {'holding' if obs.gripper_holding else 'empty'}")
    if obs.memory_known:
        parts.append(f"working memory: {obs.held_object or 'nothing'}")
    return "; ".join(parts)


def _held_violations(names: _Names, texts: list[tuple[str, str]], obs: StepObservation) -> tuple[int, list[Violation]]:
    holding = _measured_holding(obs)
    if holding is None:
        return 0, []
    claims = 0
    out: list[Violation] = []
    for fld, text in texts:
        for clause in _clauses(text):
            raw = _raw_words(clause)
            if raw & NOT_NOW:
                continue
            if _EMPTY.search(clause):
                claims += 1
                if holding:
                    out.append(Violation("holds_something", fld, clause,
                                         f"says the gripper is empty; {_measured_text(obs)}"))
                continue
            m = _HOLD.search(clause) or _HELD_BY.search(clause)
            if m is None or raw & NEGATIONS:
                continue
            claims += 1
            said = names.mentions(m.group("obj"))
            if not holding:
                what = f"'{said[0]}'" if said else "something"
                out.append(Violation("holds_nothing", fld, clause,
                                     f"says the gripper holds {what}; {_measured_text(obs)}"))
            elif said and obs.held_object and not names.matches(said[0], [obs.held_object]):
                out.append(Violation("holds_other", fld, clause,
                                     f"says the gripper holds '{said[0]}'; {_measured_text(obs)}"))
    return claims, out


def _position_violations(names: _Names, texts: list[tuple[str, str]],
                         obs: StepObservation) -> tuple[int, list[Violation]]:
    if not obs.positions:
        return 0, []
    labels = sorted({p[0] for p in obs.positions})
    claims = 0
    out: list[Violation] = []
    for fld, text in texts:
        for m in _COORDS.finditer(text):
            head = re.split(r"[.;!?]\s", text[:m.start()])[-1]
            said = names.mentions(head)
            if not said:
                continue  # "it was seen at (...)": no object named
            phrase = said[-1]
            meant = [lab for lab in labels if names.matches(phrase, [lab])]
            if not meant:
                continue  # no measured position for that object: not checked
            claims += 1
            x, y = float(m.group(1)), float(m.group(2))
            z = float(m.group(3)) if m.group(3) is not None else None
            best = min(math.dist((x, y, *(() if z is None else (z,))), (px, py, *(() if z is None else (pz,))))
                       for lab, px, py, pz in obs.positions if lab in meant)
            if best > POSITION_TOL_M:
                out.append(Violation("position", fld, f"{head.strip()} {m.group(0)}",
                                     f"says '{phrase}' is at {m.group(0)}; the nearest measured position of "
                                     f"{_list(meant)} is {best:.2f} m away (tolerance {POSITION_TOL_M} m)"))
    return claims, out


def _list(labels: Sequence[str]) -> str:
    return ", ".join(sorted(set(labels))) if labels else "nothing"


def check_step(step: ReasoningStep, obs: StepObservation | None) -> StepGrounding:
    """The grounding check of one step against what was measured when it observed."""
    texts = _texts(step)
    if not texts or obs is None:
        return StepGrounding(step.step, checked=False)
    known = [d.label for d in obs.detections or ()] + [p[0] for p in obs.positions]
    if obs.held_object:
        known.append(obs.held_object)
    names = _Names(known)
    claims = 0
    violations: list[Violation] = []
    for part in (_seen_violations, _held_violations, _position_violations):
        n, v = part(names, texts, obs)
        claims += n
        violations += v
    return StepGrounding(step.step, checked=True, claims=claims, violations=violations)


def check_steps(steps: Iterable[tuple[ReasoningStep, StepObservation | None]]) -> list[StepGrounding]:
    """The grounding check of every step of a run, in order."""
    return [check_step(s, o) for s, o in steps]


def violation_rate(results: Iterable[StepGrounding]) -> float | None:
    """Percentage of checked steps with at least one violation (None: no step could be checked)."""
    checked = [r for r in results if r.checked]
    return 100.0 * sum(r.violated for r in checked) / len(checked) if checked else None
