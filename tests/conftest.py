"""Session-wide test configuration."""

from __future__ import annotations

import os

# Never let a developer's real keys or endpoints leak into tests.
for var in ("OPENAI_API_KEY", "ANTHROPIC_API_KEY", "AERMANI_REASONER_API_KEY", "AERMANI_GATEWAY_TOKEN"):
    os.environ.pop(var, None)
os.environ.setdefault("RUST_LOG", "error")


import inspect  # noqa: E402

import pytest  # noqa: E402

# MuJoCo picks its OpenGL platform when first imported: the simulator's default (headless EGL) is set before any
# test module imports mujoco itself, whatever the collection order (services/sim/render.py check_gl_platform).
import services.sim  # noqa: E402, F401


@pytest.fixture
def anyio_backend() -> str:
    """Async tests run on asyncio (the stack's loop), through anyio's pytest plugin."""
    return "asyncio"


@pytest.hookimpl(tryfirst=True)
def pytest_pycollect_makeitem(collector: pytest.Collector, name: str, obj: object) -> None:
    """Every `async def test_...` runs under the anyio plugin (marked before the plugin collects it, so
    parametrized tests work too); no per-test wrappers."""
    if collector.funcnamefilter(name) and inspect.iscoroutinefunction(obj):
        pytest.mark.anyio(obj)


# The tests that run the whole stack with the simulator: each takes most of two cores for minutes and keeps the
# stack's deadlines (a vehicle state older than half a second is stale), so two at once would make each other fail.
STACK = (
    "tests/evaluation/test_integration.py", "tests/evaluation/test_fork.py",
    "tests/evaluation/test_baselines_integration.py", "tests/evaluation/test_output_modes_integration.py",
    "tests/faults/test_faults.py", "tests/reasoner/test_demo.py", "tests/reasoner/test_rules_stack.py",
    "tests/executor/test_grasp_closed_loop.py", "tests/executor/test_integration.py", "tests/gateway/test_fullstack.py",
    "tests/shared/test_secure_stack.py", "tests/perception/test_sweep.py",
)


def _in_stack(nodeid: str) -> bool:
    return nodeid.split("::", 1)[0] in STACK


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The STACK files' tests carry the `stack` mark (`-m "not stack"` leaves them out)."""
    for item in items:
        if _in_stack(item.nodeid):
            item.add_marker(pytest.mark.stack)


def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object:
    """`make test` runs two pytest-xdist workers with `--dist loadgroup`: the STACK tests are one group, run on one
    worker one at a time, first (the largest group goes first); every other test, mostly waiting on sockets and
    timers, is its own unit for the other worker. The group is chosen here from the test's file because xdist's
    own `xdist_group` mark no longer reaches its scheduler under pytest 9.2 (pytest-xdist issue 1386)."""
    if config.getoption("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class StackOnOneWorker(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return "stack" if _in_stack(nodeid) else nodeid

    return StackOnOneWorker(config, log)


@pytest.fixture
def router() -> object:
    """One Zenoh router on a free loopback port (multicast scouting off); yields its endpoint."""
    from aermani.launcher import free_port, open_router

    port = free_port()
    session = open_router(port)
    yield f"tcp/127.0.0.1:{port}"
    session.close()
