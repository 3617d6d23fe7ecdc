"""The prompt compiler: P_t = {L, Preamble, History, Skill Library, Rules} for each paper variant.

Parts are plain text with fixed section headers so that every backend (and the fake VLM used in tests)
sees exactly the same prompt; `CompiledPrompt.parts` is what the reasoning step records.

Layout for prompt caches (vLLM prefix caching, OpenAI automatic caching, Anthropic `cache_control`): the
parts that depend only on the variant and the skill library (Preamble, Skill Library, Rules) come first
and are byte-identical across the steps and tasks of a vehicle (`CompiledPrompt.prefix`); the task
command, the History with the current observation, and the image come after (`suffix`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

from services.reasoner.drt import DRT_FIELDS, FIELD_HELP
from services.reasoner.library import library_text, policy_skills
from shared.messages import Detection, OutcomeCode, SkillLibrary, SkillOutcome, VehicleState, WorkingMemory

# Which prompt parts and DRT fields each variant has (paper Table IV; react is the ReAct baseline).
PROMPT_PARTS: dict[str, tuple[str, ...]] = {
    "unstructured": ("command", "skill_library"),
    "no_drt": ("command", "preamble", "history", "skill_library", "rules"),
    "drt_v1": ("command", "preamble", "history", "skill_library", "rules"),
    "drt_v2": ("command", "preamble", "history", "skill_library", "rules"),
    "drt_v3": ("command", "preamble", "history", "skill_library", "rules"),
    "full": ("command", "preamble", "history", "skill_library", "rules"),
    "react": ("command", "preamble", "history", "skill_library", "rules"),
    # The Table III baselines (baselines.py): RT-2-style direct action has no preamble.
    "saycan": ("command", "preamble", "history", "skill_library", "rules"),
    "direct": ("command", "history", "skill_library", "rules"),
    "waypoint": ("command", "preamble", "history", "skill_library", "rules"),
    "plan_once": ("command", "preamble", "history", "skill_library", "rules"),
}
CONSTANT_PARTS = ("preamble", "skill_library", "rules")
"""Parts that depend only on the variant and the skill library: the cacheable prefix, in this order."""
FREE_TEXT_BASELINES = ("unstructured", "react")
"""The variants `free_text_baselines` decodes as free text (no answer schema), as the paper did."""
SECTION_TITLES = {
    "command": "Task command",
    "preamble": "Preamble",
    "history": "History",
    "skill_library": "Skill Library",
    "rules": "Rules",
}

PREAMBLE = (
    "You are the high-level policy of an aerial manipulator: a multirotor running PX4 with a two-finger gripper "
    "under its body and an RGB-D camera looking forward and 35 degrees down. At each step you receive the "
    "current camera image and this prompt, and you choose exactly ONE skill from the Skill Library. The skill "
    "runs as a predefined, flight-safe routine until it terminates (succeeded, failed, timeout or rejected); "
    "its outcome is then added to the History and you are asked again. You never control the motors directly. "
    "To pick an object: localize it with obj_localization, then grasp. To place it: localize the surface with "
    "placement_localization, then place. Use motion skills to search when the target is not visible or to "
    "approach it. Answer done when the command is complete."
)



@dataclass
class HistoryEntry:
    """One executed step as the History remembers it."""

    step: int
    skill: str
    argument: str | None
    state: str
    message: str = ""
    perceived: str = ""
    summary: str = ""
    reasoning: str = ""
    outcome: SkillOutcome | None = None
    """The executor's outcome (its code and facts); None for a step the loop recorded itself."""
    image_description: str = ""
    """The step's DRT image description (shown only in the paper's History, `paper_history`)."""
    prediction: str = ""
    """The DRT's predicted outcome of the chosen skill (shown only in the paper's History)."""

    def call(self) -> str:
        return f"{self.skill}({self.argument})" if self.argument else self.skill

    def condensed(self) -> str:
        if self.outcome is None or self.outcome.code is None:  # the loop's own entries: only their message
            msg = f": {_clip(self.message, 60)}" if self.message and self.state != "succeeded" else ""
            return f"#{self.step} {self.call()} -> {self.state}{msg}"
        out = f"; outcome: {outcome_text(self.outcome)}" if self.outcome.code != OutcomeCode.SUCCEEDED else ""
        return f"#{self.step} {self.call()} -> {self.state}{out}"

    def full(self) -> str:
        lines = [f"#{self.step} {self.call()} -> {self.state}"]
        if self.outcome is not None and self.outcome.code is not None:
            lines.append(f"   outcome: {outcome_text(self.outcome)}")
        if self.message:
            lines.append(f"   executor: {_clip(self.message, 200)}")
        if self.perceived:
            lines.append(f"   perceived: {_clip(self.perceived, 200)}")
        if self.summary:
            lines.append(f"   your summary: {_clip(self.summary, 160)}")
        if self.reasoning:
            lines.append(f"   your reasoning: {_clip(self.reasoning, 160)}")
        return "\n".join(lines)

    def paper(self) -> str:
        """The step as the paper's History holds it (Algorithm 1: H <- H u {DRT_t, a_t}): the action with its
        termination status, then the step's own reasoning trace; no executor message or perception."""
        lines = [f"#{self.step} {self.call()} -> {self.state}"]
        for name, text in (("image description", self.image_description), ("summary", self.summary),
                           ("predicted outcome", self.prediction), ("reasoning", self.reasoning)):
            if text:
                lines.append(f"   your {name}: {_clip(text, 200)}")
        return "\n".join(lines)


def outcome_text(outcome: SkillOutcome) -> str:
    """A skill's outcome in the prompt's one fixed form: `missed (target red cup, attempts 2, offset 0.031 m,
    holding none)`; only the facts the skill measured appear, always in this order (`upright` or `fallen over`
    when a grasp or place measured it), `holding` always."""
    f = outcome.facts
    parts: list[str] = []
    if f.target:
        parts.append(f"target {_clip(f.target, 40)}")
    if f.attempts:
        parts.append(f"attempts {f.attempts}")
    for name, value in (("distance", f.distance_m), ("reach", f.reach_m), ("offset", f.offset_m),
                        ("gripper", f.gripper_width_m)):
        if value is not None:
            parts.append(f"{name} {value:.3f} m")
    if f.upright is not None:
        parts.append("upright" if f.upright else "fallen over")
    parts.append(f"holding {_clip(f.holding, 40) if f.holding else 'none'}")
    code = outcome.code.value if outcome.code is not None else "running"
    return f"{code} ({', '.join(parts)})"


def _clip(text: str, n: int) -> str:
    text = " ".join(text.split())
    return text if len(text) <= n else text[: n - 3] + "..."


@dataclass
class Observation:
    """o_t: the current image and vehicle state, plus what perception and the executor know now."""

    image_jpeg: bytes | None = None
    image_stamp_ns: int = 0
    state: VehicleState | None = None
    state_age_s: float = 0.0
    """How long ago (this host's clock) `state` arrived: a silent bridge leaves an old state behind."""
    detections: tuple[Detection, ...] = ()
    memory: WorkingMemory | None = None
    frame_wait_s: float = 0.0
    """How long the observation waited for a colour frame newer than the previous skill's end (StepTiming)."""
    detections_wait_s: float = 0.0
    """... for detections newer than it."""
    state_wait_s: float = 0.0
    """... for a vehicle state newer than it."""


@dataclass
class CompiledPrompt:
    """A prompt ready to send: its parts, the constant prefix and per-step suffix, and the camera image."""

    variant: str
    parts: dict[str, str]
    text: str
    """The whole prompt text: `prefix + suffix`."""
    image_jpeg: bytes | None = None
    prefix: str = ""
    """The constant head of `text` (Preamble, Skill Library, Rules): identical for every step and task of a
    vehicle with this variant and skill library, so prompt caches reuse it."""
    schema: dict | None = None
    """JSON schema of a valid answer for schema-constrained decoding (schema.py)."""

    @property
    def suffix(self) -> str:
        return self.text[len(self.prefix):]

    @property
    def has_image(self) -> bool:
        return self.image_jpeg is not None


def describe_state(obs: Observation) -> str:
    st = obs.state
    held = (obs.memory.held_object if obs.memory else None) or "nothing"
    if st is None:
        return f"Now: vehicle pose unknown, holding: {held}."
    p = st.position
    return (f"Now: position ({p.x:.2f}, {p.y:.2f}, {p.z:.2f}) m, yaw {math.degrees(st.yaw):.0f} deg, "
            f"{st.landed_state.value}, holding: {held}.")


def describe_detections(obs: Observation) -> str:
    if not obs.detections:
        return "Perception sees now: nothing recognised."
    items = []
    pos = obs.state.position if obs.state else None
    for d in obs.detections[:20]:
        extra: list[str] = [d.category]
        if d.size is not None:
            extra.append(f"{d.size.x:.2f} x {d.size.y:.2f} x {d.size.z:.2f} m")
        if d.centroid is not None and pos is not None:
            dist = math.dist((d.centroid.x, d.centroid.y, d.centroid.z), (pos.x, pos.y, pos.z))
            extra.append(f"{dist:.1f} m away")
        items.append(f"{d.label} [{', '.join(extra)}]")
    return "Perception sees now: " + "; ".join(items) + "."


class History:
    """The bounded History buffer H: last K steps in full, older ones condensed, character budget enforced."""

    def __init__(self, full_steps: int = 6, max_chars: int = 6000, *, paper: bool = False) -> None:
        self.full_steps = full_steps
        self.max_chars = max_chars
        self.paper = paper
        """The paper's History (`paper_history`): the DRT and action of each step only; no vehicle state, live
        detections or working memory."""
        self.entries: list[HistoryEntry] = []

    def append(self, entry: HistoryEntry) -> None:
        self.entries.append(entry)

    def extended(self, entry: HistoryEntry) -> History:
        """A copy with `entry` appended (this one unchanged): the History a speculative step is asked with."""
        other = History(self.full_steps, self.max_chars, paper=self.paper)
        other.entries = [*self.entries, entry]
        return other

    def __len__(self) -> int:
        return len(self.entries)

    def render(self, obs: Observation) -> str:
        """Executed steps first (oldest first), the current observation last: between two steps the text up to
        the newest entries repeats, so a prefix cache reuses it (vLLM, OpenAI automatic caching)."""
        if self.paper:
            return self._render_paper()
        head = [describe_state(obs), describe_detections(obs)]
        if obs.memory is not None:
            head.append("Working memory: " + memory_summary(obs.memory))
        head_text = "\n".join(head)
        if not self.entries:
            return _fit_tail("No skill executed yet.", head_text, self.max_chars)
        # Budget: keep as many full entries as fit (at least the last one), then fill what is left with
        # condensed lines, newest first; whatever does not fit is counted as omitted. Linear in what fits.
        reserve = 60  # "Earlier steps:" and "(N earlier steps omitted)"
        n_full = min(self.full_steps, len(self.entries))
        while True:
            full = [e.full() for e in self.entries[len(self.entries) - n_full:]] if n_full else []
            base = len(head_text) + len("\nRecent steps:") + sum(len(f) + 1 for f in full)
            if base + reserve <= self.max_chars or n_full <= 1:
                break
            n_full -= 1
        room = self.max_chars - base - reserve
        condensed: list[str] = []
        for e in reversed(self.entries[: len(self.entries) - n_full]):
            line = "  " + e.condensed()
            if len(line) + 1 > room:
                break
            condensed.append(line)
            room -= len(line) + 1
        condensed.reverse()
        omitted = len(self.entries) - n_full - len(condensed)
        body = []
        if omitted:
            body.append(f"({omitted} earlier steps omitted)")
        if condensed:
            body.append("Earlier steps:")
            body.extend(condensed)
        body.append("Recent steps:")
        body.extend(full)
        return _fit_tail("\n".join(body), head_text, self.max_chars)


    def _render_paper(self) -> str:
        """Every step in the paper's form, the oldest cut first to stay within the budget."""
        if not self.entries:
            return "No skill executed yet."
        blocks = [e.paper() for e in self.entries]
        kept: list[str] = []
        room = self.max_chars - 40  # "(N earlier steps omitted)"
        for b in reversed(blocks):
            if len(b) + 1 > room and kept:
                break
            kept.append(_fit(b, room))
            room -= len(kept[-1]) + 1
        kept.reverse()
        omitted = len(blocks) - len(kept)
        return "\n".join(([f"({omitted} earlier steps omitted)"] if omitted else []) + kept)


def _fit_tail(body: str, tail: str, n: int) -> str:
    """body + tail within n characters, cutting the start of the body (the oldest steps), never the tail."""
    text = f"{body}\n{tail}"
    if len(text) <= n:
        return text
    if len(tail) + 4 >= n:
        return _fit(tail, n)
    keep = n - len(tail) - 4  # "..." + "\n"
    return "..." + body[len(body) - keep:] + "\n" + tail


def _fit(text: str, n: int) -> str:
    return text if len(text) <= n else text[: n - 3] + "..."


def rules_text(variant: str, library: SkillLibrary) -> str:
    from services.reasoner import baselines

    if baselines.is_baseline(variant):
        return baselines.rules_text(variant, library)
    names = [s.name for s in policy_skills(library)]
    if variant == "react":
        return (
            "Think step by step first: write your reasoning as lines starting with 'Thought:'. Then write one line "
            "'Action:' followed by exactly one JSON object {\"skill\": <skill name>, \"argument\": <string or null>}.\n"
            f"- skill must be one of: {', '.join(names)}.\n"
            "- argument is the object or surface query for obj_localization / placement_localization, "
            "optionally the object label for grasp, and null for every other skill.\n"
            "- Choose exactly one skill. Answer done only when the command is complete."
        )
    fields = DRT_FIELDS[variant]
    example: dict = {}
    if fields:
        drt = {}
        for f in fields:
            drt[f] = dict.fromkeys(names, "<predicted outcome>") if f == "action_predictions" else f"<{FIELD_HELP[f]}>"
        example["drt"] = drt
    example["ste"] = {"skill": "<one skill name>", "argument": "<string or null>"}
    lines = [
        "Answer with exactly one JSON object and nothing else (no markdown, no comments), in this format:",
        json.dumps(example, indent=1),
    ]
    if fields:
        lines.append("The \"drt\" object is your Descriptive Reasoning Trace; fill every field:")
        lines.extend(f"- {f}: {FIELD_HELP[f]}." for f in fields)
        if "action_predictions" in fields:
            lines.append("- action_predictions must have an entry for EVERY skill: " + ", ".join(names) + ".")
    lines += [
        "The \"ste\" object is the Skill To Execute:",
        f"- skill must be exactly one of: {', '.join(names)}.",
        "- argument is the object query for obj_localization (e.g. \"red cup\"), the surface query for "
        "placement_localization (e.g. \"table\"), optionally the object label for grasp, and null otherwise.",
        "- Choose one skill per answer. Do not repeat a skill that just failed without a reason to expect a "
        "different result. Answer done only when the command is complete.",
    ]
    return "\n".join(lines)


def layout(variant: str, parts: dict[str, str]) -> tuple[str, str]:
    """(constant prefix, whole text) of a prompt from its parts: Preamble, Skill Library and Rules first (they
    depend only on the variant and the skill library), then the command and the History."""
    if variant == "unstructured":
        prefix = f"Skills:\n{parts['skill_library']}\n\n"
        return prefix, prefix + f"Command: {parts['command']}"
    wanted = PROMPT_PARTS[variant]
    prefix = "".join(f"# {SECTION_TITLES[k]}\n{parts[k]}\n\n" for k in CONSTANT_PARTS if k in wanted)
    rest = "\n\n".join(f"# {SECTION_TITLES[k]}\n{parts[k]}" for k in wanted if k not in CONSTANT_PARTS)
    return prefix, prefix + rest


class PromptCompiler:
    """Builds P_t for one variant from the command, the History, the observation and the skill registry."""

    def __init__(self, variant: str, library: SkillLibrary, *, free_text_baselines: bool = False) -> None:
        if variant not in PROMPT_PARTS:
            raise ValueError(f"unknown prompt variant {variant!r}; use one of {', '.join(PROMPT_PARTS)}")
        self.variant = variant
        self.library = library
        # The fixed parts depend only on the variant and the registry: compile them once, as the prefix.
        from services.reasoner.baselines import PREAMBLES
        from services.reasoner.schema import answer_schema

        self._library_text = library_text(library)
        self._rules = rules_text(variant, library)
        self._preamble = PREAMBLES.get(variant, PREAMBLE)
        # The paper decoded its unstructured and ReAct baselines as free text (`free_text_baselines`).
        free = free_text_baselines and variant in FREE_TEXT_BASELINES
        self.schema = None if free else answer_schema(variant, library)

    def compile(self, command: str, history: History, obs: Observation) -> CompiledPrompt:
        wanted = PROMPT_PARTS[self.variant]
        parts: dict[str, str] = {}
        for name in wanted:
            if name == "command":
                parts[name] = command
            elif name == "preamble":
                parts[name] = self._preamble
            elif name == "history":
                parts[name] = history.render(obs)
            elif name == "skill_library":
                parts[name] = self._library_text
            elif name == "rules":
                parts[name] = self._rules
        prefix, text = layout(self.variant, parts)
        return CompiledPrompt(self.variant, parts, text, obs.image_jpeg, prefix, self.schema)


REPROMPT = ("Your previous answer was invalid: {error} Answer again with one valid skill, following the Rules "
            "exactly.")
REPROMPT_UNSTRUCTURED = "Your previous answer was invalid: {error} Answer again with one skill from the list."
REPROMPT_BASELINE = "Your previous answer was invalid: {error} Answer again, following the Rules exactly."


def reprompt_text(variant: str, error: str) -> str:
    if variant in ("saycan", "plan_once"):
        return REPROMPT_BASELINE.format(error=error)
    return (REPROMPT_UNSTRUCTURED if variant == "unstructured" else REPROMPT).format(error=error)


def memory_summary(memory: WorkingMemory) -> str:
    """The working memory as one compact paragraph of the prompt's History part."""
    parts = []
    if memory.objects:
        parts.append("localized objects: " + "; ".join(
            f"{o.label} at ({o.position.x:.2f}, {o.position.y:.2f}, {o.position.z:.2f})" for o in memory.objects))
    if memory.placements:
        parts.append("placement spots: " + "; ".join(
            f"{p.label} at ({p.position.x:.2f}, {p.position.y:.2f}, {p.position.z:.2f})" for p in memory.placements))
    parts.append(f"holding: {memory.held_object or 'nothing'}")
    known = {o.label for o in (*memory.objects, *memory.placements)}
    earlier = [o for o in memory.seen if o.label not in known and o.label not in memory.visible]
    if earlier:
        parts.append("seen earlier: " + "; ".join(
            f"{o.label} at ({o.position.x:.2f}, {o.position.y:.2f}, {o.position.z:.2f})" for o in earlier))
    if memory.visible:
        parts.append("visible now: " + ", ".join(memory.visible))
    return ". ".join(parts) + "."
