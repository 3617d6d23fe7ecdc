"""Settings of the reasoner (env AERMANI_REASONER_*)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, SecretStr
from pydantic_settings import SettingsConfigDict

from shared.messages import Variant
from shared.settings import ServiceSettings


class ReasonerSettings(ServiceSettings):
    """Reasoner configuration (AERMANI_REASONER_*): backend, model endpoint, prompt variant and step limits."""

    model_config = SettingsConfigDict(env_prefix="AERMANI_REASONER_", extra="ignore", populate_by_name=True,
                                      use_attribute_docstrings=True)

    backend: str = Field("rules", pattern=r"^[a-z][a-z0-9_]{0,31}$")
    """Policy backend: a kind registered in services/reasoner/backends (`aermani vlm backends` lists them with
    what each reads); the deterministic non-VLM baseline `rules` is the default."""
    backend_modules: str = ""
    """Comma-separated Python modules imported before the backend is looked up; each registers backends with
    `@register` (a backend kept outside this repository)."""
    variant: Variant = "full"
    """Prompt variant (paper Table IV + ReAct): unstructured, no_drt, drt_v1, drt_v2, drt_v3, full, react; or a
    Table III baseline framework over the same skills (services/reasoner/baselines.py): saycan, direct, waypoint,
    plan_once."""
    model: str = ""
    """Model name; empty picks the backend's default model."""
    base_url: str | None = None
    """Endpoint base URL, e.g. http://127.0.0.1:8000/v1 for vLLM/Ollama/llama.cpp, or the Anthropic URL."""
    api_key: SecretStr | None = None
    """API key; when unset, OPENAI_API_KEY or ANTHROPIC_API_KEY is used. Never logged."""
    request_timeout_s: float = Field(30.0, gt=0)
    """Timeout of one model HTTP request, seconds."""
    transport_retries: int = Field(3, ge=0, le=10)
    """Retries with exponential backoff on transport errors (5xx, 429, connection, timeout) per model call."""
    max_tokens: int | None = Field(None, ge=16)
    """Answer token limit per model call; unset takes the model profile's."""
    temperature: float | None = Field(None, ge=0.0, le=2.0)
    """Sampling temperature; unset takes the model profile's (0 for every built-in profile)."""
    profile: str = "auto"
    """Model profile (profiles.py: gpt-4o, gemini, claude, qwen2-vl, llava-next, generic); auto picks it from
    the model name."""
    output_mode: Literal["auto", "schema", "text"] = "auto"
    """Answer decoding: schema sends the answer's JSON schema (strict) with every request and fails when the
    server rejects it; text never sends it (free text, lenient reader); auto sends it when the profile says
    the model supports it and falls back to text, remembered per endpoint and logged once, on rejection."""
    otlp_endpoint: str = ""
    """OpenTelemetry collector base URL (OTLP/HTTP, e.g. http://127.0.0.1:4318) to send one GenAI span per model
    call to; empty (the default) traces nothing. Needs the `otel` extra."""
    replay_path: str = ""
    """JSONL file of recorded ReasoningStep records or raw answers, for backend=replay."""
    t_max_s: float = Field(600.0, gt=0)
    """T_max: a task that has not finished after this many seconds ends as timeout (paper: 10 min)."""
    max_reprompts: int = Field(2, ge=0, le=10)
    """N: re-prompts with the specific error after an invalid answer, before the step fails safely (hold)."""
    max_steps: int = Field(80, ge=1)
    """Reasoning steps after which the task fails."""
    max_failed_steps: int = Field(2, ge=1)
    """Consecutive steps without a valid answer after which the task fails."""
    history_full_steps: int = Field(6, ge=0)
    """K: the last K steps appear in full in the History; older ones are condensed to one line each."""
    history_max_chars: int = Field(6000, ge=500)
    """Character budget of the History part; the oldest entries are condensed, then dropped, to stay under."""
    paper_history: bool = False
    """The History exactly as the paper's (Algorithm 1: the DRT and the action, with its termination status, of
    each step): no vehicle state, live detections, working memory or executor messages. Off (the default) adds
    them, which the paper's prompt did not have."""
    free_text_baselines: bool = False
    """Decode the unstructured and ReAct baselines as free text (no answer schema sent, whatever `output_mode`
    says), as the paper did; off, they get their schema like every variant (in `auto`, when the profile
    supports it)."""
    prediction_coverage: float = Field(1.0, ge=0.0, le=1.0)
    """Fraction of the available skills the DRT's action predictions must cover (paper: every skill)."""
    approval: list[str] = []
    """Skills that wait for an operator's approval before they run: skill names (`grasp`, `takeoff`) or
    categories (`motion`, `manipulation`, `perception`), e.g. `["grasp", "place"]`. Empty: none."""
    approval_timeout_s: float = Field(120.0, gt=0)
    """How long a skill waits for the operator; then the vehicle holds and the step fails."""
    link_wait_s: float = Field(20.0, ge=0)
    """While the autopilot link or offboard control is down mid-task, the reasoner issues no skill and waits
    this long for it to come back before it holds and ends the task (no step is spent waiting)."""
    state_stale_s: float = Field(0.5, gt=0)
    """A vehicle state older than this counts as a lost link: a dead or silent bridge leaves its last state,
    still showing `link_ok`, behind. 0.5 s is 15 periods of the bridge's default 30 Hz (`state_rate_hz`);
    raise it with a slower state rate. (It was 2 s: skills went out on a 1.35 s-old state after a bridge
    kill.)"""
    skill_timeout_s: float = Field(180.0, gt=0)
    """Longest wait for one skill's terminal status before the reasoner holds and records a timeout."""
    speculate: bool = False
    """While a skill flies, ask the model for the next step on the observation the skill's predicted outcome
    implies (a motion's end pose, a localization's estimate at the detection), and use that answer when the
    skill ended so and the fresh observation agrees (services/reasoner/speculation.py); otherwise ask again.
    Saves a model's latency per step when predictions hold; costs the discarded calls."""
    frame_wait_s: float = Field(1.0, ge=0)
    """How long to wait for a colour frame newer than the last skill's end before using the latest one."""
    library_timeout_s: float = Field(10.0, gt=0)
    """How long to wait for the executor's skill library at task start."""
    takeoff_timeout_s: float = Field(60.0, gt=0)
    """Longest wait for the takeoff skill."""
