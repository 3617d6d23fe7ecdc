"""`anthropic`: Claude through the official `anthropic` SDK (Messages API).

The user turn is [constant prompt prefix with `cache_control: ephemeral`, the rest of the prompt, image as
a base64 JPEG block]: the prefix (Preamble, Skill Library, Rules) is written to Anthropic's prompt cache
once and read on every later step and task. With a schema the answer is a forced tool call: one tool whose
`input_schema` is the answer schema and `tool_choice` naming it, which every Claude model with tool use honours
(Claude 3 and later; structured outputs through `output_config` exist only on current models, and an older one
would fall back to free text). The tool call's input is the answer. `temperature` is always sent (0 by the
model profile: the paper's runs are deterministic; the API's own default is 1.0)."""

from __future__ import annotations

import base64
import json
import time

from services.reasoner.backends.base import ChatBackend, ModelReply, ModelRequest, register
from services.reasoner.schema import SCHEMA_NAME

ANSWER_TOOL = ("Give your answer for this step: the Descriptive Reasoning Trace and the Skill To Execute, in the "
               "format the Rules describe.")


def answer_text(content: list, forced_tool: bool) -> str:
    """The answer of a Messages API reply: the forced tool call's input as JSON text when a schema was sent (the
    text blocks beside it are commentary), else the text blocks."""
    if forced_tool:
        call = next((b for b in content if getattr(b, "type", "") == "tool_use" and b.name == SCHEMA_NAME), None)
        if call is not None:
            return json.dumps(call.input, ensure_ascii=False)
    return "".join(getattr(b, "text", "") for b in content)


@register
class AnthropicBackend(ChatBackend):
    """VLM backend for Claude through the Anthropic Messages API, with prompt caching of the constant prefix."""

    kind = "anthropic"
    summary = "Claude through the Anthropic Messages API; MODEL, BASE_URL, API_KEY or ANTHROPIC_API_KEY"
    default_model = "claude-sonnet-4-5"
    key_env = "ANTHROPIC_API_KEY"
    endpoint = "Anthropic endpoint"
    sdk_name = "anthropic"
    client_name = "AsyncAnthropic"

    def prefix_part(self, prefix: str) -> dict:
        return {"type": "text", "text": prefix, "cache_control": {"type": "ephemeral"}}

    def image_part(self, jpeg: bytes) -> dict:
        return {"type": "image", "source": {"type": "base64", "media_type": "image/jpeg",
                                            "data": base64.b64encode(jpeg).decode()}}

    async def _call(self, request: ModelRequest, schema: dict | None) -> ModelReply:
        t0 = time.perf_counter()
        kw: dict = {}
        if schema is not None:
            kw["tools"] = [{"name": SCHEMA_NAME, "description": ANSWER_TOOL, "input_schema": schema}]
            kw["tool_choice"] = {"type": "tool", "name": SCHEMA_NAME}
        if self.temperature is not None:
            # In the body: this SDK's `create` no longer names the parameter, the Messages API still reads it.
            kw["extra_body"] = {"temperature": self.temperature}
        with self.sdk_errors(schema):
            # The messages are plain dicts in the wire format; the SDK types them as TypedDicts.
            resp = await self.client.messages.create(model=self.model, max_tokens=self.max_tokens,
                                                     messages=self.messages(request), **kw)  # type: ignore[arg-type]
        latency = time.perf_counter() - t0
        text = answer_text(resp.content, schema is not None)
        u = resp.usage
        cached = getattr(u, "cache_read_input_tokens", None)
        written = getattr(u, "cache_creation_input_tokens", None) or 0
        # input_tokens counts only what was neither read from nor written to the cache.
        return ModelReply(text=text, latency_s=latency, tokens_in=u.input_tokens + (cached or 0) + written,
                          tokens_out=u.output_tokens, structured=schema is not None, cached_tokens=cached)
