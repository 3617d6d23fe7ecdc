"""`anthropic`: Claude through the official `anthropic` SDK (Messages API).

The user turn is [constant prompt prefix with `cache_control: ephemeral`, the rest of the prompt, image as
a base64 JPEG block]: the prefix (Preamble, Skill Library, Rules) is written to Anthropic's prompt cache
once and read on every later step and task. With a schema the request carries structured outputs,
`output_config: {format: {type: json_schema, schema}}`, and the answer is the JSON text."""

from __future__ import annotations

import base64
import time

import anthropic

from services.reasoner.backends.base import ChatBackend, ModelReply, ModelRequest, register


@register
class AnthropicBackend(ChatBackend):
    """VLM backend for Claude through the Anthropic Messages API, with prompt caching of the constant prefix."""

    kind = "anthropic"
    summary = "Claude through the Anthropic Messages API; MODEL, BASE_URL, API_KEY or ANTHROPIC_API_KEY"
    default_model = "claude-sonnet-4-5"
    key_env = "ANTHROPIC_API_KEY"
    endpoint = "Anthropic endpoint"
    client_class = anthropic.AsyncAnthropic

    def prefix_part(self, prefix: str) -> dict:
        return {"type": "text", "text": prefix, "cache_control": {"type": "ephemeral"}}

    def image_part(self, jpeg: bytes) -> dict:
        return {"type": "image", "source": {"type": "base64", "media_type": "image/jpeg",
                                            "data": base64.b64encode(jpeg).decode()}}

    async def _call(self, request: ModelRequest, schema: dict | None) -> ModelReply:
        t0 = time.perf_counter()
        kw: dict = {}
        if schema is not None:
            kw["output_config"] = {"format": {"type": "json_schema", "schema": schema}}
        if self.temperature:
            # Recent Claude models fix sampling; a non-zero setting still reaches endpoints that accept it.
            kw["extra_body"] = {"temperature": self.temperature}
        with self.sdk_errors(anthropic, schema):
            # The messages are plain dicts in the wire format; the SDK types them as TypedDicts.
            resp = await self.client.messages.create(model=self.model, max_tokens=self.max_tokens,
                                                     messages=self.messages(request), **kw)  # type: ignore[arg-type]
        latency = time.perf_counter() - t0
        text = "".join(getattr(b, "text", "") for b in resp.content)
        u = resp.usage
        cached = getattr(u, "cache_read_input_tokens", None)
        written = getattr(u, "cache_creation_input_tokens", None) or 0
        # input_tokens counts only what was neither read from nor written to the cache.
        return ModelReply(text=text, latency_s=latency, tokens_in=u.input_tokens + (cached or 0) + written,
                          tokens_out=u.output_tokens, structured=schema is not None, cached_tokens=cached)
