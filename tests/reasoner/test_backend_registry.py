"""Extension point: a backend defined in this test module registers with @register and is usable by the
settings, a task's override (through the reasoner process and the gateway's input model) and the CLI, with
no other file changed; errors name the backend that was asked for."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from services.gateway.models import TaskCreate
from services.reasoner.backends import backend_names, make_backend
from services.reasoner.backends.base import Backend, ModelReply, ModelRequest, register
from services.reasoner.backends.rules import RulesPolicy, render_answer
from services.reasoner.settings import ReasonerSettings
from shared.errors import ConfigError
from shared.keys import Keys
from shared.messages import TaskAccept, TaskRequest, TaskState
from tests.helpers import bus_for, run_stack
from tests.reasoner.test_service import CMD, run_task, world

THIS_MODULE = __name__


@register
class CountingBackend(Backend):
    """The rules policy behind a new kind name, counting its calls: stands for any new backend module."""

    kind = "counting_test"
    summary = "a test backend registered from tests/reasoner/test_backend_registry.py"

    def __init__(self, label: str) -> None:
        self.name = f"{self.kind}:{label}"
        self.calls = 0

    @classmethod
    def from_settings(cls, settings: ReasonerSettings) -> CountingBackend:
        return cls(settings.model or "default")

    async def complete(self, request: ModelRequest) -> ModelReply:
        self.calls += 1
        t0 = time.perf_counter()
        ctx = request.context
        return ModelReply(render_answer(ctx, *RulesPolicy().decide(ctx)), time.perf_counter() - t0)


SLOW_BUILD_S = 6.0  # longer than the launcher's hung_after_s (4 s): an SDK import on a loaded 2-core machine


@register
class SlowToBuildBackend(CountingBackend):
    """Takes seconds to build, as a model SDK's first import does on a loaded machine."""

    kind = "slow_build_test"
    summary = "a test backend that blocks for SLOW_BUILD_S while it is built"

    @classmethod
    def from_settings(cls, settings: ReasonerSettings) -> SlowToBuildBackend:
        time.sleep(SLOW_BUILD_S)
        return cls(settings.model or "default")


@register
class SlowToBuildOverride(SlowToBuildBackend):
    """The same, asked for by a task (the per-task override builds its backend when the task arrives)."""

    kind = "slow_build_override_test"
    summary = "a second slow-to-build test backend, for a task's override"


def test_registered_backend_is_selectable_by_settings_and_gateway_input() -> None:
    assert "counting_test" in backend_names()
    b = make_backend(ReasonerSettings(backend="counting_test", model="m1"))
    assert isinstance(b, CountingBackend) and b.name == "counting_test:m1"
    assert TaskCreate(command="pick up the red cup", backend="counting_test").backend == "counting_test"
    assert "enum" not in TaskCreate.model_json_schema()["properties"]["backend"]["anyOf"][0]
    with pytest.raises(ConfigError, match="unknown reasoner backend 'nope'.*counting_test"):
        make_backend(ReasonerSettings(), "nope")


def test_cli_lists_a_backend_from_a_module_setting() -> None:
    env = {**os.environ, "AERMANI_REASONER_BACKEND_MODULES": THIS_MODULE}
    out = subprocess.run([sys.executable, "-m", "aermani.cli", "vlm", "backends"], capture_output=True, text=True,
                         env=env, timeout=120, check=True).stdout
    assert "counting_test" in out and "rules" in out
    bad = subprocess.run([sys.executable, "-m", "aermani.cli", "vlm", "backends"], capture_output=True, text=True,
                         env={**env, "AERMANI_REASONER_BACKEND_MODULES": "no_such_module_xyz"}, timeout=120)
    assert bad.returncode != 0 and "no_such_module_xyz" in bad.stdout + bad.stderr


@pytest.mark.integration
async def test_reasoner_process_runs_a_task_on_the_registered_backend_and_names_a_missing_key(
        tmp_path, monkeypatch) -> None:
    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    monkeypatch.delenv("AERMANI_REASONER_API_KEY", raising=False)
    keys = Keys("am1")
    w = world()
    env = {"AERMANI_REASONER_BACKEND_MODULES": THIS_MODULE, "AERMANI_REASONER_MODEL": "m2"}
    with run_stack(["reasoner"], tmp_path, env=env) as stack:
        async def missing_key() -> TaskAccept:
            async with bus_for(stack) as bus:
                return await bus.query(keys.start_task, TaskRequest(command=CMD, backend="openai"), timeout=10)

        final, steps = await run_task(stack, w, TaskRequest(command=CMD, backend="counting_test"))
        refused = await missing_key()
    assert not refused.accepted
    assert "no API key: set AERMANI_REASONER_API_KEY or OPENAI_API_KEY" in refused.reason
    assert "rules" not in refused.reason
    assert final.state is TaskState.SUCCEEDED, final.message
    assert final.backend == "counting_test:m2" and all(s.backend == "counting_test:m2" for s in steps)


def test_no_help_text_lists_the_backends() -> None:
    """The names live in the registry only: `--backend` help points to `aermani vlm backends`."""
    for cmd in (["demo"], ["eval"], ["rereason"], ["vlm", "probe"]):
        out = subprocess.run([sys.executable, "-m", "aermani.cli", *cmd, "--help"], capture_output=True, text=True,
                             timeout=120, env={**os.environ, "COLUMNS": "200"}).stdout
        assert "--backend" in out and "vlm backends" in out, cmd
        assert "anthropic" not in out and "openai, " not in out, cmd


@pytest.mark.integration
async def test_a_backend_slow_to_build_does_not_get_the_reasoner_killed_as_hung(tmp_path) -> None:
    """Building the backend (default or a task's override) runs off the event loop, so the heartbeat goes on
    and the supervising launcher never takes the reasoner for hung (it did: a loop blocked 4 s is killed)."""
    env = {"AERMANI_REASONER_BACKEND_MODULES": THIS_MODULE, "AERMANI_REASONER_BACKEND": "slow_build_test"}
    with run_stack(["reasoner"], tmp_path, env=env, supervise=True) as stack:
        (proc,) = stack.procs
        deadline = time.monotonic() + 90
        while "reasoner ready" not in proc.log_path.read_text(errors="replace"):
            assert time.monotonic() < deadline, proc.tail(40)
            time.sleep(0.2)
        final, _ = await run_task(stack, world(), TaskRequest(command=CMD))
        override, _ = await run_task(stack, world(), TaskRequest(command=CMD, backend="slow_build_override_test"))
        assert proc.restarts == 0 and not [e for e in stack.events if "hung" in e], stack.events
    assert final.state is TaskState.SUCCEEDED and final.backend == "slow_build_test:default", final.message
    assert override.state is TaskState.SUCCEEDED and override.backend == "slow_build_override_test:default", \
        override.message
