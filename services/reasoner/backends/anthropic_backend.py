"""`anthropic`: Claude through the official `anthropic` SDK (Messages API); the image as a base64 JPEG block."""

from __future__ import annotations

import base64
import time

import anthropic

from services.reasoner.backends.base import Backend, ModelReply, ModelRequest, api_key, conversation, register
from shared.errors import ModelError


@register
class AnthropicBackend(Backend):
    kind = "anthropic"
    summary = "Claude through the Anthropic Messages API; MODEL, BASE_URL, API_KEY or ANTHROPIC_API_KEY"
    default_model = "claude-3-5-sonnet-latest"

    @classmethod
    def from_settings(cls, settings) -> AnthropicBackend:
        return cls(model=settings.model or cls.default_model,
                   api_key=api_key(settings, cls.kind, "ANTHROPIC_API_KEY"), base_url=settings.base_url,
                   timeout_s=settings.request_timeout_s, retries=settings.transport_retries,
                   max_tokens=settings.max_tokens, temperature=settings.temperature)

    def __init__(self, *, model: str, api_key: str, base_url: str | None, timeout_s: float, retries: int,
                 max_tokens: int, temperature: float) -> None:
        self.model = model
        self.name = f"anthropic:{model}"
        self.max_tokens = max_tokens
        self.temperature = temperature
        # Like the OpenAI SDK: bounded retries with backoff on 408/409/429/5xx, connection errors, timeouts.
        self.client = anthropic.AsyncAnthropic(api_key=api_key, base_url=base_url, timeout=timeout_s,
                                               max_retries=retries)

    def messages(self, request: ModelRequest) -> list[dict]:
        content: list[dict] = []
        if request.prompt.image_jpeg is not None:
            content.append({"type": "image", "source": {"type": "base64", "media_type": "image/jpeg",
                                                         "data": base64.b64encode(request.prompt.image_jpeg).decode()}})
        content.append({"type": "text", "text": request.prompt.text})
        return conversation(request, content)

    async def complete(self, request: ModelRequest) -> ModelReply:
        t0 = time.perf_counter()
        try:
            # This SDK's create() has no temperature parameter (recent Claude models fix sampling); a non-zero
            # setting still reaches endpoints that accept it through the request body.
            extra = {"temperature": self.temperature} if self.temperature else None
            resp = await self.client.messages.create(model=self.model, max_tokens=self.max_tokens,
                                                     messages=self.messages(request), extra_body=extra)
        except anthropic.APIStatusError as exc:
            raise ModelError(f"Anthropic endpoint answered HTTP {exc.status_code} for model {self.model} after the "
                             f"retry budget: {str(exc)[:200]}") from exc
        except anthropic.APIError as exc:
            raise ModelError(f"Anthropic endpoint unreachable for model {self.model} after the retry budget: "
                             f"{type(exc).__name__}: {str(exc)[:200]}") from exc
        latency = time.perf_counter() - t0
        text = "".join(getattr(b, "text", "") for b in resp.content)
        return ModelReply(text=text, latency_s=latency, tokens_in=resp.usage.input_tokens,
                          tokens_out=resp.usage.output_tokens)

    async def aclose(self) -> None:
        await self.client.close()
