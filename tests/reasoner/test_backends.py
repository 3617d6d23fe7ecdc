"""OpenAI-compatible and Anthropic backends against local fake VLM servers, through the real loop."""

from __future__ import annotations

import asyncio
import json

import pytest

from services.reasoner.backends import make_backend
from services.reasoner.backends.replay import ListReplaySource, ReplayBackend
from services.reasoner.loop import TaskRunner
from services.reasoner.settings import ReasonerSettings
from shared.errors import ConfigError
from shared.messages import TaskRequest, TaskState
from tests.reasoner.fake_vlm import FakeVLMServer
from tests.reasoner.fake_world import MiniWorld, MiniWorldPort, Thing

CMD = "Pick up the red cup and place it on the table"


def world() -> MiniWorld:
    return MiniWorld([Thing("red cup"), Thing("table", "surface", size=(1.2, 0.8, 0.75))])


@pytest.fixture(scope="module")
def vlm():
    with FakeVLMServer(timeout_delay=3.0) as srv:
        yield srv


def settings_for(kind: str, vlm: FakeVLMServer, **kw: object) -> ReasonerSettings:
    base = vlm.openai_base_url if kind == "openai" else vlm.anthropic_base_url
    return ReasonerSettings(**{"backend": kind, "base_url": base, "api_key": "none", "model": "fake-vlm",
                               "request_timeout_s": 1.0, "transport_retries": 3, "max_steps": 20, **kw})


def run(settings: ReasonerSettings, w: MiniWorld):
    backend = make_backend(settings)
    steps, statuses = [], []

    async def go():
        try:
            return await TaskRunner(TaskRequest(command=CMD), settings, backend, MiniWorldPort(w),
                                    publish_step=steps.append, publish_status=statuses.append).run(asyncio.Event())
        finally:
            await backend.aclose()

    return asyncio.run(asyncio.wait_for(go(), 120)), steps


@pytest.mark.parametrize("kind", ["openai", "anthropic"])
def test_clean_run_sends_image_and_counts_tokens(kind: str, vlm: FakeVLMServer) -> None:
    vlm.faults.clear()
    n0 = len(vlm.requests)
    w = world()
    final, steps = run(settings_for(kind, vlm), w)
    assert final.state is TaskState.SUCCEEDED, final.message
    assert final.backend == f"{kind}:fake-vlm" and w.placed_on == {"red cup": "table"}
    assert all(vlm.images[n0:]) and len(vlm.requests) - n0 == final.model_calls == len(steps)
    assert all(c.tokens_in and c.tokens_out and c.latency_s > 0 for s in steps for c in s.calls)
    body = vlm.requests[n0]
    content = body["messages"][0]["content"]
    # constant prefix first (cache_control on Anthropic), then the rest of the prompt, the image last
    assert content[0]["text"].startswith("# Preamble") and "# Task command" in content[1]["text"]
    if kind == "openai":
        assert content[2]["image_url"]["url"].startswith("data:image/jpeg;base64,")
        assert body["response_format"]["json_schema"]["strict"] is True
    else:
        assert content[2]["source"]["media_type"] == "image/jpeg"
        assert content[0]["cache_control"] == {"type": "ephemeral"} and body["tool_choice"]["type"] == "tool"
        assert body["temperature"] == 0.0  # sent: the API's default would be 1.0
    # every request carried the skill-enum schema; the stand-in found nothing to object to
    assert all(sc is not None for sc in vlm.schemas[n0:]) and vlm.schema_errors == []
    assert all(c.structured for s in steps for c in s.calls)
    assert len({r["messages"][0]["content"][0]["text"] for r in vlm.requests[n0:]}) == 1  # byte-identical prefix
    assert all(c.tokens_cached for s in steps[1:] for c in s.calls)  # the prefix came from the prompt cache


@pytest.mark.parametrize("kind", ["openai", "anthropic"])
def test_injected_faults_show_as_reprompts_and_iar(kind: str, vlm: FakeVLMServer) -> None:
    vlm.faults.clear()
    n0 = len(vlm.requests)
    # step 1: two invalid answers then a valid one; step 2: missing DRT then valid; step 3: fenced (valid);
    # step 4: a 500 and a timeout, retried by the transport, then valid; step 5: missing argument then valid.
    vlm.faults.extend(["invalid_json", "unknown_skill", None, "missing_fields", None, "fences", "500", "timeout",
                       None, "missing_arg", None])
    w = world()
    final, steps = run(settings_for(kind, vlm), w)
    assert final.state is TaskState.SUCCEEDED, final.message
    assert [s.retries for s in steps[:5]] == [2, 1, 0, 0, 1]
    assert [c.valid for c in steps[0].calls] == [False, False, True]
    assert "No JSON object" in steps[0].calls[0].error and "Unknown skill 'fly_to_target'" in steps[0].calls[1].error
    assert "Missing DRT field(s)" in steps[1].calls[0].error
    assert steps[2].calls[0].raw_answer.startswith("```json") and steps[2].valid
    assert "needs an argument" in steps[4].calls[0].error
    assert final.invalid_answers == 4 and final.model_calls == sum(len(s.calls) for s in steps)
    # 4 invalid out of the model calls: IAR as the paper defines it
    assert final.invalid_answers / final.model_calls == pytest.approx(4 / final.model_calls)
    # the re-prompt carried the specific error back to the model
    second = vlm.requests[n0 + 1]
    last_user = second["messages"][-1]["content"]
    assert "Your previous answer was invalid: No JSON object" in (last_user if isinstance(last_user, str)
                                                                   else json.dumps(last_user))
    assert len(vlm.requests) - n0 == final.model_calls + 2  # the 500 and the timeout were transport retries


def test_invalid_beyond_budget_fails_step_and_holds(vlm: FakeVLMServer) -> None:
    vlm.faults.clear()
    vlm.faults.extend(["invalid_json"] * 6)
    w = world()
    final, steps = run(settings_for("openai", vlm, max_reprompts=2, max_failed_steps=2), w)
    assert final.state is TaskState.FAILED and "2 steps without a valid answer" in final.message
    assert [len(s.calls) for s in steps] == [3, 3] and not any(s.valid for s in steps)
    assert w.executed.count("hold") == 2 and final.invalid_answers == 6


def test_outage_fails_task_with_clear_message() -> None:
    with FakeVLMServer(outage=True) as down:
        s = ReasonerSettings(backend="openai", base_url=down.openai_base_url, api_key="none", model="m",
                             request_timeout_s=1.0, transport_retries=1)
        w = world()
        final, steps = run(s, w)
    assert final.state is TaskState.FAILED and "model unavailable" in final.message and "503" in final.message
    assert len(down.requests) == 2 and w.executed[-1] == "hold"


def test_invalid_answer_then_transport_error_stays_in_the_step_record(vlm: FakeVLMServer) -> None:
    """An invalid answer followed, in the same step, by a transport error is still in the step's calls (and in
    the status's counters), so IAR counts it."""
    vlm.faults.clear()
    vlm.faults.extend(["invalid_json", "500", "500"])  # the re-prompt fails twice: transport retry budget 1
    w = world()
    final, steps = run(settings_for("openai", vlm, transport_retries=1), w)
    assert final.state is TaskState.FAILED and "model unavailable" in final.message
    assert [c.valid for c in steps[-1].calls] == [False]
    assert final.invalid_answers == 1 and final.model_calls == 1


def test_missing_key_is_a_config_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    with pytest.raises(ConfigError, match="AERMANI_REASONER_API_KEY"):
        make_backend(ReasonerSettings(backend="openai"))


def test_replay_backend_reproduces_a_run(tmp_path) -> None:
    w = world()
    final, steps = run(ReasonerSettings(backend="rules"), w)
    log = tmp_path / "steps.jsonl"
    log.write_text("".join(s.model_dump_json() + "\n" for s in steps))
    w2 = world()
    s2 = ReasonerSettings(backend="replay", replay_path=str(log))
    final2, steps2 = run(s2, w2)
    assert final2.state is TaskState.SUCCEEDED and w2.executed == w.executed
    assert [s.ste for s in steps2] == [s.ste for s in steps]
    # exhausted log: the task fails safely
    w3 = MiniWorld([Thing("red cup")])
    backend = ReplayBackend(ListReplaySource(['{"ste": {"skill": "yaw_left"}}']))
    out = []
    final3 = asyncio.run(TaskRunner(TaskRequest(command=CMD), ReasonerSettings(), backend, MiniWorldPort(w3),
                                    publish_step=out.append, publish_status=lambda s: None).run(asyncio.Event()))
    assert final3.state is TaskState.FAILED and "no more answers" in final3.message


@pytest.mark.parametrize("kind", ["openai", "anthropic"])
def test_schema_rejected_falls_back_to_text_once_per_endpoint(kind: str, caplog: pytest.LogCaptureFixture) -> None:
    with FakeVLMServer(reject_schema=True) as srv:
        w = world()
        with caplog.at_level("WARNING", logger="aermani.reasoner.backends"):
            final, steps = run(settings_for(kind, srv), w)
    assert final.state is TaskState.SUCCEEDED, final.message
    # the first request carried the schema and was refused; every later one is free text
    assert srv.schemas[0] is not None and all(sc is None for sc in srv.schemas[1:])
    assert len(srv.requests) == final.model_calls + 1
    assert not any(c.structured for s in steps for c in s.calls)
    warned = [r for r in caplog.records if "rejected schema-constrained output" in r.getMessage()]
    assert len(warned) == 1 and srv.url.split("//")[1] in warned[0].getMessage()


def test_schema_mode_is_tried_again_after_a_refusal_ages(monkeypatch: pytest.MonkeyPatch) -> None:
    """A refusal is remembered for SCHEMA_RETRY_S, not for the life of the process: once the server takes the
    schema again (a transient 400), the next calls after that time are schema-constrained again."""
    from services.reasoner.backends import base

    with FakeVLMServer(reject_schema=True) as srv:
        run(settings_for("openai", srv), world())
        assert srv.schemas[0] is not None and srv.schemas[1] is None
        srv.reject_schema = False
        n0 = len(srv.requests)
        run(settings_for("openai", srv, max_steps=2), world())
        assert all(sc is None for sc in srv.schemas[n0:]), "a fresh refusal must still be honoured"
        monkeypatch.setattr(base, "SCHEMA_RETRY_S", 0.0)
        n1 = len(srv.requests)
        final, steps = run(settings_for("openai", srv), world())
    assert final.state is TaskState.SUCCEEDED, final.message
    assert all(sc is not None for sc in srv.schemas[n1:]) and all(c.structured for s in steps for c in s.calls)


def test_forced_modes(vlm: FakeVLMServer) -> None:
    n0 = len(vlm.requests)
    final, steps = run(settings_for("openai", vlm, output_mode="text"), world())
    assert final.state is TaskState.SUCCEEDED and all(sc is None for sc in vlm.schemas[n0:])
    assert "response_format" not in vlm.requests[n0] and not any(c.structured for s in steps for c in s.calls)
    with FakeVLMServer(reject_schema=True) as srv:
        final, _ = run(settings_for("openai", srv, output_mode="schema"), world())
    assert final.state is TaskState.FAILED and "rejected the answer schema" in final.message
    assert "AERMANI_REASONER_OUTPUT_MODE" in final.message


@pytest.mark.parametrize("variant", ["unstructured", "no_drt", "drt_v1", "drt_v3", "full", "react"])
def test_each_variant_answers_in_its_format_under_its_schema(variant: str, vlm: FakeVLMServer) -> None:
    n0 = len(vlm.requests)
    final, steps = run(settings_for("openai", vlm, variant=variant, max_steps=8), world())
    # unstructured has no History: from the prompt alone the stand-in cannot tell how far the task got
    assert final.state is (TaskState.FAILED if variant == "unstructured" else TaskState.SUCCEEDED), final.message
    assert vlm.schema_errors == [] and final.invalid_answers == 0 and steps
    answers = [c.raw_answer for s in steps for c in s.calls]
    if variant == "react":
        assert all(set(json.loads(a)) == {"thought", "action"} for a in answers)
        assert all(s.drt.reasoning for s in steps)
    elif variant == "full":
        assert all(set(json.loads(a)["drt"]) == {"image_description", "summary", "action_predictions", "reasoning"}
                   for a in answers)
    props = vlm.schemas[n0]["properties"]
    assert ("drt" in props) == (variant.startswith("drt") or variant == "full")


def test_standing_fault_schedule() -> None:
    """The schedule of the committed variants run (every 20th answer truncated), reproducible from the repo."""
    with FakeVLMServer(fault_every=3) as srv:
        final, steps = run(settings_for("openai", srv), world())
    calls = [c for s in steps for c in s.calls]
    assert final.state is TaskState.SUCCEEDED
    assert [i for i, c in enumerate(calls, 1) if not c.valid] == [i for i in range(1, len(calls) + 1) if i % 3 == 0]
