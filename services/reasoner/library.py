"""The Skill Library part of the prompt, and the library for offline tools.

The live loop always uses the library the executor serves (`executor/skills`); offline tools (`aermani vlm
check`, re-reasoning a log without its library, tests) use the built-in library at default settings from the
contract (`shared/skill_library.json`, kept current from the executor's registry by the executor's tests).
"""

from __future__ import annotations

from shared.messages import SkillLibrary, SkillSpec


def default_library() -> SkillLibrary:
    """The library a default executor serves (built-in skills, default settings), for offline checks."""
    from shared.skills import builtin_library

    return builtin_library()


def policy_skills(library: SkillLibrary) -> list[SkillSpec]:
    """Skills offered to the model, in registry order."""
    return [s for s in library.skills if s.policy_visible]


def signature(spec: SkillSpec) -> str:
    if spec.argument is None:
        return spec.name
    return f"{spec.name}(<{spec.argument}>)" if spec.argument_required else f"{spec.name}([{spec.argument}])"


def library_text(library: SkillLibrary) -> str:
    """The Skill Library part: one line per policy-visible skill with its fixed parameters."""
    lines = []
    for spec in policy_skills(library):
        params = ", ".join(f"{p.name}={p.value}{p.unit}" for p in spec.parameters)
        lines.append(f"- {signature(spec)}: {spec.description}" + (f" ({params})" if params else ""))
    return "\n".join(lines)
