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


@pytest.fixture
def router() -> object:
    """One Zenoh router on a free loopback port (multicast scouting off); yields its endpoint."""
    from aermani.launcher import free_port, open_router

    port = free_port()
    session = open_router(port)
    yield f"tcp/127.0.0.1:{port}"
    session.close()
