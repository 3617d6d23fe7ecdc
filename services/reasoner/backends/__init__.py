"""Policy backends behind one interface, chosen by the `backend` setting from the registry in base.py (where the
interface, its request and reply types and `@register` are imported from; this package builds a backend).

Importing this package registers the built-in backends (one module each); `backend_modules` names extra
modules to import first, so a backend defined outside this package registers the same way.
"""

from __future__ import annotations

import importlib

from services.reasoner.backends import anthropic_backend, openai_backend, replay, rules  # noqa: F401 - register
from services.reasoner.backends.base import BACKENDS, Backend
from services.reasoner.settings import ReasonerSettings
from shared.errors import ConfigError

__all__ = ["BACKENDS", "backend_names", "load_backend_modules", "make_backend"]


def load_backend_modules(modules: str) -> None:
    """Import each comma-separated module (each registers its backends); a ConfigError names a missing one."""
    for mod in filter(None, (m.strip() for m in modules.split(","))):
        try:
            importlib.import_module(mod)
        except ImportError as exc:
            raise ConfigError(f"cannot import backend module {mod!r} named in AERMANI_REASONER_BACKEND_MODULES: "
                              f"{exc}") from exc


def backend_names() -> list[str]:
    """Registered backend kinds, in registration order."""
    return list(BACKENDS)


def make_backend(settings: ReasonerSettings, name: str | None = None) -> Backend:
    """The backend named by `name` (or settings.backend), built from the settings."""
    load_backend_modules(settings.backend_modules)
    name = name or settings.backend
    return BACKENDS.lookup(name).from_settings(settings.model_copy(update={"backend": name}))
