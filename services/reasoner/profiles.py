"""Model profiles: per-model defaults a chat backend applies (image size limit, answer tokens, temperature,
schema support, how the image travels), picked by the model name or forced by AERMANI_REASONER_PROFILE.

Explicit settings (AERMANI_REASONER_MAX_TOKENS, _TEMPERATURE, _OUTPUT_MODE) win over a profile. The
limits are the providers' documented ones at the time of writing; docs/reasoner.md shows how to run each.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from shared.errors import ConfigError


@dataclass(frozen=True)
class ModelProfile:
    """Defaults for one model family."""

    name: str
    """Profile name (AERMANI_REASONER_PROFILE)."""
    match: tuple[str, ...]
    """Lower-case substrings of a model name that select this profile."""
    backend: str
    """The backend kind that talks to it."""
    image_max_side: int
    """Longest image side sent, px; larger frames are downscaled (the provider would downscale anyway, after
    charging the upload)."""
    max_tokens: int
    """Answer token limit."""
    temperature: float
    """Sampling temperature (0: the most repeatable decisions)."""
    schema: bool
    """Whether the endpoint accepts a strict JSON schema for the answer (auto mode tries it when True and
    falls back to free text, remembered per endpoint, when the server rejects it)."""
    image_transport: Literal["data_url", "base64_block"]
    """How the JPEG travels: an OpenAI-style `image_url` data URL, or an Anthropic base64 image block."""
    serve: str
    """How to reach it (docs)."""


PROFILES: tuple[ModelProfile, ...] = (
    ModelProfile("gpt-4o", ("gpt-4o", "gpt-4.1", "gpt-5"), "openai", 2048, 1024, 0.0, True, "data_url",
                 "OpenAI: BASE_URL unset, OPENAI_API_KEY"),
    ModelProfile("gemini", ("gemini",), "openai", 3072, 4096, 0.0, True, "data_url",
                 "Gemini's OpenAI-compatible endpoint: BASE_URL=https://generativelanguage.googleapis.com/v1beta/"
                 "openai/, API_KEY=<Gemini key>; thinking models spend answer tokens on thoughts, hence 4096"),
    ModelProfile("claude", ("claude",), "anthropic", 1568, 1024, 0.0, True, "base64_block",
                 "Anthropic: ANTHROPIC_API_KEY; structured outputs need a current model (older ones reject the "
                 "schema and auto mode falls back to text)"),
    ModelProfile("qwen2-vl", ("qwen2-vl", "qwen2.5-vl", "qwen2_vl", "qwen-vl", "qwen2.5vl"), "openai", 1024, 512, 0.0,
                 True, "data_url",
                 "vLLM: `vllm serve Qwen/Qwen2-VL-7B-Instruct` (BASE_URL=http://127.0.0.1:8000/v1); Ollama: "
                 "`ollama pull qwen2.5vl` (BASE_URL=http://127.0.0.1:11434/v1); API_KEY=none"),
    ModelProfile("llava-next", ("llava-next", "llava-v1.6", "llava_next", "llava"), "openai", 672, 512, 0.0, True,
                 "data_url",
                 "vLLM: `vllm serve llava-hf/llava-v1.6-mistral-7b-hf` (BASE_URL=http://127.0.0.1:8000/v1); "
                 "Ollama: `ollama pull llava` (BASE_URL=http://127.0.0.1:11434/v1); API_KEY=none"),
)
GENERIC = ModelProfile("generic", (), "openai", 1536, 1024, 0.0, True, "data_url",
                       "any other OpenAI-compatible endpoint")


def profile_for(model: str, forced: str = "auto") -> ModelProfile:
    """The profile named by `forced`, or the first whose `match` is in the model name, or GENERIC."""
    if forced and forced != "auto":
        for p in (*PROFILES, GENERIC):
            if p.name == forced:
                return p
        raise ConfigError(f"unknown model profile {forced!r}: set AERMANI_REASONER_PROFILE to auto or one of "
                          f"{', '.join(p.name for p in (*PROFILES, GENERIC))}")
    low = model.lower()
    return next((p for p in PROFILES if any(m in low for m in p.match)), GENERIC)
