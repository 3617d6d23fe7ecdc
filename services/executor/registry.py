"""The skill registry: one class per skill, registered with `@register`; its spec is the Skill Library text."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import ClassVar, Literal

from services.executor.context import SkillContext
from services.executor.settings import ExecutorSettings
from shared.errors import ConfigError
from shared.messages import OutcomeCode, SkillFacts, SkillLibrary, SkillParameter, SkillSpec

Category = Literal["motion", "perception", "manipulation", "operator", "control"]


@dataclass
class SkillResult:
    """What a successful run reports: its code and measured facts (what a policy reads) and a message (what a
    person reads). The executor adds poses, the held object and the gripper's opening."""

    message: str = ""
    code: OutcomeCode = OutcomeCode.SUCCEEDED
    facts: SkillFacts = field(default_factory=SkillFacts)


class Skill(ABC):
    """Base of every skill. Subclasses set the class attributes and implement `run`; the executor applies
    the generic preconditions (state health, airborne, offboard) from the flags, then `check`."""

    name: ClassVar[str]
    category: ClassVar[Category]
    description: ClassVar[str]
    """Skill Library text; `{s.<setting>}` placeholders are filled from ExecutorSettings."""
    argument: ClassVar[str | None] = None
    argument_required: ClassVar[bool] = False
    policy_visible: ClassVar[bool] = True
    moves: ClassVar[bool] = True
    """Commands the autopilot: needs fresh state and a healthy link."""
    needs_airborne: ClassVar[bool] = True
    needs_offboard: ClassVar[bool] = True
    """Sends position setpoints: needs OFFBOARD with a running setpoint stream."""

    def __init__(self, settings: ExecutorSettings) -> None:
        self.settings = settings

    def parameters(self) -> tuple[SkillParameter, ...]:
        return ()

    def spec(self) -> SkillSpec:
        return SkillSpec(name=self.name, category=self.category, description=self.description.format(s=self.settings),
                         argument=self.argument, argument_required=self.argument_required,
                         parameters=self.parameters(), policy_visible=self.policy_visible)

    def check(self, ctx: SkillContext, argument: str | None) -> str | None:
        """Skill-specific preconditions: None when the skill may start, else why not. A plain string is
        refused as `blocked`; a `Refusal` (skills.common) carries its own code and facts."""
        return None

    def timeout_s(self, ctx: SkillContext, argument: str | None) -> float:
        return 30.0

    @abstractmethod
    async def run(self, ctx: SkillContext, argument: str | None) -> SkillResult:
        """The routine: returns on success, raises SkillFailed (with a reason for the model) otherwise."""


REGISTRY: dict[str, type[Skill]] = {}


def register(cls: type[Skill]) -> type[Skill]:
    """Class decorator: add a skill to the library (names are unique)."""
    if not getattr(cls, "name", ""):
        raise ValueError(f"{cls.__name__} has no skill name")
    if cls.name in REGISTRY and REGISTRY[cls.name] is not cls:
        raise ValueError(f"skill {cls.name!r} is registered twice ({REGISTRY[cls.name].__name__}, {cls.__name__})")
    REGISTRY[cls.name] = cls
    return cls


def library_order() -> list[str]:
    """Every registered skill's name in the Skill Library's order: the built-in modules in their order
    (`skills.builtin_modules`), each skill where its module defines it, then the others as they registered; the
    same whichever module was imported first (a test importing one skill module directly, before the library
    loaded, put grasp and place first and made the committed library file read stale)."""
    from services.executor.skills import builtin_modules

    rank = {m: i for i, m in enumerate(builtin_modules())}
    seen = {n: i for i, n in enumerate(REGISTRY)}
    return sorted(REGISTRY, key=lambda n: (rank.get(REGISTRY[n].__module__, len(rank)), seen[n]))


def load_skills(modules: list[str] | tuple[str, ...] = ()) -> None:
    """Register the built-in skills and those of `modules` (extra skills outside this package)."""
    import importlib

    from services.executor.skills import load_builtin

    load_builtin()
    for name in modules:
        try:
            importlib.import_module(name)
        except ImportError as exc:
            raise ConfigError(f"cannot import skill module {name!r} (AERMANI_EXECUTOR_SKILL_MODULES): {exc}") from exc


def library(settings: ExecutorSettings | None = None) -> SkillLibrary:
    """The Skill Library of every registered skill, as the executor serves it on `executor/skills`."""
    settings = settings or ExecutorSettings()
    return SkillLibrary(skills=tuple(sk.spec() for sk in build_library(settings).values()))


def build_library(settings: ExecutorSettings, names: list[str] | None = None) -> dict[str, Skill]:
    """Instances of the registered skills (all, or `names` in that order)."""
    load_skills(settings.skill_modules)

    chosen = names or library_order()
    unknown = [n for n in chosen if n not in REGISTRY]
    if unknown:
        raise ValueError(f"unknown skills {unknown}; registered: {sorted(REGISTRY)}")
    return {n: REGISTRY[n](settings) for n in chosen}


def builtin_library() -> SkillLibrary:
    """The built-in skills at default settings (the environment and plug-in skill modules left out): what
    shared/skill_library.json holds for offline tools."""
    from services.executor.skills import load_builtin

    load_builtin()
    settings = ExecutorSettings.model_construct()  # field defaults only: no environment, no .env file
    return SkillLibrary(skills=tuple(REGISTRY[n](settings).spec() for n in library_order()
                                     if REGISTRY[n].__module__.startswith("services.executor.skills.")))


def main(argv: list[str] | None = None) -> int:
    """`python -m services.executor.registry --write` rewrites shared/skill_library.json; `--check` exits 1 when
    the file is stale."""
    import argparse
    from pathlib import Path

    from services.executor import registry  # this module as the skills register into it (not __main__)
    from shared import skills

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("--write", action="store_true", help="rewrite the file")
    ap.add_argument("--check", action="store_true", help="exit 1 when the file differs from the registry")
    args = ap.parse_args(argv)
    path = Path(skills.__file__).with_name(skills.LIBRARY_FILE)
    text = skills.library_json(registry.builtin_library())
    if args.write:
        path.write_text(text, encoding="utf-8")
        print(f"wrote {path}")
        return 0
    stale = not path.exists() or path.read_text(encoding="utf-8") != text
    if stale:
        print(f"{path} is stale: run python -m services.executor.registry --write")
    return 1 if stale and args.check else 0


if __name__ == "__main__":
    raise SystemExit(main())
