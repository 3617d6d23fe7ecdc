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
    hostile_text    a valid answer whose reasoning holds a lone surrogate (escaped), Rich markup, a bidi override,
                    a zero-width space and an ANSI escape              -> valid, its step published
    fragments       31 kB of tiny `{x}` pairs                        -> invalid answer, re-prompt
    int_argument    obj_localization with the argument 5             -> invalid answer, re-prompt
    bool_argument   obj_localization with the argument true          -> invalid answer, re-prompt
    two_objects     the answer, then a second object naming another skill -> invalid (ambiguous), re-prompt
    surrogate_text  the answer cut in half with a lone surrogate (a real one: the HTTP body escapes it)
                                                                     -> invalid answer, re-prompt that echoes it
    python_literal  an 18 kB Python literal that fails at its end     -> invalid answer, re-prompt
    phantom_object  a valid answer whose image description also claims a green bottle (deliberately wrong
                    when none is detected: the grounding check's test)  -> valid, its step published
    phantom_hold    a valid answer whose summary and reasoning claim the gripper holds the red cup
                    (deliberately wrong while it is empty)              -> valid, its step published
    detour          a valid answer naming yaw_left instead of the policy's skill (a run that diverges)

`outage=True` answers HTTP 503 to everything.

Schema-constrained output: a request with an answer schema (OpenAI `response_format` of type
`json_schema`; Anthropic a forced tool's `input_schema`, or `output_config.format`) is checked (a valid JSON
schema, strict: every object closed and all its properties required, `strict: true` on OpenAI) and answered
with JSON in the schema's shape (ReAct as {"thought", "action"}; the Table III baselines, saycan, direct,
waypoint and plan_once, in their formats: prompt_reader.baseline_answer; on Anthropic as the tool call's input); every
problem found, and every answer that does not validate against the schema it came with, is appended to
`schema_errors` (tests assert it stays empty).
`reject_schema=True` answers such requests HTTP 400, like a server without structured outputs.
Prompt caching is imitated: a first text block seen before (OpenAI) or marked `cache_control` (Anthropic)
is reported as cached prompt tokens (tokens here are characters / 4: the stand-in has no tokenizer).

Reuse (e.g. the evaluation engineer):

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

import jsonschema
import uvicorn
from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse as _JSONResponse

from tests.reasoner.prompt_reader import answer_for_prompt

FAULTS = ("invalid_json", "unknown_skill", "missing_fields", "missing_arg", "fences", "timeout", "500", "none", "ok",
          "hostile_text", "fragments", "int_argument", "bool_argument", "two_objects", "surrogate_text",
          "python_literal", "phantom_object", "phantom_hold", "detour")
# A valid answer whose reasoning holds what a model may send and a terminal or an encoder chokes on: half an
# emoji (a lone surrogate, escaped in the JSON), Rich markup, a right-to-left override, a zero-width space and an
# ANSI escape (JSON escapes: the parser decodes them).
HOSTILE_TEXT = r" \ud83d [/dim][bold] \u202e \u200b \u001b[2J"


class JSONResponse(_JSONResponse):
    """A JSON response with everything outside ASCII escaped, as many servers write it: a lone surrogate in an
    answer travels as `\\ud83d` (UTF-8 could not carry it), and the client's JSON decoder makes it one again."""

    def render(self, content: Any) -> bytes:
        return json.dumps(content, ensure_ascii=True, separators=(",", ":")).encode()


def apply_fault(answer: str, fault: str | None) -> str:
    if fault in (None, "none", "ok"):
        return answer
    if fault == "invalid_json":
        return answer[: max(1, len(answer) // 2)]
    if fault == "fences":
        return f"```json\n{answer}\n```"
    if fault == "fragments":
        return ("{x} " * 7800)[:31_200]
    if fault == "surrogate_text":
        return answer[: max(1, len(answer) // 2)] + " \ud83d"
    if fault == "python_literal":
        return "{'a': [" + "1," * 9000 + "], 'b': x}"
    try:
        obj = json.loads(answer[answer.index("{"):])
    except ValueError:
        return "I am not sure what to do."
    ste = obj.get("ste", obj)
    _edit(obj, ste, fault)
    prefix = answer[: answer.index("{")]
    if fault == "two_objects":
        other = json.loads(json.dumps(obj))
        other_ste = other.get("ste", other)
        other_ste["skill"] = "yaw_left" if ste.get("skill") != "yaw_left" else "yaw_right"
        other_ste["argument"] = None
        return f"{prefix}{json.dumps(obj)}\nOr, if that fails: {json.dumps(other)}"
    if fault == "hostile_text":
        drt = obj.get("drt", obj)
        drt["reasoning"] = f"{drt.get('reasoning') or ''}@@HOSTILE@@"
        return prefix + json.dumps(obj).replace("@@HOSTILE@@", HOSTILE_TEXT)
    return prefix + json.dumps(obj)


def _edit(obj: dict, ste: dict, fault: str | None) -> None:
    """The faults that edit the decoded answer in place: invalid skills and arguments, a missing field, or a
    deliberately wrong answer that stays valid: another skill (detour), a DRT that claims a green bottle in view
    (phantom_object) or the red cup in the gripper (phantom_hold) whatever was measured."""
    drt = obj.get("drt")
    if fault == "unknown_skill":
        ste["skill"] = "fly_to_target"
    elif fault == "missing_arg":
        ste["skill"], ste["argument"] = "obj_localization", None
    elif fault in ("int_argument", "bool_argument"):
        ste["skill"], ste["argument"] = "obj_localization", 5 if fault == "int_argument" else True
    elif fault == "missing_fields":
        if "drt" in obj:
            obj.pop("drt")
        else:
            ste.pop("skill", None)
    elif fault == "detour":
        ste["skill"], ste["argument"] = "yaw_left", None
    elif drt is not None and fault == "phantom_object":
        drt["image_description"] = f"{drt.get('image_description') or ''} I also see a green bottle."
    elif drt is not None and fault == "phantom_hold":
        drt["summary"] = "Holding: red cup."
        drt["reasoning"] = f"I am holding the red cup. {drt.get('reasoning') or ''}"


def _anthropic_content(body: dict, answer: str) -> list[dict]:
    """A Messages API reply's content: the answer as the forced tool's input when it decodes to an object (a
    faulty answer that does not stays text, as a model's malformed output would), else a text block."""
    if body.get("tools"):
        try:
            obj = json.loads(answer[answer.index("{"):]) if "{" in answer else None
        except ValueError:
            obj = None
        if isinstance(obj, dict):
            return [{"type": "tool_use", "id": "toolu_fake", "name": body["tools"][0]["name"], "input": obj}]
    return [{"type": "text", "text": answer}]


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


def strict_problems(schema: Any, where: str = "$") -> list[str]:
    """What OpenAI's strict mode would refuse: open objects, optional properties, unsupported keywords."""
    out: list[str] = []
    if isinstance(schema, dict):
        if schema.get("type") == "object":
            props = schema.get("properties", {})
            if schema.get("additionalProperties") is not False:
                out.append(f"{where}: object without additionalProperties: false")
            if sorted(schema.get("required", [])) != sorted(props):
                out.append(f"{where}: not every property is required")
        for bad in ("minLength", "maxLength", "oneOf", "allOf", "not", "if"):
            if bad in schema:
                out.append(f"{where}: {bad} is not supported in strict mode")
        for k, v in schema.items():
            out += strict_problems(v, f"{where}.{k}")
    elif isinstance(schema, list):
        for i, v in enumerate(schema):
            out += strict_problems(v, f"{where}[{i}]")
    return out


def shaped_answer(answer: str, schema: dict) -> str:
    """The rules answer in the schema's JSON shape, as a constrained decoder would emit it."""
    props = schema.get("properties", {})
    if answer.startswith("Thought:"):  # react
        thought, _, action = answer.partition("\nAction: ")
        return json.dumps({"thought": thought.removeprefix("Thought: "), "action": json.loads(action)})
    if not answer.startswith("{"):  # unstructured: skill or skill(arg)
        skill, _, arg = answer.partition("(")
        ste = {"skill": skill, "argument": arg[:-1] if arg else None}
        return json.dumps({"ste": ste} if "ste" in props else ste)
    if list(props) == ["ste"] and "ste" not in json.loads(answer):  # direct: the flat skill object in "ste"
        return json.dumps({"ste": json.loads(answer)})
    return answer


class FakeVLMServer:
    def __init__(self, *, timeout_delay: float = 3.0, outage: bool = False, model: str = "fake-vlm",
                 reject_schema: bool = False, fault_every: int = 0, periodic_fault: str = "invalid_json",
                 port: int = 0, reject_images: bool = False, latency_s: float = 0.0) -> None:
        self.faults: deque[str | None] = deque()
        self.latency_s = latency_s
        """Every answer is sent this long after its request arrived, like a model's response time (a remote
        VLM's median is about 1 s: benchmarks/speculation.py)."""
        self.fault_every = fault_every
        """When > 0 and no fault is queued, every fault_every-th answer gets `periodic_fault` (a standing schedule
        for pipeline checks, e.g. scripts/eval_variants.sh: every 20th answer truncated)."""
        self.periodic_fault = periodic_fault
        self._answered = 0
        self.requests: list[dict] = []
        self.images: list[bool] = []
        self.schemas: list[dict | None] = []
        """The answer schema of each request (None: free text), in order."""
        self.schema_errors: list[str] = []
        self.reject_schema = reject_schema
        self.reject_images = reject_images
        """Answer HTTP 400 to a request with an image, like a text-only model's server."""
        self._seen_prefixes: set[str] = set()
        self.timeout_delay = timeout_delay
        self.outage = outage
        self.model = model
        self.app = self._build()
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind(("127.0.0.1", port))
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
        self._answered += 1
        if self.faults:
            return self.faults.popleft()
        if self.fault_every and self._answered % self.fault_every == 0:
            return self.periodic_fault
        return None

    def _schema_of(self, body: dict) -> dict | None:
        """The answer schema a request carries (checked), or None for free text."""
        rf = body.get("response_format")
        if rf is not None:  # OpenAI-compatible
            if rf.get("type") != "json_schema":
                self.schema_errors.append(f"response_format type {rf.get('type')!r}, expected json_schema")
                return None
            js = rf.get("json_schema", {})
            if js.get("strict") is not True or not js.get("name"):
                self.schema_errors.append("json_schema without strict: true or a name")
            schema = js.get("schema")
        elif body.get("tools") is not None:  # Anthropic: the answer as a forced tool call
            tools = body["tools"]
            choice = body.get("tool_choice") or {}
            if len(tools) != 1 or choice.get("type") != "tool" or choice.get("name") != tools[0].get("name"):
                self.schema_errors.append(f"tools {[t.get('name') for t in tools]} not forced by tool_choice {choice}")
            schema = tools[0].get("input_schema")
        else:
            fmt = (body.get("output_config") or {}).get("format")
            if fmt is None:
                return None
            if fmt.get("type") != "json_schema":
                self.schema_errors.append(f"output_config.format type {fmt.get('type')!r}")
            schema = fmt.get("schema")
        try:
            jsonschema.Draft202012Validator.check_schema(schema)
        except jsonschema.SchemaError as exc:
            self.schema_errors.append(f"not a JSON schema: {exc.message}")
            return None
        self.schema_errors.extend(strict_problems(schema))
        return schema

    def _cached(self, content: Any, anthropic: bool) -> int:
        """Prompt 'tokens' (chars / 4) of the first text block that a prompt cache would hold."""
        if isinstance(content, str) or not content or content[0].get("type") != "text":
            return 0
        first = content[0]
        if anthropic and "cache_control" not in first:
            return 0
        hit = first["text"] in self._seen_prefixes
        self._seen_prefixes.add(first["text"])
        return len(first["text"]) // 4 if hit else 0

    async def _answer(self, body: dict, messages: list[dict]) -> tuple[str | None, int, str]:
        """(answer text or None for an HTTP error, status, fault)."""
        self.requests.append(body)
        first_user = next((m for m in messages if m.get("role") == "user"), {"content": ""})
        text, image = _prompt_text(first_user.get("content", ""))
        self.images.append(image)
        schema = self._schema_of(body)
        self.schemas.append(schema)
        if self.outage:
            return None, 503, "outage"
        if image and self.reject_images:
            return None, 400, "image_rejected"
        if schema is not None and self.reject_schema:
            return None, 400, "schema_rejected"
        fault = self._next_fault()
        if fault == "500":
            return None, 500, fault
        if fault == "timeout":
            await asyncio.sleep(self.timeout_delay)
        if self.latency_s > 0:
            await asyncio.sleep(self.latency_s)
        answer = answer_for_prompt(text)
        if schema is not None:
            answer = shaped_answer(answer, schema)
            for err in jsonschema.Draft202012Validator(schema).iter_errors(json.loads(answer)):
                self.schema_errors.append(f"the policy's answer does not fit the schema: {err.message}")
        return apply_fault(answer, fault), 200, fault or "none"

    def _build(self) -> FastAPI:
        app = FastAPI()

        @app.post("/v1/chat/completions")
        async def chat(request: Request) -> JSONResponse:
            body = await request.json()
            answer, status, _fault = await self._answer(body, body.get("messages", []))
            if answer is None:
                kind = "invalid_request_error" if status == 400 else "server_error"
                msg = "response_format json_schema is not supported" if status == 400 else "injected server error"
                return JSONResponse({"error": {"message": msg, "type": kind}}, status_code=status)
            cached = self._cached(body["messages"][0].get("content", ""), anthropic=False)
            return JSONResponse({
                "id": f"chatcmpl-{len(self.requests)}", "object": "chat.completion", "created": int(time.time()),
                "model": body.get("model", self.model),
                "choices": [{"index": 0, "message": {"role": "assistant", "content": answer},
                             "finish_reason": "stop"}],
                "usage": {"prompt_tokens": len(json.dumps(body)) // 4, "completion_tokens": len(answer) // 4,
                          "total_tokens": (len(json.dumps(body)) + len(answer)) // 4,
                          "prompt_tokens_details": {"cached_tokens": cached}},
            })

        @app.post("/v1/messages")
        async def messages(request: Request) -> JSONResponse:
            body = await request.json()
            answer, status, _fault = await self._answer(body, body.get("messages", []))
            if answer is None:
                kind = "invalid_request_error" if status == 400 else "api_error"
                return JSONResponse({"type": "error", "error": {"type": kind, "message": "injected"}},
                                    status_code=status)
            cached = self._cached(body["messages"][0].get("content", ""), anthropic=True)
            return JSONResponse({
                "id": f"msg_{len(self.requests)}", "type": "message", "role": "assistant",
                "model": body.get("model", self.model), "content": _anthropic_content(body, answer),
                "stop_reason": "tool_use" if body.get("tools") else "end_turn", "stop_sequence": None,
                "usage": {"input_tokens": len(json.dumps(body)) // 4 - cached, "output_tokens": len(answer) // 4,
                          "cache_read_input_tokens": cached, "cache_creation_input_tokens": 0},
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
    import argparse

    ap = argparse.ArgumentParser(description="Serve the local VLM stand-in (not a model: the rules policy).")
    ap.add_argument("--port", type=int, default=0, help="loopback port (0: a free one)")
    ap.add_argument("--fault-every", type=int, default=0, help="every N-th answer gets --fault")
    ap.add_argument("--fault", default="invalid_json", choices=FAULTS)
    ap.add_argument("--reject-schema", action="store_true", help="answer HTTP 400 to requests with a schema")
    a = ap.parse_args()
    srv = FakeVLMServer(port=a.port, fault_every=a.fault_every, periodic_fault=a.fault,
                        reject_schema=a.reject_schema).start()
    print(f"OpenAI-compatible: {srv.openai_base_url}   Anthropic: {srv.anthropic_base_url}", flush=True)
    try:
        while True:
            time.sleep(1)
    except KeyboardInterrupt:
        srv.stop()
