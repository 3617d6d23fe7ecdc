"""Session-wide test configuration."""

from __future__ import annotations

import os

# Never let a developer's real keys or endpoints leak into tests.
for var in ("OPENAI_API_KEY", "ANTHROPIC_API_KEY", "AERMANI_REASONER_API_KEY", "AERMANI_GATEWAY_TOKEN"):
    os.environ.pop(var, None)
os.environ.setdefault("RUST_LOG", "error")


import inspect  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture
def anyio_backend() -> str:
    """Async tests run on asyncio (the stack's loop), through anyio's pytest plugin."""
    return "asyncio"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every `async def test_...` runs under the anyio plugin; no per-test wrappers."""
    for item in items:
        fn = getattr(item, "function", None)
        if fn is not None and inspect.iscoroutinefunction(fn):
            item.add_marker(pytest.mark.anyio)


@pytest.fixture
def router() -> object:
    """One Zenoh router on a free loopback port (multicast scouting off); yields its endpoint."""
    from shared.launcher import free_port, open_router

    port = free_port()
    session = open_router(port)
    yield f"tcp/127.0.0.1:{port}"
    session.close()
