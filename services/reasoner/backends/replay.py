"""`replay`: answers taken from a recorded log, for deterministic regression runs.

A source yields raw answers in order. `JsonlReplaySource` reads a JSONL file whose lines are either a
ReasoningStep (every model call's raw answer, invalid ones included, in order), an object with a `raw`
field, or a JSON string. Other sources (e.g. an MCAP log of `reasoner/step`) plug in by implementing
`ReplaySource.answers()`.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

from services.reasoner.backends.base import Backend, ModelReply, ModelRequest, register
from shared.errors import ConfigError, ModelError


class ReplaySource(Protocol):
    """Where a replay backend gets its recorded answers from, in order."""

    def answers(self) -> Iterator[str]: ...


class JsonlReplaySource:
    """Replay answers read from a JSONL file of recorded steps, {"raw": ...} objects or strings."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise ConfigError(f"replay file {self.path} does not exist: set AERMANI_REASONER_REPLAY_PATH")

    def answers(self) -> Iterator[str]:
        with self.path.open() as f:
            for n, line in enumerate(f, 1):
                if not line.strip():
                    continue
                try:
                    item = json.loads(line)
                except ValueError as exc:
                    raise ConfigError(f"{self.path}:{n} is not JSON: {exc}") from exc
                if isinstance(item, str):
                    yield item
                elif isinstance(item, dict) and "calls" in item:
                    for call in item["calls"]:
                        yield call["raw_answer"]
                elif isinstance(item, dict) and "raw" in item:
                    yield item["raw"]
                else:
                    raise ConfigError(f"{self.path}:{n}: expected a ReasoningStep, {{\"raw\": ...}} or a string")


class ListReplaySource:
    """Replay answers from an in-memory list (for tests and scripted runs)."""

    def __init__(self, answers: list[str]) -> None:
        self._answers = list(answers)

    def answers(self) -> Iterator[str]:
        return iter(self._answers)


@register
class ReplayBackend(Backend):
    """Backend that returns recorded answers one per call instead of querying a model."""

    kind = "replay"
    summary = "answers from a JSONL of recorded ReasoningSteps, {\"raw\": ...} objects or strings; REPLAY_PATH"
    name = "replay"
    speculates = False  # one answer per call, in order: a discarded speculative call would skip one

    @classmethod
    def from_settings(cls, settings) -> ReplayBackend:
        if not settings.replay_path:
            raise ConfigError("backend replay needs AERMANI_REASONER_REPLAY_PATH (a JSONL of recorded answers)")
        return cls(JsonlReplaySource(settings.replay_path))

    def __init__(self, source: ReplaySource) -> None:
        self._it = source.answers()

    async def complete(self, request: ModelRequest) -> ModelReply:
        t0 = time.perf_counter()
        try:
            text = next(self._it)
        except StopIteration:
            raise ModelError("the replay log has no more answers")
        return ModelReply(text=text, latency_s=time.perf_counter() - t0)
