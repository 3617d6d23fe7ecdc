"""The one interface every policy backend implements: raw text in, raw text + tokens + latency out."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

from services.reasoner.prompt import CompiledPrompt, reprompt_text


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
    """A policy pi(o_t, P_t). Transport retries happen inside; after the budget it raises ModelError."""

    name: str = ""

    @abstractmethod
    async def complete(self, request: ModelRequest) -> ModelReply: ...

    async def aclose(self) -> None:
        return None
