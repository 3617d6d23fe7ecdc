"""Policy backends behind one interface, chosen by the `backend` setting (rules|openai|anthropic|replay)."""

from __future__ import annotations

import os

from services.reasoner.backends.base import Backend, ModelReply, ModelRequest, PastStep, PolicyContext, Seen
from services.reasoner.settings import ReasonerSettings
from shared.errors import ConfigError

__all__ = ["Backend", "ModelReply", "ModelRequest", "PastStep", "PolicyContext", "Seen", "make_backend"]

DEFAULT_MODELS = {"openai": "gpt-4o", "anthropic": "claude-3-5-sonnet-latest"}


def _key(settings: ReasonerSettings, env_var: str) -> str:
    if settings.api_key is not None:
        return settings.api_key.get_secret_value()
    key = os.environ.get(env_var)
    if not key:
        raise ConfigError(f"backend {settings.backend} needs an API key: set AERMANI_REASONER_API_KEY or {env_var} "
                          "(a local server that ignores keys still needs a placeholder such as 'none')")
    return key


def make_backend(settings: ReasonerSettings, name: str | None = None) -> Backend:
    """The backend named by `name` (or settings.backend)."""
    name = name or settings.backend
    if name == "rules":
        from services.reasoner.backends.rules import RulesBackend

        return RulesBackend()
    common = {"model": settings.model or DEFAULT_MODELS.get(name, ""), "base_url": settings.base_url,
                  "timeout_s": settings.request_timeout_s, "retries": settings.transport_retries,
                  "max_tokens": settings.max_tokens, "temperature": settings.temperature}
    if name == "openai":
        from services.reasoner.backends.openai_backend import OpenAIBackend

        return OpenAIBackend(api_key=_key(settings, "OPENAI_API_KEY"), **common)
    if name == "anthropic":
        from services.reasoner.backends.anthropic_backend import AnthropicBackend

        return AnthropicBackend(api_key=_key(settings, "ANTHROPIC_API_KEY"), **common)
    if name == "replay":
        from services.reasoner.backends.replay import JsonlReplaySource, ReplayBackend

        if not settings.replay_path:
            raise ConfigError("backend replay needs AERMANI_REASONER_REPLAY_PATH (a JSONL of recorded answers)")
        return ReplayBackend(JsonlReplaySource(settings.replay_path))
    raise ConfigError(f"unknown reasoner backend {name!r}: use rules, openai, anthropic or replay")
