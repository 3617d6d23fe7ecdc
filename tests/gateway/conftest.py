"""Fixtures: a gateway served in-process over a real router with a stand-in vehicle on the bus."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator

import httpx
import pytest

from tests.gateway.fakes import Harness

TOKEN = "test-token-7f3a9c2e51b4"


@pytest.fixture(scope="module")
def gw(tmp_path_factory) -> Iterator[Harness]:
    h = Harness(tmp_path_factory.mktemp("gw"), gateway_settings={"token": TOKEN}).start()
    try:
        yield h
    finally:
        h.stop()


@pytest.fixture
def client(gw: Harness) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=gw.base_url + "/api/v1", timeout=30.0,
                      headers={"Authorization": f"Bearer {TOKEN}"}) as c:
        yield c


def read_sse(client: httpx.Client, url: str, last_event_id: int | None = None, timeout: float = 60.0,
             stop: int | None = None) -> list[dict]:
    """Read an SSE stream until the server ends it (or `stop` events); return events as dicts."""
    headers = {"Last-Event-ID": str(last_event_id)} if last_event_id is not None else {}
    events, cur = [], {}
    deadline = time.monotonic() + timeout
    with client.stream("GET", url, headers=headers, timeout=timeout) as r:
        assert r.status_code == 200, r.read()
        assert r.headers["content-type"].startswith("text/event-stream")
        for line in r.iter_lines():
            if time.monotonic() > deadline:
                raise TimeoutError(f"SSE stream {url} did not end in {timeout} s")
            if line == "":
                if "data" in cur:
                    cur["data"] = json.loads(cur["data"])
                    events.append(cur)
                    if stop is not None and len(events) >= stop:
                        break
                cur = {}
            elif line.startswith(":"):
                continue
            else:
                field, _, value = line.partition(":")
                cur[field] = value[1:] if value.startswith(" ") else value
    return events


def wait_task(client: httpx.Client, task_id: str, states: set[str], timeout: float = 60.0) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        body = client.get(f"/tasks/{task_id}").json()
        if body["state"] in states:
            return body
        if time.monotonic() > deadline:
            raise TimeoutError(f"task {task_id} still {body['state']}, wanted {states}")
        time.sleep(0.1)
