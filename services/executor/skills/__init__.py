"""The built-in skills, one family per module; every module in this package is imported on first use, so a
new skill is one module here with `@register` on its class (or a module of its own package named in
`AERMANI_EXECUTOR_SKILL_MODULES`) and nothing else changes."""

from __future__ import annotations

import importlib
import pkgutil

_ORDER = ("motion", "localization", "manipulation", "control")
"""The paper's tables in order (the Skill Library lists skills in registration order); any other module of
this package comes after them, alphabetically."""


def builtin_modules() -> list[str]:
    """The modules of this package in the Skill Library's order: the paper's tables, then the others."""
    found = sorted(info.name for info in pkgutil.iter_modules(__path__))
    return [f"{__name__}.{n}" for n in (*[n for n in _ORDER if n in found], *[n for n in found if n not in _ORDER])]


def load_builtin() -> None:
    """Import every module of this package (each registers its skills)."""
    for name in builtin_modules():
        importlib.import_module(name)
