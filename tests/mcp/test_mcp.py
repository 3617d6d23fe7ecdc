"""The MCP server driven by the SDK's real client, over stdio (a subprocess) and streamable HTTP, against a
real gateway on loopback with a stand-in vehicle on a real Zenoh bus."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator

import httpx
import pytest
from mcp import Client
from mcp.client.stdio import StdioServerParameters

from services.reasoner.library import default_library
from tests.gateway.fakes import Harness
from tests.helpers import free_port

pytestmark = pytest.mark.integration

GW_TOKEN = "gw-token-for-mcp-tests-41c2"
MCP_TOKEN = "mcp-token-for-tests-9d0e"


@pytest.fixture(scope="module")
def gw(tmp_path_factory) -> Iterator[Harness]:
    h = Harness(tmp_path_factory.mktemp("mcp"), gateway_settings={"token": GW_TOKEN}, steps=3,
                step_delay_s=0.2).start()
    try:
        yield h
    finally:
        h.stop()


def _env(gw: Harness, **extra: str) -> dict[str, str]:
    env = {"AERMANI_MCP_GATEWAY_URL": gw.base_url + "/api/v1", "AERMANI_GATEWAY_TOKEN": GW_TOKEN, **extra}
    if os.environ.get("PYTHONPATH"):
        env["PYTHONPATH"] = os.environ["PYTHONPATH"]
    return env


def _json(result) -> object:
    assert not result.is_error, result.content
    if result.structured_content is not None:
        sc = result.structured_content
        return sc.get("result", sc) if isinstance(sc, dict) else sc
    return json.loads(result.content[0].text)


async def _wait_state(client: Client, task_id: str, states: set[str], timeout: float = 60.0) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        st = _json(await client.call_tool("task_status", {"task_id": task_id}))
        if st["state"] in states:
            return st
        assert time.monotonic() < deadline, st
        await asyncio.sleep(0.2)


async def _drive(client: Client) -> None:
    tools = {t.name: t for t in (await client.list_tools()).tools}
    names = set(tools)
    assert {"list_vehicles", "start_task", "task_status", "abort", "list_skills", "get_camera_frame"} <= names
    assert "run_skill" not in names  # task level only by default
    # Every tool says what it does to the world: polling is read-only, starting a task is not.
    assert all(t.title and t.annotations is not None for t in tools.values()), tools
    for name in ("list_vehicles", "task_status", "list_skills", "get_camera_frame", "list_approvals"):
        assert tools[name].annotations.read_only_hint is True and tools[name].annotations.destructive_hint is False
    assert tools["start_task"].annotations.read_only_hint is False and tools["start_task"].annotations.destructive_hint
    assert tools["abort"].annotations.idempotent_hint is True and tools["abort"].annotations.read_only_hint is False
    vehicles = _json(await client.call_tool("list_vehicles", {}))
    assert [v["vehicle_id"] for v in vehicles] == ["am1"]

    started = _json(await client.call_tool("start_task", {"command": "pick up the red cup"}))
    final = await _wait_state(client, started["task_id"], {"succeeded", "failed", "aborted", "timeout"})
    assert final["state"] == "succeeded" and final["steps"] == 3
    real = {s.name for s in default_library().skills}
    assert [s["skill"] for s in final["last_steps"]] and all(s["skill"] in real for s in final["last_steps"])
    assert all(s["reasoning"] for s in final["last_steps"])

    skills = _json(await client.call_tool("list_skills", {"vehicle": "am1"}))
    assert "grasp" in {s["name"] for s in skills} and "takeoff" not in {s["name"] for s in skills}
    assert _json(await client.call_tool("list_skills", {})) == skills  # the only vehicle needs no name

    frame = await client.call_tool("get_camera_frame", {"vehicle": "am1"})
    image = next(c for c in frame.content if c.type == "image")
    assert image.mime_type == "image/jpeg" and base64.b64decode(image.data)[:2] == b"\xff\xd8"

    endless = _json(await client.call_tool("start_task", {"command": "look around until abort"}))
    await _wait_state(client, endless["task_id"], {"running"})
    for scopeless in ({"reason": "test"}, {"reason": "test", "task_id": endless["task_id"], "fleet": True}):
        refused = await client.call_tool("abort", scopeless)
        assert refused.is_error and "exactly one scope" in refused.content[0].text, refused.content
    assert (await _wait_state(client, endless["task_id"], {"running"}))["state"] == "running"  # nothing stopped
    aborted = _json(await client.call_tool("abort", {"task_id": endless["task_id"], "reason": "mcp test"}))
    assert aborted["acknowledged"] == ["am1"]
    final = await _wait_state(client, endless["task_id"], {"aborted"})
    assert final["state"] == "aborted"

    history = await client.read_resource("aermani://tasks")
    assert endless["task_id"] in history.contents[0].text
    bad = await client.call_tool("task_status", {"task_id": "task-doesnotexist"})
    assert bad.is_error and "404" in bad.content[0].text


def test_stdio_client_starts_follows_sees_and_aborts(gw):
    params = StdioServerParameters(command=sys.executable, args=["-m", "aermani.cli", "mcp"], env=_env(gw))

    async def main():
        async with Client(params) as client:
            await _drive(client)

    asyncio.run(asyncio.wait_for(main(), 180))


def test_task_status_says_aborting_until_the_end_arrives(gw):
    """The stand-in vehicle acknowledges the abort at once and reports the task's end only when released."""
    params = StdioServerParameters(command=sys.executable, args=["-m", "aermani.cli", "mcp"], env=_env(gw))
    gw.call(lambda: setattr(gw.fake, "release", asyncio.Event()))

    async def main():
        async with Client(params) as client:
            started = _json(await client.call_tool("start_task", {"command": "look around until abort, slow to stop"}))
            await _wait_state(client, started["task_id"], {"running"})
            _json(await client.call_tool("abort", {"vehicle": "am1", "reason": "mcp aborting test"}))
            st = _json(await client.call_tool("task_status", {"task_id": started["task_id"]}))
            assert st["state"] == "aborting", st
            gw.call(gw.fake.release.set)
            assert (await _wait_state(client, started["task_id"], {"aborted"}))["state"] == "aborted"

    asyncio.run(asyncio.wait_for(main(), 120))


def test_in_a_fleet_every_vehicle_tool_needs_a_vehicle(tmp_path):
    """Two vehicles: no tool falls back to the gateway's own one or to "am1"; named, each reaches its own."""
    h = Harness(tmp_path, gateway_settings={"token": GW_TOKEN}, steps=1, step_delay_s=0.05).start()
    am2 = h.add_vehicle("am2", steps=1, step_delay_s=0.05)
    params = StdioServerParameters(command=sys.executable, args=["-m", "aermani.cli", "mcp"], env=_env(h))

    async def main():
        async with Client(params) as client:
            deadline = time.monotonic() + 30
            while sorted(v["vehicle_id"] for v in _json(await client.call_tool("list_vehicles", {}))) != ["am1", "am2"]:
                assert time.monotonic() < deadline, "the second vehicle never appeared"
                await asyncio.sleep(0.2)
            for tool, args in (("start_task", {"command": "pick up the red cup"}), ("list_skills", {}),
                               ("get_camera_frame", {})):
                refused = await client.call_tool(tool, args)
                assert refused.is_error and "2 vehicles are known (am1, am2)" in refused.content[0].text, \
                    (tool, refused.content)
            started = _json(await client.call_tool("start_task", {"command": "pick up the red cup", "vehicle": "am2"}))
            assert started["vehicle_id"] == "am2"
            assert (await _wait_state(client, started["task_id"], {"succeeded"}))["vehicle_id"] == "am2"
            assert _json(await client.call_tool("list_skills", {"vehicle": "am2"}))
            aborted = _json(await client.call_tool("abort", {"vehicle": "am2", "reason": "only am2"}))
            assert aborted["vehicles"] == ["am2"] and aborted["acknowledged"] == ["am2"]

    try:
        asyncio.run(asyncio.wait_for(main(), 120))
        assert h.fake.current_req is None and not h.fake.aborts  # am1 was never touched
        assert [a.reason for a in am2.aborts] == ["only am2"]
    finally:
        h.stop()


@contextlib.contextmanager
def _http_server(gw: Harness, **settings: object) -> Iterator[str]:
    """The MCP HTTP app on a real uvicorn server on loopback; yields its /mcp URL."""
    import uvicorn

    from services.mcp.server import http_app
    from services.mcp.settings import McpSettings

    port = free_port()
    config = McpSettings(transport="http", port=port, gateway_url=gw.base_url + "/api/v1", gateway_token=GW_TOKEN,
                         **settings)
    config.check_safe()
    server = uvicorn.Server(uvicorn.Config(http_app(config), host="127.0.0.1", port=port, log_config=None))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 20
        while not server.started:
            assert time.monotonic() < deadline, "MCP HTTP server did not start"
            time.sleep(0.05)
        yield f"http://127.0.0.1:{port}/mcp"
    finally:
        server.should_exit = True
        thread.join(10)


def _client(url: str, **headers: str):
    import httpx2
    from mcp.client.streamable_http import streamable_http_client

    http = httpx2.AsyncClient(headers=headers, timeout=30)
    return http, Client(streamable_http_client(url, http_client=http))


INIT = {"jsonrpc": "2.0", "id": 1, "method": "initialize",
        "params": {"protocolVersion": "2025-06-18", "capabilities": {}, "clientInfo": {"name": "t", "version": "1"}}}
MCP_HEADERS = {"Accept": "application/json, text/event-stream"}


def test_http_client_needs_the_token_then_drives_a_task(gw):
    with _http_server(gw, token=MCP_TOKEN) as url:
        r = httpx.post(url, json=INIT, headers=MCP_HEADERS)
        assert r.status_code == 401
        r = httpx.post(url, json=INIT, headers={**MCP_HEADERS, "Authorization": "Bearer wrong"})
        assert r.status_code == 401

        async def main():
            http, client = _client(url, Authorization=f"Bearer {MCP_TOKEN}")
            async with http, client:
                await _drive(client)

        asyncio.run(asyncio.wait_for(main(), 180))


def test_http_checks_origin_exactly(gw):
    allowed = "http://127.0.0.1:3000"
    with _http_server(gw, token=MCP_TOKEN, allowed_origins=[allowed]) as url:
        auth = {**MCP_HEADERS, "Authorization": f"Bearer {MCP_TOKEN}"}
        # The SDK's own default allowed any port of localhost; a page on another port, or a sandboxed one
        # (Origin: null), or an unrelated site is refused before the token is even looked at.
        for origin in ("http://localhost:5173", "http://127.0.0.1:3001", "https://127.0.0.1:3000", "null",
                       "http://evil.example", allowed + "/"):
            r = httpx.post(url, json=INIT, headers={**auth, "Origin": origin})
            assert r.status_code == 403, (origin, r.status_code, r.text)
            assert "AERMANI_MCP_ALLOWED_ORIGINS" in r.json()["error"]
        r = httpx.post(url, json=INIT, headers={**auth, "Origin": allowed})
        assert r.status_code == 200, r.text

        async def main():
            http, client = _client(url, Authorization=f"Bearer {MCP_TOKEN}", Origin=allowed)
            async with http, client:
                assert [v["vehicle_id"] for v in _json(await client.call_tool("list_vehicles", {}))] == ["am1"]

        asyncio.run(asyncio.wait_for(main(), 60))


def test_http_refuses_to_start_without_its_token_on_loopback_too():
    """No HTTP server without AERMANI_MCP_TOKEN, on loopback as beyond it: the CLI exits 2 with an error that
    names the variable, before it listens (its port stays free), and the app cannot be built either."""
    from services.mcp.server import http_app
    from services.mcp.settings import McpSettings
    from shared.errors import ConfigError

    port = free_port()
    env = {k: v for k, v in os.environ.items() if k not in ("AERMANI_MCP_TOKEN", "AERMANI_MCP_HOST")}
    for host in ("127.0.0.1", "0.0.0.0"):
        r = subprocess.run([sys.executable, "-m", "aermani.cli", "mcp", "--transport", "http", "--port", str(port)],
                           env={**env, "AERMANI_MCP_HOST": host, "AERMANI_GATEWAY_TOKEN": GW_TOKEN},
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 2, (host, r.returncode, r.stdout, r.stderr)
        assert "AERMANI_MCP_TOKEN" in r.stderr and "Traceback" not in r.stderr, r.stderr
        assert GW_TOKEN not in r.stderr + r.stdout  # the gateway token never reaches a log
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", port))  # nothing listened on it
    for host in ("127.0.0.1", "::1", "0.0.0.0"):
        with pytest.raises(ConfigError, match="AERMANI_MCP_TOKEN"):
            McpSettings(transport="http", host=host).check_safe()
        with pytest.raises(ConfigError, match="AERMANI_MCP_TOKEN"):
            http_app(McpSettings(transport="http", host=host, gateway_token=GW_TOKEN))
    McpSettings(transport="http", token=MCP_TOKEN).check_safe()
    McpSettings(transport="stdio").check_safe()  # stdio: the client started the process, no token needed


def test_allowed_origins_must_be_exact():
    from pydantic import ValidationError

    from services.mcp.settings import McpSettings

    for bad in ("http://localhost:*", "*", "http://127.0.0.1:3000/", "localhost:3000", "http://a.example/x"):
        with pytest.raises(ValidationError, match="not an exact origin"):
            McpSettings(allowed_origins=[bad])
    assert McpSettings(allowed_origins=["http://[::1]:3000", "https://ops.example"]).allowed_origins


def test_stdio_client_decides_approvals(tmp_path):
    h = Harness(tmp_path, gateway_settings={"token": GW_TOKEN}, steps=5, step_delay_s=0.2).start()
    params = StdioServerParameters(command=sys.executable, args=["-m", "aermani.cli", "mcp"], env=_env(h))

    async def pending(client: Client) -> list[dict]:
        deadline = time.monotonic() + 30
        while True:
            items = _json(await client.call_tool("list_approvals", {}))
            if items:
                return items
            assert time.monotonic() < deadline, "no approval request appeared"
            await asyncio.sleep(0.2)

    async def main():
        async with Client(params) as client:
            started = _json(await client.call_tool("start_task", {"command": "pick up the red cup with approval"}))
            first = (await pending(client))[0]
            assert first["skill"] == "grasp" and first["reasoning"]
            out = _json(await client.call_tool("decide_approval", {"approval_id": first["approval_id"],
                                                                  "approve": False, "reason": "not that one"}))
            assert out["approved"] is False
            again = await client.call_tool("decide_approval", {"approval_id": first["approval_id"], "approve": True})
            assert again.is_error  # decided once
            second = (await pending(client))[0]
            assert second["approval_id"] != first["approval_id"]
            _json(await client.call_tool("decide_approval", {"approval_id": second["approval_id"], "approve": True}))
            final = await _wait_state(client, started["task_id"], {"succeeded", "failed", "aborted", "timeout"})
            assert final["state"] == "succeeded"

    try:
        asyncio.run(asyncio.wait_for(main(), 120))
        assert [(d.approved, d.reason, d.operator) for d in h.fake.decisions] == [(False, "not that one", "mcp"),
                                                                                  (True, "", "mcp")]
    finally:
        h.stop()
