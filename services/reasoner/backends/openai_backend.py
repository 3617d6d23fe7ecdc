"""`openai`: any OpenAI-compatible chat-completions endpoint (GPT-4o, Gemini's compatible endpoint, vLLM,
Ollama, llama.cpp server, LM Studio) through the official `openai` SDK; the image goes as a JPEG data URL.

The user turn is [constant prompt prefix, the rest of the prompt, image]: the first text part is identical
for every step, which is what automatic prefix caching (OpenAI, vLLM) reuses. With a schema the request
carries `response_format: {type: json_schema, json_schema: {name, strict: true, schema}}`."""

from __future__ import annotations

import base64
import time

from services.reasoner.backends.base import ChatBackend, ModelReply, ModelRequest, register
from services.reasoner.schema import SCHEMA_NAME


def image_data_url(jpeg: bytes) -> str:
    return "data:image/jpeg;base64," + base64.b64encode(jpeg).decode("ascii")


def response_format(schema: dict) -> dict:
    return {"type": "json_schema", "json_schema": {"name": SCHEMA_NAME, "strict": True, "schema": schema}}


@register
class OpenAIBackend(ChatBackend):
    """VLM backend for any OpenAI-compatible chat-completions endpoint (GPT-4o, Gemini, vLLM, Ollama, ...)."""

    kind = "openai"
    summary = ("any OpenAI-compatible chat-completions endpoint (GPT-4o, Gemini, vLLM, Ollama, llama.cpp); "
               "MODEL, BASE_URL, API_KEY or OPENAI_API_KEY")
    default_model = "gpt-4o"
    key_env = "OPENAI_API_KEY"
    endpoint = "OpenAI-compatible endpoint"
    sdk_name = "openai"
    client_name = "AsyncOpenAI"

    def image_part(self, jpeg: bytes) -> dict:
        return {"type": "image_url", "image_url": {"url": image_data_url(jpeg)}}

    async def _call(self, request: ModelRequest, schema: dict | None) -> ModelReply:
        t0 = time.perf_counter()
        extra = {"response_format": response_format(schema)} if schema is not None else {}
        with self.sdk_errors(schema):
            # The messages are plain dicts in the wire format; the SDK types them as TypedDicts.
            resp = await self.client.chat.completions.create(  # type: ignore[call-overload]
                model=self.model, messages=self.messages(request), max_tokens=self.max_tokens,
                temperature=self.temperature, **extra)
        latency = time.perf_counter() - t0
        text = (resp.choices[0].message.content or "") if resp.choices else ""
        usage = resp.usage
        details = getattr(usage, "prompt_tokens_details", None) if usage else None
        return ModelReply(text=text, latency_s=latency, tokens_in=usage.prompt_tokens if usage else None,
                          tokens_out=usage.completion_tokens if usage else None, structured=schema is not None,
                          cached_tokens=getattr(details, "cached_tokens", None))
