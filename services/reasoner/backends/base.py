"""The one interface every policy backend implements (raw text in, raw text + tokens + latency out) and the
backend registry: a backend is one module with a `Backend` subclass decorated with `@register`; its `kind`
is the value of `AERMANI_REASONER_BACKEND` and of a task's `backend` override, and nothing else names it."""

from __future__ import annotations

import os
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar

from services.reasoner.prompt import CompiledPrompt, reprompt_text
from shared.errors import ConfigError

if TYPE_CHECKING:
    from services.reasoner.settings import ReasonerSettings


@dataclass
class Seen:
    """A thing perception reports now (from `perception/detections`)."""

    label: str
    category: str = "object"
    volume: float | None = None
    distance: float | None = None


@dataclass
class PastStep:
    skill: str
    argument: str | None
    state: str
    message: str = ""


@dataclass
class PolicyContext:
    """What a non-VLM policy may read: the same context the prompt is built from, never the pixels."""

    command: str
    variant: str
    skills: list[str]
    steps: list[PastStep] = field(default_factory=list)
    held: str | None = None
    visible: list[Seen] = field(default_factory=list)
    known_objects: list[str] = field(default_factory=list)
    known_placements: list[str] = field(default_factory=list)
    pose: tuple[float, float, float] | None = None
    """Vehicle x, y (world, m) and yaw (rad), when known."""
    positions: dict[str, tuple[float, float]] = field(default_factory=dict)
    """World x, y of localized objects and placement spots by label (working memory), and of everything
    perception has detected before ("seen earlier"), localized positions taking precedence."""


@dataclass
class ModelRequest:
    prompt: CompiledPrompt
    context: PolicyContext
    feedback: list[tuple[str, str]] = field(default_factory=list)
    """Earlier invalid answers of this step with the re-prompt text, oldest first."""


@dataclass
class ModelReply:
    text: str
    latency_s: float
    tokens_in: int | None = None
    tokens_out: int | None = None


def conversation(request: ModelRequest, first_user_content: list[dict]) -> list[dict]:
    """Chat messages for a step: the prompt (with its image) as the first user turn, then each earlier
    invalid answer and its re-prompt, so the model sees exactly what it got wrong."""
    msgs: list[dict] = [{"role": "user", "content": first_user_content}]
    for raw, error in request.feedback:
        msgs.append({"role": "assistant", "content": raw or "(empty)"})
        msgs.append({"role": "user", "content": reprompt_text(request.prompt.variant, error)})
    return msgs


class Backend(ABC):
    """A policy pi(o_t, P_t). Transport retries happen inside; after the budget it raises ModelError.

    Subclasses set `kind` (the registry name) and `summary` (one line for `aermani vlm backends`), and build
    themselves from the reasoner settings in `from_settings`."""

    kind: ClassVar[str] = ""
    """Registry name: AERMANI_REASONER_BACKEND, TaskRequest.backend, `--backend`."""
    summary: ClassVar[str] = ""
    """One line saying what the backend is and which settings it reads."""
    name: str = ""
    """Label of this instance in records, e.g. `openai:gpt-4o` (the kind plus the model when there is one)."""

    @classmethod
    def from_settings(cls, settings: ReasonerSettings) -> Backend:
        """Build from the reasoner settings; raise ConfigError naming the setting to fix."""
        return cls()

    @abstractmethod
    async def complete(self, request: ModelRequest) -> ModelReply: ...

    async def aclose(self) -> None:
        return None


BACKENDS: dict[str, type[Backend]] = {}


def register(cls: type[Backend]) -> type[Backend]:
    """Class decorator: make a backend selectable by its `kind`."""
    if not cls.kind:
        raise ValueError(f"{cls.__name__} has no `kind`")
    BACKENDS[cls.kind] = cls
    return cls


def api_key(settings: ReasonerSettings, kind: str, env_var: str) -> str:
    """The key for backend `kind`: AERMANI_REASONER_API_KEY, else `env_var`; a ConfigError naming both."""
    if settings.api_key is not None:
        return settings.api_key.get_secret_value()
    key = os.environ.get(env_var)
    if not key:
        raise ConfigError(f"backend {kind} needs an API key: set AERMANI_REASONER_API_KEY or {env_var} "
                          "(a local server that ignores keys still needs a placeholder such as 'none')")
    return key
