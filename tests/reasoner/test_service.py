"""The reasoner as a real process on real Zenoh, against an executor stand-in served on the bus."""

from __future__ import annotations

import asyncio

import pytest

from shared.keys import Keys
from shared.mcaplog import reasoning_steps, task_statuses
from shared.messages import Abort, TaskRequest, TaskState
from shared.tasks import submit_task
from tests.helpers import bus_for, run_stack
from tests.reasoner.fake_vlm import FakeVLMServer
from tests.reasoner.fake_world import MiniWorld, Thing, serve_executor

pytestmark = pytest.mark.integration
KEYS = Keys("am1")
CMD = "Pick up the red cup and place it on the table"


def world() -> MiniWorld:
    return MiniWorld([Thing("red cup"), Thing("table", "surface", size=(1.2, 0.8, 0.75))])


async def run_task(stack, w: MiniWorld, request: TaskRequest, *, skill_delay: float = 0.0, on_running=None,
                   refuse=None):
    async with bus_for(stack) as bus:
        ticker = await serve_executor(bus, w, KEYS, skill_delay=skill_delay, refuse=refuse)
        steps = bus.subscribe(KEYS.reasoning_step, maxsize=1000)
        statuses = bus.subscribe(KEYS.task_status, maxsize=100)
        try:
            await asyncio.sleep(0.5)  # let the router propagate the new queryables and subscriptions
            accept = await submit_task(bus, KEYS, request)
            assert accept.accepted, accept.reason
            if on_running is not None:
                await on_running(bus)
            while True:
                st = await statuses.recv(timeout=120)
                if st.state.terminal:
                    break
            got = []
            while len(got) < st.steps:  # Zenoh orders nothing across keys: a step may come after the end
                got.append(await steps.recv(timeout=30))
            await asyncio.sleep(0.3)  # (anything beyond the count would be a defect the tests then see)
            while steps.qsize():
                got.append(await steps.recv(timeout=1))
            return st, got
        finally:
            ticker.cancel()


async def test_rules_task_over_the_bus_and_one_task_at_a_time(tmp_path) -> None:
    w = world()
    with run_stack(["reasoner"], tmp_path) as stack:
        async def second_rejected(bus) -> None:
            other = await bus.query(KEYS.start_task, TaskRequest(command="pick up the apple"), timeout=10)
            assert not other.accepted and "already runs" in other.reason

        final, steps = await run_task(stack, w, TaskRequest(command=CMD), skill_delay=0.3,
                                     on_running=second_rejected)
    assert final.state is TaskState.SUCCEEDED, final.message
    assert w.placed_on == {"red cup": "table"} and w.executed[0] == "takeoff"
    assert [s.ste.skill for s in steps] == ["obj_localization", "grasp", "placement_localization", "place", "done"]
    assert all(s.prompt.keys() == {"command", "preamble", "history", "skill_library", "rules"} for s in steps)
    assert all(s.image_stamp_ns == 0 for s in steps)  # no camera in this stack: no image sent
    assert steps[2].outcome is not None and steps[1].skill_state.value == "succeeded"


async def test_abort_stops_the_task(tmp_path) -> None:
    w = MiniWorld([Thing("table", "surface")])  # the cup is never found: the task would scan forever
    with run_stack(["reasoner"], tmp_path) as stack:
        async def abort(bus) -> None:
            await asyncio.sleep(1.0)
            bus.publish(KEYS.abort, Abort(reason="test abort", source="test"))

        final, _steps = await run_task(stack, w, TaskRequest(command="find the purple cup"), skill_delay=0.2,
                                      on_running=abort)
    assert final.state is TaskState.ABORTED and "test abort" in final.message


@pytest.mark.parametrize("kind", ["openai", "anthropic"])
async def test_vlm_backend_process_with_injected_faults(tmp_path, kind: str) -> None:
    with FakeVLMServer() as vlm:
        vlm.faults.extend(["invalid_json", None, "500", None, "unknown_skill"])
        env = {"AERMANI_REASONER_BACKEND": kind, "AERMANI_REASONER_API_KEY": "none",
               "AERMANI_REASONER_MODEL": "fake-vlm", "AERMANI_REASONER_REQUEST_TIMEOUT_S": "5",
               "AERMANI_REASONER_BASE_URL": vlm.openai_base_url if kind == "openai" else vlm.anthropic_base_url}
        w = world()
        with run_stack(["reasoner"], tmp_path, env=env) as stack:
            final, steps = await run_task(stack, w, TaskRequest(command=CMD))
    assert final.state is TaskState.SUCCEEDED, final.message
    assert final.backend == f"{kind}:fake-vlm"
    assert [s.retries for s in steps[:3]] == [1, 0, 1]
    assert final.invalid_answers == 2 and final.model_calls == sum(len(s.calls) for s in steps)


async def test_hostile_answers_go_through_the_live_loop_and_every_step_is_logged(tmp_path) -> None:
    """Every answer issue 31 found failing, through the real reasoner process over the bus against the local
    model server, one stack for all: the task goes on (re-prompts) to its end, and every step is published and
    in the recorder's MCAP log. A valid answer whose reasoning holds a lone surrogate, Rich markup, a bidi
    override and an ANSI escape runs its skill (the surrogate replaced); 31 kB of `{x}` pairs, an integer and a
    boolean argument, two objects naming different skills, an invalid answer holding a lone surrogate (echoed
    back on the re-prompt) and an 18 kB Python literal are each re-prompted with the reason."""
    with FakeVLMServer() as vlm:
        vlm.faults.extend(["fragments", "int_argument", "hostile_text",  # step 1: two re-prompts, then runs
                           "bool_argument", "two_objects", None,  # step 2
                           "surrogate_text", "python_literal", "hostile_text"])  # step 3
        env = {"AERMANI_REASONER_BACKEND": "openai", "AERMANI_REASONER_API_KEY": "none",
               "AERMANI_REASONER_MODEL": "fake-vlm", "AERMANI_REASONER_BASE_URL": vlm.openai_base_url,
               "AERMANI_REASONER_MAX_REPROMPTS": "2", "AERMANI_RECORDER_OUT_DIR": str(tmp_path / "rec")}
        w = world()
        with run_stack(["reasoner", "recorder"], tmp_path, env=env) as stack:
            final, steps = await run_task(stack, w, TaskRequest(command=CMD))
            await asyncio.sleep(1.0)  # the last samples reach the recorder before it stops
        requests = list(vlm.requests)
    assert final.state is TaskState.SUCCEEDED, final.message
    assert [s.step for s in steps] == list(range(1, final.steps + 1)), "a step was not published"
    assert [s.retries for s in steps[:3]] == [2, 2, 2] and final.invalid_answers == 6
    errors = [[c.error for c in s.calls if not c.valid] for s in steps[:3]]
    expected = [["brackets, quotes and backslashes", "must be a string or null"],
                ["must be a string or null", "2 JSON objects naming different skills"],
                ["", "characters of objects that are not JSON"]]
    for got, want in zip(errors, expected, strict=True):
        assert all(w in g for g, w in zip(got, want, strict=True)), errors
    assert len(steps[0].calls[0].raw_answer) == 31_200  # recorded whole: within what the parser reads
    surrogate = steps[2].calls[0]
    assert "\ufffd" in surrogate.raw_answer and surrogate.error, surrogate
    # The re-prompt after it echoed the answer to the model, the surrogate replaced (it used to fail the request).
    echoes = [m["content"] for r in requests for m in r["messages"] if m["role"] == "assistant"]
    assert any(e.endswith(" \ufffd") for e in echoes), [e[-20:] for e in echoes]
    hostile = [steps[0], steps[2]]
    assert all("\ufffd [/dim][bold] \u202e" in (s.drt.reasoning or "") for s in hostile), hostile[0].drt
    assert all(c.raw_answer.encode("utf-8") for s in steps for c in s.calls)
    [log] = sorted((tmp_path / "rec").glob("*.mcap"))
    logged = reasoning_steps(log)
    assert [(s.step, len(s.calls)) for s in logged] == [(s.step, len(s.calls)) for s in steps], "a step is not logged"
    assert task_statuses(log)[final.task_id].state is TaskState.SUCCEEDED


async def test_operator_approval_rejection_replans_and_approval_runs(tmp_path) -> None:
    """With approval on for grasp: the grasp waits; a rejection is recorded as rejected by the operator and
    the policy chooses again; an approval lets it run."""
    from shared.messages import ApprovalDecision, ApprovalState

    w = world()
    env = {"AERMANI_REASONER_APPROVAL": '["grasp"]', "AERMANI_REASONER_APPROVAL_TIMEOUT_S": "60"}
    decisions: list[str] = []

    async def operator(bus) -> None:
        approvals = bus.subscribe(KEYS.approval, maxsize=100)
        while True:
            st = await approvals.recv(timeout=60)
            if st.state is not ApprovalState.PENDING:
                continue
            assert st.skill == "grasp" and st.reasoning  # the operator sees what and why
            await asyncio.sleep(0.5)
            assert not any(e.startswith("grasp") for e in w.executed)  # it waits: nothing ran while pending
            approve = bool(decisions)  # reject the first request, approve the next
            decisions.append("approve" if approve else "reject")
            reply = await bus.query(KEYS.decide_approval, ApprovalDecision(
                approval_id=st.approval_id, approved=approve, reason="" if approve else "wrong cup",
                operator="test"), timeout=10)
            assert reply.accepted, reply.reason
            again = await bus.query(KEYS.decide_approval, ApprovalDecision(approval_id=st.approval_id, approved=True),
                                    timeout=10)
            assert not again.accepted  # decided once
            if approve:
                return

    async def start_operator(bus) -> None:
        asyncio.get_running_loop().create_task(operator(bus))

    with run_stack(["reasoner"], tmp_path, env=env) as stack:
        final, steps = await run_task(stack, w, TaskRequest(command=CMD), on_running=start_operator)
    assert decisions == ["reject", "approve"]
    assert final.state is TaskState.SUCCEEDED, final.message
    grasps = [s for s in steps if s.ste and s.ste.skill == "grasp"]
    assert grasps[0].skill_state.value == "rejected" and "rejected by the operator (test): wrong cup" in \
        grasps[0].skill_message
    assert grasps[-1].skill_state.value == "succeeded"
    assert sum(e.startswith("grasp") for e in w.executed) == 1 and w.placed_on == {"red cup": "table"}


async def test_approval_is_asked_only_for_a_skill_the_executor_would_start(tmp_path) -> None:
    """The executor refuses the first grasp as out of reach (until the vehicle has flown closer): no operator
    is asked about it, the step is rejected with the executor's reason and code, and the grasp the executor
    would start is the one the operator approves."""
    from shared.messages import ApprovalDecision, ApprovalState, OutcomeCode, SkillFacts, SkillOutcome

    w = world()
    env = {"AERMANI_REASONER_APPROVAL": '["grasp"]', "AERMANI_REASONER_APPROVAL_TIMEOUT_S": "60"}
    refused_at: list[int] = []
    asked: list[tuple[int, int]] = []  # (step, grasps checked so far) of each approval request

    def too_far(req):
        if req.skill != "grasp":
            return None
        if not refused_at:
            refused_at.append(len(w.executed))
        if any(e.startswith("forward") for e in w.executed[refused_at[0]:]):
            return None
        return ("the red cup is 1.90 m away, beyond the grasp's 0.60 m reach; nothing was moved",
                SkillOutcome(code=OutcomeCode.OUT_OF_REACH, facts=SkillFacts(distance_m=1.9, reach_m=0.6)))

    async def operator(bus) -> None:
        approvals = bus.subscribe(KEYS.approval, maxsize=100)
        while True:
            st = await approvals.recv(timeout=60)
            if st.state is not ApprovalState.PENDING:
                continue
            asked.append((st.step, sum(c.skill == "grasp" for c in w.checks)))
            reply = await bus.query(KEYS.decide_approval, ApprovalDecision(approval_id=st.approval_id, approved=True,
                                                                          operator="test"), timeout=10)
            assert reply.accepted, reply.reason

    async def start_operator(bus) -> None:
        asyncio.get_running_loop().create_task(operator(bus))

    with run_stack(["reasoner"], tmp_path, env=env) as stack:
        final, steps = await run_task(stack, w, TaskRequest(command=CMD), on_running=start_operator, refuse=too_far)
    assert final.state is TaskState.SUCCEEDED, final.message
    grasps = [s for s in steps if s.ste and s.ste.skill == "grasp"]
    assert len(grasps) >= 2, [s.ste.skill for s in steps if s.ste]
    first, last = grasps[0], grasps[-1]
    assert first.skill_state.value == "rejected" and "beyond the grasp's 0.60 m reach" in first.skill_message
    assert last.skill_state.value == "succeeded"
    assert [step for step, _ in asked] == [last.step]  # one request, for the grasp that could start
    assert asked[0][1] == len(grasps)  # asked after its own check, never before one
    assert sum(e.startswith("grasp") for e in w.executed) == 1 and w.placed_on == {"red cup": "table"}


async def test_approval_timeout_holds_and_fails_the_step(tmp_path) -> None:
    w = world()
    env = {"AERMANI_REASONER_APPROVAL": '["manipulation"]', "AERMANI_REASONER_APPROVAL_TIMEOUT_S": "1",
           "AERMANI_REASONER_MAX_STEPS": "6"}
    with run_stack(["reasoner"], tmp_path, env=env) as stack:
        final, steps = await run_task(stack, w, TaskRequest(command=CMD))
    grasps = [s for s in steps if s.ste and s.ste.skill == "grasp"]
    assert grasps and all(s.skill_state.value == "failed" and "no operator decision within 1 s; vehicle held"
                          in s.skill_message for s in grasps)
    assert not any(e.startswith("grasp") for e in w.executed) and "hold" in w.executed
    assert final.state is TaskState.FAILED
