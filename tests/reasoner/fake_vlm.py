"""Local stand-ins for VLM HTTP APIs that answer like a VLM, for tests, demos and evaluation runs.

`FakeVLMServer` is a real uvicorn/FastAPI server on a free loopback port serving both
`POST /v1/chat/completions` (OpenAI-compatible) and `POST /v1/messages` (Anthropic Messages API). It
answers each prompt with the `rules` policy's answer computed from the prompt text alone, and can inject
faults, one per HTTP request, in the order queued:

    invalid_json    the answer cut in half (not parseable)         -> invalid answer, re-prompt
    unknown_skill   the STE names "fly_to_target"                  -> invalid answer, re-prompt
    missing_fields  the DRT (or the skill) is left out             -> invalid answer, re-prompt
    missing_arg     obj_localization without its argument          -> invalid answer, re-prompt
    fences          the answer wrapped in ```json fences            -> valid (lenient reader)
    timeout         the answer is delayed by `timeout_delay` s     -> client timeout, transport retry
    500             HTTP 500                                        -> transport retry
    none / ok       a normal answer

`outage=True` answers HTTP 503 to everything. Reuse (e.g. the evaluation engineer):

    from tests.reasoner.fake_vlm import FakeVLMServer
    with FakeVLMServer() as vlm:                   # or vlm.start() / vlm.stop()
        vlm.faults.extend(["invalid_json", None, "500"])
        env = {"AERMANI_REASONER_BACKEND": "openai", "AERMANI_REASONER_BASE_URL": vlm.openai_base_url,
               "AERMANI_REASONER_API_KEY": "none"}   # anthropic: vlm.anthropic_base_url
        ...
    vlm.requests  # every request body received (JSON), in order

Faults can also be queued over HTTP: `POST /control/faults {"faults": ["500", null]}`.
"""

from __future__ import annotations

import asyncio
import json
import socket
import threading
import time
from collections import deque
from typing import Any

import uvicorn
from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from services.reasoner.backends.rules import answer_for_prompt

FAULTS = ("invalid_json", "unknown_skill", "missing_fields", "missing_arg", "fences", "timeout", "500", "none", "ok")


def apply_fault(answer: str, fault: str | None) -> str:
    if fault in (None, "none", "ok"):
        return answer
    if fault == "invalid_json":
        return answer[: max(1, len(answer) // 2)]
    if fault == "fences":
        return f"```json\n{answer}\n```"
    try:
        obj = json.loads(answer[answer.index("{"):])
    except ValueError:
        return "I am not sure what to do."
    ste = obj.get("ste", obj)
    if fault == "unknown_skill":
        ste["skill"] = "fly_to_target"
    elif fault == "missing_arg":
        ste["skill"], ste["argument"] = "obj_localization", None
    elif fault == "missing_fields":
        if "drt" in obj:
            obj.pop("drt")
        else:
            ste.pop("skill", None)
    prefix = answer[: answer.index("{")]
    return prefix + json.dumps(obj)


def _prompt_text(content: Any) -> tuple[str, bool]:
    """(text, has_image) of a user message content (string or list of parts)."""
    if isinstance(content, str):
        return content, False
    text, image = "", False
    for part in content:
        if part.get("type") == "text":
            text += part.get("text", "")
        elif part.get("type") in ("image_url", "image"):
            image = True
    return text, image


class FakeVLMServer:
    def __init__(self, *, timeout_delay: float = 3.0, outage: bool = False, model: str = "fake-vlm") -> None:
        self.faults: deque[str | None] = deque()
        self.requests: list[dict] = []
        self.images: list[bool] = []
        self.timeout_delay = timeout_delay
        self.outage = outage
        self.model = model
        self.app = self._build()
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind(("127.0.0.1", 0))
        self.port = self._sock.getsockname()[1]
        self._server = uvicorn.Server(uvicorn.Config(self.app, log_level="warning", lifespan="off"))
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def openai_base_url(self) -> str:
        return f"{self.url}/v1"

    @property
    def anthropic_base_url(self) -> str:
        return self.url

    def _next_fault(self) -> str | None:
        return self.faults.popleft() if self.faults else None

    async def _answer(self, body: dict, messages: list[dict]) -> tuple[str | None, int, str]:
        """(answer text or None for an HTTP error, status, fault)."""
        self.requests.append(body)
        first_user = next((m for m in messages if m.get("role") == "user"), {"content": ""})
        text, image = _prompt_text(first_user.get("content", ""))
        self.images.append(image)
        if self.outage:
            return None, 503, "outage"
        fault = self._next_fault()
        if fault == "500":
            return None, 500, fault
        if fault == "timeout":
            await asyncio.sleep(self.timeout_delay)
        return apply_fault(answer_for_prompt(text), fault), 200, fault or "none"

    def _build(self) -> FastAPI:
        app = FastAPI()

        @app.post("/v1/chat/completions")
        async def chat(request: Request) -> JSONResponse:
            body = await request.json()
            answer, status, _fault = await self._answer(body, body.get("messages", []))
            if answer is None:
                return JSONResponse({"error": {"message": "injected server error", "type": "server_error"}},
                                    status_code=status)
            return JSONResponse({
                "id": f"chatcmpl-{len(self.requests)}", "object": "chat.completion", "created": int(time.time()),
                "model": body.get("model", self.model),
                "choices": [{"index": 0, "message": {"role": "assistant", "content": answer},
                             "finish_reason": "stop"}],
                "usage": {"prompt_tokens": len(json.dumps(body)) // 4, "completion_tokens": len(answer) // 4,
                          "total_tokens": (len(json.dumps(body)) + len(answer)) // 4},
            })

        @app.post("/v1/messages")
        async def messages(request: Request) -> JSONResponse:
            body = await request.json()
            answer, status, _fault = await self._answer(body, body.get("messages", []))
            if answer is None:
                return JSONResponse({"type": "error", "error": {"type": "api_error", "message": "injected"}},
                                    status_code=status)
            return JSONResponse({
                "id": f"msg_{len(self.requests)}", "type": "message", "role": "assistant",
                "model": body.get("model", self.model), "content": [{"type": "text", "text": answer}],
                "stop_reason": "end_turn", "stop_sequence": None,
                "usage": {"input_tokens": len(json.dumps(body)) // 4, "output_tokens": len(answer) // 4},
            })

        @app.post("/control/faults")
        async def faults(request: Request) -> JSONResponse:
            body = await request.json()
            self.faults.extend(body.get("faults", []))
            return JSONResponse({"queued": len(self.faults)})

        return app

    def start(self) -> FakeVLMServer:
        self._thread = threading.Thread(target=self._server.run, kwargs={"sockets": [self._sock]}, daemon=True,
                                        name="fake-vlm")
        self._thread.start()
        deadline = time.monotonic() + 30
        while not self._server.started:
            if time.monotonic() > deadline or not self._thread.is_alive():
                raise RuntimeError("fake VLM server did not start")
            time.sleep(0.02)
        return self

    def stop(self) -> None:
        self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=10)
        self._sock.close()

    def __enter__(self) -> FakeVLMServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


if __name__ == "__main__":  # `python -m tests.reasoner.fake_vlm`: serve until Ctrl-C, print the URLs
    srv = FakeVLMServer().start()
    print(f"OpenAI-compatible: {srv.openai_base_url}   Anthropic: {srv.anthropic_base_url}", flush=True)
    try:
        while True:
            time.sleep(1)
    except KeyboardInterrupt:
        srv.stop()
