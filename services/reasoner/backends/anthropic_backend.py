"""`anthropic`: Claude through the official `anthropic` SDK (Messages API).

The user turn is [constant prompt prefix with `cache_control: ephemeral`, the rest of the prompt, image as
a base64 JPEG block]: the prefix (Preamble, Skill Library, Rules) is written to Anthropic's prompt cache
once and read on every later step and task. With a schema the request carries structured outputs,
`output_config: {format: {type: json_schema, schema}}`, and the answer is the JSON text."""

from __future__ import annotations

import base64
import time

import anthropic

from services.reasoner.backends.base import (
    ChatBackend,
    ModelReply,
    ModelRequest,
    SchemaRejected,
    conversation,
    register,
)
from shared.errors import ModelError


@register
class AnthropicBackend(ChatBackend):
    """VLM backend for Claude through the Anthropic Messages API, with prompt caching of the constant prefix."""

    kind = "anthropic"
    summary = "Claude through the Anthropic Messages API; MODEL, BASE_URL, API_KEY or ANTHROPIC_API_KEY"
    default_model = "claude-sonnet-4-5"
    key_env = "ANTHROPIC_API_KEY"

    def __init__(self, **kw: object) -> None:
        super().__init__(**kw)  # type: ignore[arg-type]
        # Like the OpenAI SDK: bounded retries with backoff on 408/409/429/5xx, connection errors, timeouts.
        self.client = anthropic.AsyncAnthropic(api_key=self.api_key, base_url=self.base_url or None,
                                               timeout=self.timeout_s, max_retries=self.retries)

    def messages(self, request: ModelRequest) -> list[dict]:
        p = request.prompt
        content: list[dict] = []
        if p.prefix:
            content.append({"type": "text", "text": p.prefix, "cache_control": {"type": "ephemeral"}})
        content.append({"type": "text", "text": p.suffix})
        jpeg = self.image(request)
        if jpeg is not None:
            content.append({"type": "image", "source": {"type": "base64", "media_type": "image/jpeg",
                                                         "data": base64.b64encode(jpeg).decode()}})
        return conversation(request, content)

    async def _call(self, request: ModelRequest, schema: dict | None) -> ModelReply:
        t0 = time.perf_counter()
        kw: dict = {}
        if schema is not None:
            kw["output_config"] = {"format": {"type": "json_schema", "schema": schema}}
        if self.temperature:
            # Recent Claude models fix sampling; a non-zero setting still reaches endpoints that accept it.
            kw["extra_body"] = {"temperature": self.temperature}
        try:
            # The messages are plain dicts in the wire format; the SDK types them as TypedDicts.
            resp = await self.client.messages.create(model=self.model, max_tokens=self.max_tokens,
                                                     messages=self.messages(request), **kw)  # type: ignore[arg-type]
        except (anthropic.BadRequestError, anthropic.UnprocessableEntityError) as exc:
            if schema is not None:
                raise SchemaRejected(f"HTTP {exc.status_code}: {str(exc)[:200]}") from exc
            raise ModelError(f"Anthropic endpoint refused the request for model {self.model} (HTTP "
                             f"{exc.status_code}): {str(exc)[:200]}") from exc
        except anthropic.APIStatusError as exc:
            raise ModelError(f"Anthropic endpoint answered HTTP {exc.status_code} for model {self.model} after the "
                             f"retry budget: {str(exc)[:200]}") from exc
        except anthropic.APIError as exc:
            raise ModelError(f"Anthropic endpoint unreachable for model {self.model} after the retry budget: "
                             f"{type(exc).__name__}: {str(exc)[:200]}") from exc
        latency = time.perf_counter() - t0
        text = "".join(getattr(b, "text", "") for b in resp.content)
        u = resp.usage
        cached = getattr(u, "cache_read_input_tokens", None)
        written = getattr(u, "cache_creation_input_tokens", None) or 0
        # input_tokens counts only what was neither read from nor written to the cache.
        return ModelReply(text=text, latency_s=latency, tokens_in=u.input_tokens + (cached or 0) + written,
                          tokens_out=u.output_tokens, structured=schema is not None, cached_tokens=cached)

    async def aclose(self) -> None:
        await self.client.close()
