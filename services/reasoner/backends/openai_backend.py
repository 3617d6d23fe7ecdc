"""`openai`: any OpenAI-compatible chat-completions endpoint (GPT-4o, Gemini's compatible endpoint, vLLM,
Ollama, llama.cpp server, LM Studio) through the official `openai` SDK; the image goes as a JPEG data URL."""

from __future__ import annotations

import base64
import time

import openai

from services.reasoner.backends.base import Backend, ModelReply, ModelRequest, api_key, conversation, register
from shared.errors import ModelError


def image_data_url(jpeg: bytes) -> str:
    return "data:image/jpeg;base64," + base64.b64encode(jpeg).decode("ascii")


@register
class OpenAIBackend(Backend):
    kind = "openai"
    summary = ("any OpenAI-compatible chat-completions endpoint (GPT-4o, Gemini, vLLM, Ollama, llama.cpp); "
               "MODEL, BASE_URL, API_KEY or OPENAI_API_KEY")
    default_model = "gpt-4o"

    @classmethod
    def from_settings(cls, settings) -> OpenAIBackend:
        return cls(model=settings.model or cls.default_model, api_key=api_key(settings, cls.kind, "OPENAI_API_KEY"),
                   base_url=settings.base_url, timeout_s=settings.request_timeout_s,
                   retries=settings.transport_retries, max_tokens=settings.max_tokens,
                   temperature=settings.temperature)

    def __init__(self, *, model: str, api_key: str, base_url: str | None, timeout_s: float, retries: int,
                 max_tokens: int, temperature: float) -> None:
        self.model = model
        self.name = f"openai:{model}"
        self.max_tokens = max_tokens
        self.temperature = temperature
        # The SDK retries 408/409/429/5xx, connection errors and timeouts with exponential backoff and jitter;
        # max_retries is our bounded budget per call.
        self.client = openai.AsyncOpenAI(api_key=api_key, base_url=base_url, timeout=timeout_s, max_retries=retries)

    def messages(self, request: ModelRequest) -> list[dict]:
        content: list[dict] = [{"type": "text", "text": request.prompt.text}]
        if request.prompt.image_jpeg is not None:
            content.append({"type": "image_url", "image_url": {"url": image_data_url(request.prompt.image_jpeg)}})
        return conversation(request, content)

    async def complete(self, request: ModelRequest) -> ModelReply:
        t0 = time.perf_counter()
        try:
            resp = await self.client.chat.completions.create(
                model=self.model, messages=self.messages(request), max_tokens=self.max_tokens,
                temperature=self.temperature)
        except openai.APIStatusError as exc:
            raise ModelError(f"OpenAI-compatible endpoint answered HTTP {exc.status_code} for model {self.model}"
                             f" after the retry budget: {str(exc)[:200]}") from exc
        except openai.APIError as exc:  # connection, timeout
            raise ModelError(f"OpenAI-compatible endpoint unreachable for model {self.model} after the retry "
                             f"budget: {type(exc).__name__}: {str(exc)[:200]}") from exc
        latency = time.perf_counter() - t0
        text = (resp.choices[0].message.content or "") if resp.choices else ""
        usage = resp.usage
        return ModelReply(text=text, latency_s=latency, tokens_in=usage.prompt_tokens if usage else None,
                          tokens_out=usage.completion_tokens if usage else None)

    async def aclose(self) -> None:
        await self.client.close()
