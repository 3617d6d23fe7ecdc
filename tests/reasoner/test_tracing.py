"""Optional OpenTelemetry tracing: one GenAI client span per model call, sent over OTLP/HTTP to a real
HTTP receiver on loopback; nothing is traced when the endpoint is unset."""

from __future__ import annotations

import asyncio
import socket
import threading
import time

import pytest
import uvicorn
from fastapi import FastAPI, Request, Response

from services.reasoner import tracing
from services.reasoner.backends import make_backend
from tests.reasoner.fake_vlm import FakeVLMServer
from tests.reasoner.test_backends import run, settings_for, world

trace_pb2 = pytest.importorskip("opentelemetry.proto.collector.trace.v1.trace_service_pb2")


class OtlpReceiver:
    """A minimal OTLP/HTTP trace receiver (POST /v1/traces, protobuf) on a free loopback port."""

    def __init__(self) -> None:
        self.spans: list = []
        app = FastAPI()

        @app.post("/v1/traces")
        async def traces(request: Request) -> Response:
            msg = trace_pb2.ExportTraceServiceRequest()
            msg.ParseFromString(await request.body())
            for rs in msg.resource_spans:
                for ss in rs.scope_spans:
                    self.spans.extend(ss.spans)
            return Response(trace_pb2.ExportTraceServiceResponse().SerializeToString(),
                            media_type="application/x-protobuf")

        self._sock = socket.socket()
        self._sock.bind(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self._sock.getsockname()[1]}"
        self._server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="off"))
        self._thread = threading.Thread(target=self._server.run, kwargs={"sockets": [self._sock]}, daemon=True)

    def __enter__(self) -> OtlpReceiver:
        self._thread.start()
        while not self._server.started:
            time.sleep(0.02)
        return self

    def __exit__(self, *exc: object) -> None:
        self._server.should_exit = True
        self._thread.join(10)
        self._sock.close()


def attrs(span) -> dict:
    out = {}
    for kv in span.attributes:
        v = kv.value
        out[kv.key] = v.string_value or v.int_value or v.double_value
    return out


def test_model_calls_become_genai_spans(tmp_path) -> None:
    with OtlpReceiver() as rx, FakeVLMServer() as vlm:
        vlm.faults.extend(["invalid_json"])
        final, steps = run(settings_for("openai", vlm, otlp_endpoint=rx.url), world())
        tracing.flush()
        deadline = time.monotonic() + 10
        while len(rx.spans) < final.model_calls and time.monotonic() < deadline:
            time.sleep(0.1)
    assert final.state.value == "succeeded"
    assert len(rx.spans) == final.model_calls  # one span per model call, re-prompts included
    a = attrs(rx.spans[0])
    assert rx.spans[0].name == "chat fake-vlm" and a["gen_ai.operation.name"] == "chat"
    assert a["gen_ai.provider.name"] == "openai" and a["gen_ai.request.model"] == "fake-vlm"
    assert a["gen_ai.output.type"] == "json" and a["gen_ai.usage.input_tokens"] > 0
    assert a["gen_ai.usage.output_tokens"] > 0 and a["server.address"] == "127.0.0.1"


def test_tracing_is_off_by_default() -> None:
    with FakeVLMServer() as vlm:
        backend = make_backend(settings_for("openai", vlm))
        asyncio.run(backend.aclose())
    assert backend.tracer is None and tracing.tracer_for("") is None
