"""The one interface every policy backend implements (raw text in, raw text + tokens + latency out) and the
backend registry: a backend is one module with a `Backend` subclass decorated with `@register`; its `kind`
is the value of `AERMANI_REASONER_BACKEND` and of a task's `backend` override, and nothing else names it."""

from __future__ import annotations

import importlib
import logging
import os
import time
from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

from services.reasoner.prompt import CompiledPrompt, reprompt_text
from shared.errors import ConfigError, ModelError
from shared.messages import OutcomeCode, SkillFacts, SkillOutcome
from shared.registry import Registry
from shared.text import well_formed

if TYPE_CHECKING:
    from services.reasoner.settings import ReasonerSettings


@dataclass
class Seen:
    """A thing perception reports now (from `perception/detections`)."""

    label: str
    category: str = "object"
    volume: float | None = None
    distance: float | None = None
    catalog_volume: float | None = None  # its class's catalogued volume (perception's catalogue), when known


LEGACY_CODES: dict[str, OutcomeCode] = {
    "succeeded": OutcomeCode.SUCCEEDED, "failed": OutcomeCode.FAILED, "rejected": OutcomeCode.BLOCKED,
    "timeout": OutcomeCode.TIMED_OUT, "aborted": OutcomeCode.ABORTED,
}
"""The code of a status that has none (a log older than schema minor 3), from its state."""


def code_of(state: str, code: OutcomeCode | str | None) -> OutcomeCode:
    """A step's outcome code: its own, else the one its state implies (LEGACY_CODES; anything else failed)."""
    if code:
        return OutcomeCode(code)
    return LEGACY_CODES.get(state, OutcomeCode.FAILED)


@dataclass
class PastStep:
    """One earlier step of the task as the policy sees it: skill, argument, state, outcome code and facts, and
    the poses the executor measured. `message` is the executor's prose, kept for people: no policy reads it."""

    skill: str
    argument: str | None
    state: str
    message: str = ""
    code: OutcomeCode | None = None
    """None is filled from `state` (LEGACY_CODES)."""
    facts: SkillFacts = field(default_factory=SkillFacts)
    pose: tuple[float, float, float] | None = None
    """Vehicle x, y (world, m) and yaw (rad) when the step ended (its outcome's end pose)."""
    found_at: tuple[float, float, float] | None = None
    """Where the step's estimate put the object or placement spot (world x, y, z, m)."""
    surface_z: float | None = None
    """Height of the surface a placement_localization found, m."""

    def __post_init__(self) -> None:
        self.code = code_of(self.state, self.code)

    @classmethod
    def from_outcome(cls, skill: str, argument: str | None, state: str, message: str,
                     outcome: SkillOutcome | None) -> PastStep:
        """The step from an executor's status outcome (None for an entry the loop made itself)."""
        if outcome is None:
            return cls(skill, argument, state, message)
        end, est = outcome.end_pose, outcome.estimate
        where = est.pose.position if est is not None and est.pose is not None else None
        return cls(skill, argument, state, message, outcome.code, outcome.facts,
                   pose=(end.position.x, end.position.y, end.yaw) if end is not None else None,
                   found_at=(where.x, where.y, where.z) if where is not None else None,
                   surface_z=getattr(est, "surface_z", None))


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
    """What a backend is asked for one step: the compiled prompt, the policy context and re-prompt feedback."""

    prompt: CompiledPrompt
    context: PolicyContext
    feedback: list[tuple[str, str]] = field(default_factory=list)
    """Earlier invalid answers of this step with the re-prompt text, oldest first."""


@dataclass
class ModelReply:
    """A backend's answer to one request: the raw text, latency, token counts and whether it was structured."""

    text: str
    latency_s: float
    tokens_in: int | None = None
    tokens_out: int | None = None
    structured: bool = False
    """The answer was decoded under the answer's JSON schema (schema-constrained output)."""
    cached_tokens: int | None = None
    """Prompt tokens the server read from its prompt cache, when it says."""
    failure: str | None = None
    """Set with a `done` answer when the backend ends the task as failed, with the reason (the rules baseline:
    "not found: ..." after exploring the room); the task then ends FAILED instead of SUCCEEDED."""


ECHO_CHARS = 4000
"""Longest invalid answer sent back verbatim in a re-prompt (a real one is 1-4 kB); a longer one is cut, with
the count of what was left out, so 32 kB of junk is not paid for again as prompt tokens on every re-prompt."""


def echoed(raw: str) -> str:
    """An invalid answer as the re-prompt repeats it to the model: well formed (a lone surrogate would fail
    the HTTP request's UTF-8 encoding, ending the task on the re-prompt meant to recover it), at most
    ECHO_CHARS characters."""
    text = well_formed(raw) if raw else "(empty)"
    if len(text) > ECHO_CHARS:
        text = f"{text[:ECHO_CHARS]}\n[... {len(text) - ECHO_CHARS} more characters of this answer not repeated]"
    return text


def conversation(request: ModelRequest, first_user_content: list[dict]) -> list[dict]:
    """Chat messages for a step: the prompt (with its image) as the first user turn, then each earlier
    invalid answer (`echoed`) and its re-prompt, so the model sees what it got wrong."""
    msgs: list[dict] = [{"role": "user", "content": first_user_content}]
    for raw, error in request.feedback:
        msgs.append({"role": "assistant", "content": echoed(raw)})
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
    speculates: ClassVar[bool] = True
    """Whether an answer depends on its request alone, so a speculative call (AERMANI_REASONER_SPECULATE) may be
    made and thrown away; False for a backend that answers in sequence (a replayed log)."""

    @classmethod
    def from_settings(cls, settings: ReasonerSettings) -> Backend:
        """Build from the reasoner settings; raise ConfigError naming the setting to fix."""
        return cls()

    @abstractmethod
    async def complete(self, request: ModelRequest) -> ModelReply: ...

    def refusal(self, command: str, skills: list[str]) -> str | None:
        """Why this backend refuses the command outright (before takeoff, before any skill), or None to run it.
        `skills` are the live library's policy skills. Model backends accept every command."""
        return None

    def unsupported(self, variant: str) -> str | None:
        """Why this backend cannot answer in `variant`'s format (the task then fails before takeoff), or None.
        Model backends answer every variant."""
        return None

    async def aclose(self) -> None:
        return None


BACKENDS: Registry[type[Backend]] = Registry("reasoner backend", "kind",
                                             "AERMANI_REASONER_BACKEND (or the task's backend)", ConfigError)
register = BACKENDS.register
"""Class decorator: make a backend selectable by its `kind`."""


def missing_key(kind: str, env_var: str) -> str:
    """The error for a chat backend started without its key: what to set, first."""
    return (f"no API key: set AERMANI_REASONER_API_KEY or {env_var} for backend {kind} (a local server that "
            "ignores keys still needs a placeholder such as 'none')")


def api_key(settings: ReasonerSettings, kind: str, env_var: str) -> str:
    """The key for backend `kind`: AERMANI_REASONER_API_KEY, else `env_var`; a ConfigError naming both."""
    if settings.api_key is not None:
        return settings.api_key.get_secret_value()
    key = os.environ.get(env_var)
    if not key:
        raise ConfigError(missing_key(kind, env_var))
    return key


# --------------------------------------------------------------------------- chat-model backends

log = logging.getLogger("aermani.reasoner.backends")
_SCHEMA_REJECTED: dict[tuple[str, str, str], tuple[str, float]] = {}
"""(backend kind, base URL, model) -> (why the server rejected schema-constrained output, when: monotonic s), in
auto mode. Free text is used while the rejection is younger than SCHEMA_RETRY_S, then the schema is tried again:
a 400 can be transient (an overloaded proxy, a server restarting with other flags) and must not cost the
structured output for the rest of the process."""
SCHEMA_RETRY_S = 300.0


def _kind(exc: ModelError, kind: str) -> ModelError:
    exc.kind = kind
    return exc


class SchemaRejected(Exception):
    """The server refused the request because of the answer schema (HTTP 400/422 with a schema sent)."""


def jpeg_size(jpeg: bytes) -> tuple[int, int] | None:
    """(width, height) from the JPEG's start-of-frame marker, without decoding the image."""
    i = 2
    while i + 9 < len(jpeg):
        if jpeg[i] != 0xFF:
            return None
        marker = jpeg[i + 1]
        seg = int.from_bytes(jpeg[i + 2: i + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            return int.from_bytes(jpeg[i + 7: i + 9], "big"), int.from_bytes(jpeg[i + 5: i + 7], "big")
        i += 2 + seg
    return None


def fit_image(jpeg: bytes, max_side: int) -> bytes:
    """The JPEG, downscaled so its longest side is at most `max_side` (unchanged when it already fits)."""
    size = jpeg_size(jpeg)
    if size is not None and max(size) <= max_side:
        return jpeg
    import cv2
    import numpy as np

    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        return jpeg
    h, w = img.shape[:2]
    scale = max_side / max(h, w)
    if scale >= 1:
        return jpeg
    small = cv2.resize(img, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 90])
    return buf.tobytes() if ok else jpeg


class ChatBackend(Backend):
    """A hosted or local chat model: model profile, output mode (schema-constrained or free text) with the
    per-endpoint fallback, the settings every such backend reads, the request's chat turns and the SDK's
    client and errors. Subclasses name their SDK client and implement `image_part` and `_call`."""

    default_model: ClassVar[str] = ""
    key_env: ClassVar[str] = ""
    endpoint: ClassVar[str] = ""
    """What the server is called in errors ("OpenAI-compatible endpoint")."""
    sdk_name: ClassVar[str] = ""
    """The official SDK's module (`openai`), imported when a backend is built: importing both SDKs took 2.8 s of
    every `aermani` command's and every reasoner's start, whichever backend it used."""
    client_name: ClassVar[str] = ""
    """The SDK's async client class (`AsyncOpenAI`), built with the endpoint settings."""

    def __init__(self, *, model: str, api_key: str, base_url: str | None = None, timeout_s: float = 30.0,
                 retries: int = 3, max_tokens: int | None = None, temperature: float | None = None,
                 output_mode: str = "auto", profile: str = "auto") -> None:
        from services.reasoner.profiles import profile_for

        self.model = model
        self.name = f"{self.kind}:{model}"
        self.profile = profile_for(model, profile)
        self.max_tokens = max_tokens or self.profile.max_tokens
        self.temperature = self.profile.temperature if temperature is None else temperature
        self.output_mode = output_mode
        self.base_url = base_url or ""
        self.api_key = api_key
        self.timeout_s = timeout_s
        self.retries = retries
        # The SDK retries 408/409/429/5xx, connection errors and timeouts with exponential backoff and jitter;
        # `retries` is the bounded budget per call.
        self.sdk: Any = importlib.import_module(self.sdk_name) if self.sdk_name else None
        self.client: Any = None if self.sdk is None else getattr(self.sdk, self.client_name)(
            api_key=api_key, base_url=base_url or None, timeout=timeout_s, max_retries=retries)
        """The official SDK's async client, closed by `aclose`."""
        self.tracer = None
        """OpenTelemetry tracer for model-call spans (tracing.py), None when tracing is off."""

    @classmethod
    def from_settings(cls, settings: ReasonerSettings) -> ChatBackend:
        from services.reasoner.tracing import tracer_for

        backend = cls(model=settings.model or cls.default_model, api_key=api_key(settings, cls.kind, cls.key_env),
                      base_url=settings.base_url, timeout_s=settings.request_timeout_s,
                      retries=settings.transport_retries, max_tokens=settings.max_tokens,
                      temperature=settings.temperature, output_mode=settings.output_mode, profile=settings.profile)
        backend.tracer = tracer_for(settings.otlp_endpoint)
        return backend

    @property
    def _endpoint(self) -> tuple[str, str, str]:
        return self.kind, self.base_url, self.model

    def schema_for(self, request: ModelRequest) -> dict | None:
        """The answer schema to send with this request, or None for free text."""
        if request.prompt.schema is None or self.output_mode == "text":
            return None
        if self.output_mode == "auto" and (not self.profile.schema or self._schema_rejected_recently()):
            return None
        return request.prompt.schema

    def _schema_rejected_recently(self) -> bool:
        seen = _SCHEMA_REJECTED.get(self._endpoint)
        if seen is None:
            return False
        if time.monotonic() - seen[1] < SCHEMA_RETRY_S:
            return True
        del _SCHEMA_REJECTED[self._endpoint]
        log.info("%s endpoint %s: trying schema-constrained output again for model %s (refused %.0f s ago)",
                 self.kind, self.base_url or "(default)", self.model, time.monotonic() - seen[1])
        return False

    def image(self, request: ModelRequest) -> bytes | None:
        jpeg = request.prompt.image_jpeg
        return None if jpeg is None else fit_image(jpeg, self.profile.image_max_side)

    async def complete(self, request: ModelRequest) -> ModelReply:
        from services.reasoner import tracing

        schema = self.schema_for(request)
        with tracing.model_call_span(self.tracer, provider=self.kind, model=self.model, base_url=self.base_url,
                                     max_tokens=self.max_tokens, temperature=self.temperature,
                                     structured=schema is not None) as span:
            reply = await self._complete(request, schema)
            tracing.record_usage(span, reply.tokens_in, reply.tokens_out, reply.structured)
            return reply

    async def _complete(self, request: ModelRequest, schema: dict | None) -> ModelReply:
        try:
            return await self._call(request, schema)
        except SchemaRejected as exc:
            if self.output_mode == "schema":
                raise _kind(ModelError(f"{self.kind} endpoint {self.base_url or '(default)'} rejected the answer "
                                       f"schema for model {self.model}: {exc}; set AERMANI_REASONER_OUTPUT_MODE=text "
                                       "or auto"), "schema") from exc
            reply = await self._call(request, None)  # raises when free text fails too: nothing is remembered
            if self._endpoint not in _SCHEMA_REJECTED:  # remembered per endpoint for a while, logged once
                log.warning("%s endpoint %s rejected schema-constrained output for model %s (%s); using free "
                            "text and the lenient reader for %.0f s", self.kind, self.base_url or "(default)",
                            self.model, str(exc)[:200], SCHEMA_RETRY_S)
            _SCHEMA_REJECTED[self._endpoint] = (str(exc), time.monotonic())
            return reply

    async def aclose(self) -> None:
        if self.client is not None:
            await self.client.close()

    def messages(self, request: ModelRequest) -> list[dict]:
        """The chat turns: [prompt prefix, rest of the prompt, image] as the first user turn (the first text
        part is the same for every step: what prefix caching reuses), then the step's feedback."""
        p = request.prompt
        content: list[dict] = [self.prefix_part(p.prefix)] if p.prefix else []
        content.append({"type": "text", "text": p.suffix})
        jpeg = self.image(request)
        if jpeg is not None:
            content.append(self.image_part(jpeg))
        return conversation(request, content)

    def prefix_part(self, prefix: str) -> dict:
        """The content part carrying the constant prompt prefix."""
        return {"type": "text", "text": prefix}

    @abstractmethod
    def image_part(self, jpeg: bytes) -> dict:
        """The content part carrying the (fitted) JPEG image, in the API's format."""

    @contextmanager
    def sdk_errors(self, schema: dict | None) -> Iterator[None]:
        """Translate the errors of an official SDK (`openai`, `anthropic`: the same Stainless-generated error
        classes) after its retry budget: SchemaRejected for a refused request that carried a schema,
        else ModelError naming the endpoint (`endpoint` names its kind) and the model."""
        sdk = self.sdk
        try:
            yield
        except (sdk.BadRequestError, sdk.UnprocessableEntityError) as exc:
            if schema is not None:
                raise SchemaRejected(f"HTTP {exc.status_code}: {str(exc)[:200]}") from exc
            raise _kind(ModelError(f"{self.endpoint} refused the request for model {self.model} (HTTP "
                                   f"{exc.status_code}): {str(exc)[:200]}"), "refused") from exc
        except sdk.APIStatusError as exc:
            raise _kind(ModelError(f"{self.endpoint} answered HTTP {exc.status_code} for model {self.model} after "
                                   f"the retry budget: {str(exc)[:200]}"),
                        "refused" if 400 <= exc.status_code < 500 and exc.status_code not in (408, 429)
                        else "server") from exc
        except sdk.APIError as exc:  # connection, timeout
            raise _kind(ModelError(f"{self.endpoint} unreachable for model {self.model} after the retry budget: "
                                   f"{type(exc).__name__}: {str(exc)[:200]}"), "unreachable") from exc

    @abstractmethod
    async def _call(self, request: ModelRequest, schema: dict | None) -> ModelReply:
        """One model call (transport retries inside); raise SchemaRejected when a schema was sent and the
        server refused the request for it, ModelError after the retry budget."""
