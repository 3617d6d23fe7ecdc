"""Optional OpenTelemetry tracing of model calls, with the GenAI semantic conventions.

Off by default. `AERMANI_REASONER_OTLP_ENDPOINT=http://collector:4318` sends one CLIENT span per model call
(`chat <model>`: gen_ai.operation.name, gen_ai.provider.name, gen_ai.request.model / max_tokens /
temperature, gen_ai.output.type json|text, gen_ai.usage.input_tokens / output_tokens, server.address /
port, error.type) over OTLP/HTTP. Needs the `otel` extra (opentelemetry-sdk and the OTLP/HTTP exporter);
without it a set endpoint is a ConfigError saying what to install.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any
from urllib.parse import urlparse

from shared.errors import ConfigError

_PROVIDERS: dict[str, Any] = {}
"""OTLP endpoint -> TracerProvider (one per endpoint and process)."""


def tracer_for(endpoint: str) -> Any | None:
    """A tracer exporting to `endpoint` (the collector's base URL), or None when tracing is off."""
    if not endpoint:
        return None
    try:
        from opentelemetry.exporter.otlp.proto.http.trace_exporter import OTLPSpanExporter
        from opentelemetry.sdk.resources import Resource
        from opentelemetry.sdk.trace import TracerProvider
        from opentelemetry.sdk.trace.export import BatchSpanProcessor
    except ImportError as exc:
        raise ConfigError(f"AERMANI_REASONER_OTLP_ENDPOINT is set but OpenTelemetry is not installed ({exc}); "
                          "install the extra: pip install 'aermani[otel]'") from exc
    provider = _PROVIDERS.get(endpoint)
    if provider is None:
        provider = TracerProvider(resource=Resource.create({"service.name": "aermani-reasoner"}))
        provider.add_span_processor(BatchSpanProcessor(
            OTLPSpanExporter(endpoint=endpoint.rstrip("/") + "/v1/traces"), schedule_delay_millis=500))
        _PROVIDERS[endpoint] = provider
    return provider.get_tracer("aermani.reasoner")


def flush(timeout_s: float = 5.0) -> None:
    """Export pending spans now (at task end and shutdown)."""
    for p in _PROVIDERS.values():
        p.force_flush(int(timeout_s * 1000))


@contextlib.contextmanager
def model_call_span(tracer: Any | None, *, provider: str, model: str, base_url: str, max_tokens: int,
                    temperature: float, structured: bool) -> Iterator[Any | None]:
    """A GenAI client span around one model call; yields the span (None when tracing is off)."""
    if tracer is None:
        yield None
        return
    from opentelemetry.trace import SpanKind, Status, StatusCode

    url = urlparse(base_url) if base_url else None
    attrs: dict[str, Any] = {"gen_ai.operation.name": "chat", "gen_ai.provider.name": provider,
                             "gen_ai.request.model": model, "gen_ai.request.max_tokens": max_tokens,
                             "gen_ai.request.temperature": temperature,
                             "gen_ai.output.type": "json" if structured else "text"}
    if url is not None and url.hostname:
        attrs["server.address"] = url.hostname
        attrs["server.port"] = url.port or (443 if url.scheme == "https" else 80)
    with tracer.start_as_current_span(f"chat {model}", kind=SpanKind.CLIENT, attributes=attrs,
                                      record_exception=False, set_status_on_exception=False) as span:
        try:
            yield span
        except Exception as exc:
            span.set_attribute("error.type", type(exc).__name__)
            span.set_status(Status(StatusCode.ERROR, str(exc)[:200]))
            raise


def record_usage(span: Any | None, tokens_in: int | None, tokens_out: int | None, structured: bool) -> None:
    if span is None:
        return
    if tokens_in is not None:
        span.set_attribute("gen_ai.usage.input_tokens", tokens_in)
    if tokens_out is not None:
        span.set_attribute("gen_ai.usage.output_tokens", tokens_out)
    span.set_attribute("gen_ai.output.type", "json" if structured else "text")
