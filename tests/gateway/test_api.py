"""API tests: the gateway over a real Zenoh router with a stand-in vehicle (reasoner/executor) on the bus."""

from __future__ import annotations

import httpx
import pytest

from tests.gateway.conftest import TOKEN, read_sse, wait_task

pytestmark = pytest.mark.integration


def test_task_runs_and_streams_to_the_end(client: httpx.Client) -> None:
    r = client.post("/tasks", json={"command": "pick up the red cup and place it on the table"})
    assert r.status_code == 202, r.text
    created = r.json()
    tid = created["task_id"]
    assert created["vehicle_id"] == "am1"
    assert created["links"]["events"] == f"/api/v1/tasks/{tid}/events"

    events = read_sse(client, f"/tasks/{tid}/events")
    ids = [int(e["id"]) for e in events]
    assert ids == sorted(ids) and len(set(ids)) == len(ids)
    kinds = [e["event"] for e in events]
    assert kinds.count("step") == 3
    assert "skill_status" in kinds
    assert kinds[-1] == "task_status" and events[-1]["data"]["state"] == "succeeded"
    assert all(e["data"]["task_id"] == tid for e in events)

    task = client.get(f"/tasks/{tid}").json()
    assert task["state"] == "succeeded"
    assert [s["step"]["step"] for s in task["reasoning_steps"]] == [1, 2, 3]
    first = task["reasoning_steps"][0]["step"]
    assert first["drt"]["image_description"].startswith("a red cup")
    assert first["ste"]["skill"] == "takeoff"
    assert len(task["skill_results"]) == 3 and {s["state"] for s in task["skill_results"]} == {"succeeded"}
    m = task["metrics"]
    assert (m["steps"], m["model_calls"], m["invalid_answers"]) == (3, 4, 1)
    assert m["iar"] == pytest.approx(0.25)
    assert m["latency_p50_s"] is not None and m["latency_p95_s"] >= m["latency_p50_s"]
    assert m["skills"] == {"succeeded": 3}
    assert task["last_event_id"] == ids[-1]

    # Resuming after an event replays only what came later; resuming after the end returns at once.
    later = read_sse(client, f"/tasks/{tid}/events", last_event_id=ids[2])
    assert [int(e["id"]) for e in later] == ids[3:]
    assert read_sse(client, f"/tasks/{tid}/events", last_event_id=ids[-1]) == []

    page = client.get("/tasks", params={"limit": 1}).json()
    assert page["limit"] == 1 and page["total"] >= 1 and len(page["items"]) == 1
    assert client.get("/tasks", params={"state": "succeeded"}).json()["items"][0]["steps"] == 3


def test_conflict_abort_and_restart(gw, client: httpx.Client) -> None:
    r = client.post("/tasks", json={"command": "look around until abort", "vehicle_id": "am1"})
    assert r.status_code == 202, r.text
    tid = r.json()["task_id"]
    wait_task(client, tid, {"running"})
    second = client.post("/tasks", json={"command": "another one"})
    assert second.status_code == 409
    assert tid in second.json()["detail"]

    # Read part of the live stream, then abort: the stream must end with the aborted status.
    assert len(read_sse(client, f"/tasks/{tid}/events", stop=3)) == 3
    ab = client.post(f"/tasks/{tid}/abort", json={"reason": "test abort"})
    assert ab.status_code == 202, ab.text
    assert ab.json() == {"vehicles": ["am1"], "acknowledged": ["am1"], "task_id": tid,
                         "messages": {"am1": "holding"}, "services": {"am1": {"executor": "holding"}}}
    assert gw.fake.aborts[-1].task_id == tid and gw.fake.aborts[-1].reason == "test abort"
    end = read_sse(client, f"/tasks/{tid}/events")[-1]
    assert end["event"] == "task_status" and end["data"]["state"] == "aborted"
    assert wait_task(client, tid, {"aborted"})["message"] == "test abort"
    again = client.post(f"/tasks/{tid}/abort")
    assert again.status_code == 409 and again.json()["error"] == "conflict"

    all_ = client.post("/abort")
    assert all_.status_code == 202 and all_.json()["vehicles"] == ["am1"]
    assert all_.json()["acknowledged"] == ["am1"]
    assert gw.fake.aborts[-1].task_id is None


def test_a_task_whose_end_was_missed_does_not_block_its_vehicle(gw, client: httpx.Client) -> None:
    """The store still shows a task running whose final status was published while the gateway was away. The
    reasoner is idle, so it accepts a new task, and the stale row ends with the reason instead of answering
    409 forever. (While a task really runs, the reasoner refuses: the conflict test above.)"""
    from shared.messages import TaskState, TaskStatus

    store, stale = gw.app.state.store, "task-missedend01"
    status = TaskStatus(vehicle_id="am1", task_id=stale, command="an old one", state=TaskState.RUNNING, steps=4)
    gw.call(lambda: store.create_task(stale, "am1", "an old one", {"command": "an old one"}))
    gw.call(lambda: store.record_status("am1", status.model_dump(mode="json")))
    assert client.get(f"/tasks/{stale}").json()["state"] == "running"
    r = client.post("/tasks", json={"command": "a fresh one", "vehicle_id": "am1"})
    assert r.status_code == 202, r.text
    old = client.get(f"/tasks/{stale}").json()
    assert old["state"] == "failed" and "its end was not received" in old["message"], old
    wait_task(client, r.json()["task_id"], {"succeeded", "failed"})


@pytest.mark.parametrize(("body", "status", "where"), [
    ({"command": "x" * 501}, 422, "body.command"),
    ({"command": "fly\x00 away"}, 422, "body.command"),
    ({"command": "line\nbreak"}, 422, "body.command"),
    ({"command": "place it on the \u202eelbat"}, 422, "body.command"),  # right-to-left override
    ({"command": "pick up the red\u200bcup"}, 422, "body.command"),  # zero-width space
    ({"command": "   "}, 422, "body.command"),
    ({"command": "ok", "variant": "nope"}, 422, "body.variant"),
    ({"command": "ok", "surprise": 1}, 422, "body.surprise"),
    ({"command": "ok", "vehicle_id": "zz9"}, 404, None),
    ({"command": "ok", "vehicle_id": "a/b"}, 422, "body.vehicle_id"),
])
def test_task_validation(client: httpx.Client, body: dict, status: int, where: str | None) -> None:
    r = client.post("/tasks", json=body)
    assert r.status_code == status, r.text
    err = r.json()
    assert err["status"] == status and err["detail"] and err["error"]
    if where:
        assert where in err["detail"]
        assert err["fields"][0]["loc"] == where.split(".")
    else:
        assert "zz9" in err["detail"]


def test_errors_are_json(client: httpx.Client) -> None:
    for method, url, status in [("GET", "/tasks/task-nope", 404), ("GET", "/nowhere", 404),
                                ("DELETE", "/tasks", 405), ("GET", "/tasks?limit=0", 422),
                                ("GET", "/tasks/bad%20id", 422)]:
        r = client.request(method, url)
        assert r.status_code == status, (url, r.text)
        assert r.headers["content-type"] == "application/json"
        assert r.json()["status"] == status and r.json()["detail"]
    r = client.post("/tasks", content=b"{not json", headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and "json" in r.json()["detail"].lower()
    r = client.get("/tasks/task-nope/events", headers={"Last-Event-ID": "abc"})
    assert r.status_code == 422


def test_health_and_camera(gw, client: httpx.Client) -> None:
    h = client.get("/health").json()
    assert h["ok"] and h["database"]
    am1 = next(v for v in h["vehicles"] if v["vehicle_id"] == "am1")
    assert am1["services"]["reasoner"] and am1["services"]["executor"]
    assert am1["link_ok"] is True and am1["offboard_ok"] is True and am1["battery_remaining"] == 87.0

    r = client.get("/vehicles/am1/camera.jpg")
    assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg"
    assert r.content[:2] == b"\xff\xd8" and int(r.headers["x-frame-stamp-ns"]) > 0
    assert client.get("/vehicles/zz9/camera.jpg").status_code == 404

    with client.stream("GET", "/vehicles/am1/camera.mjpeg", params={"frames": 2}) as s:
        assert s.headers["content-type"].startswith("multipart/x-mixed-replace")
        body = s.read()
    assert body.count(b"--aermaniframe\r\nContent-Type: image/jpeg") == 2
    assert body.count(b"\xff\xd8") >= 2


PROTECTED = [("POST", "/tasks", {"command": "pick up the cup"}), ("GET", "/tasks/task-x/events", None),
             ("POST", "/tasks/task-x/abort", None), ("POST", "/abort", None),
             ("GET", "/vehicles/am1/camera.jpg", None), ("GET", "/vehicles/am1/camera.mjpeg", None)]


@pytest.mark.parametrize(("method", "url", "body"), PROTECTED)
@pytest.mark.parametrize("auth", [None, "Bearer wrong-token", f"Basic {TOKEN}", f"Bearer {TOKEN}x",
                                  "Bearer é".encode("latin-1")])
def test_protected_routes_need_the_token(gw, method: str, url: str, body: dict | None,
                                        auth: str | bytes | None) -> None:
    headers = {"Authorization": auth} if auth else {}
    with httpx.Client(base_url=gw.base_url + "/api/v1", timeout=30.0) as c:
        r = c.request(method, url, json=body, headers=headers)
    assert r.status_code == 401, r.text
    assert r.json()["error"] == "unauthorized"
    assert r.headers["www-authenticate"].startswith("Bearer")
    assert TOKEN not in r.text


def test_openapi_is_complete(gw) -> None:
    spec = httpx.get(gw.base_url + "/api/v1/openapi.json").json()
    paths = spec["paths"]
    for p in ("/api/v1/tasks", "/api/v1/tasks/{task_id}", "/api/v1/tasks/{task_id}/events",
              "/api/v1/tasks/{task_id}/abort", "/api/v1/abort", "/api/v1/health",
              "/api/v1/vehicles/{vehicle_id}/camera.jpg", "/api/v1/vehicles/{vehicle_id}/camera.mjpeg"):
        assert p in paths
    schemas = spec["components"]["schemas"]
    assert schemas["TaskCreate"]["examples"] and schemas["TaskCreated"]["examples"]
    assert schemas["TaskCreate"]["properties"]["command"]["description"]
    assert "text/event-stream" in paths["/api/v1/tasks/{task_id}/events"]["get"]["responses"]["200"]["content"]
    assert paths["/api/v1/tasks"]["post"]["responses"]["409"]["content"]["application/json"]["schema"]
    assert spec["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"
    page = httpx.get(gw.base_url + "/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]


def test_cli_task_command(gw, monkeypatch) -> None:
    import typer
    from typer.testing import CliRunner

    from services.gateway.cli import register

    app = typer.Typer()
    register(app)

    @app.command()
    def _other() -> None:  # a second command keeps typer in multi-command mode, as in `aermani`
        pass

    monkeypatch.setenv("AERMANI_GATEWAY_TOKEN", TOKEN)
    result = CliRunner().invoke(app, ["task", "pick up the red cup", "--url", gw.base_url])
    assert result.exit_code == 0, result.output
    assert "step 3: forward -> succeeded" in result.output and "succeeded: task complete" in result.output
    monkeypatch.setenv("AERMANI_GATEWAY_TOKEN", "wrong-token")
    result = CliRunner().invoke(app, ["task", "again", "--url", gw.base_url])
    assert result.exit_code == 1 and "invalid bearer token" in result.output


def _new_gate(gw) -> None:
    import asyncio

    gw.call(lambda: setattr(gw.fake, "release", asyncio.Event()))


def _wait_for(what: str, cond, timeout: float = 60.0) -> None:
    import time

    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def test_a_task_is_aborting_until_its_end_arrives(gw, client: httpx.Client) -> None:
    """From the abort until the reasoner's end is stored, the task says `aborting` (no longer `running`); the
    vehicle here acknowledges at once but reports the end only when the test releases it."""
    _new_gate(gw)
    r = client.post("/tasks", json={"command": "look around until abort, slow to stop", "vehicle_id": "am1"})
    assert r.status_code == 202, r.text
    tid = r.json()["task_id"]
    wait_task(client, tid, {"running"})
    assert client.post(f"/tasks/{tid}/abort", json={"reason": "stop slowly"}).status_code == 202
    task = client.get(f"/tasks/{tid}").json()
    assert task["state"] == "aborting", task["state"]
    listed = client.get("/tasks", params={"state": "aborting"}).json()
    assert [t["task_id"] for t in listed["items"]] == [tid] and listed["total"] == 1
    assert tid not in {t["task_id"] for t in client.get("/tasks", params={"state": "running"}).json()["items"]}
    assert client.get("/tasks").json()["items"][0]["state"] == "aborting"
    # Still unfinished: a second abort is sent again, not refused.
    assert client.post(f"/tasks/{tid}/abort", json={"reason": "again"}).status_code == 202
    gw.call(gw.fake.release.set)
    assert wait_task(client, tid, {"aborted", "running", "failed", "succeeded"})["state"] == "aborted"
    assert client.post(f"/tasks/{tid}/abort").status_code == 409


def test_abort_on_an_ended_task_is_refused_while_its_last_step_is_stored(gw, client: httpx.Client,
                                                                         monkeypatch) -> None:
    """The reasoner's end arrived but waits for its last step (held here until released): the task is over,
    so an abort gets 409 then too, not 202 during the grace."""
    import services.gateway.fleet as fleet_module

    monkeypatch.setattr(fleet_module, "FINISH_GRACE_S", 600.0)  # the end waits for the step, not the clock
    _new_gate(gw)
    fleet = gw.app.state.fleet
    r = client.post("/tasks", json={"command": "pick up the red cup, withholds its last step", "vehicle_id": "am1"})
    assert r.status_code == 202, r.text
    tid = r.json()["task_id"]
    _wait_for("the held end", lambda: fleet.ended(tid) is not None)
    refused = client.post(f"/tasks/{tid}/abort", json={"reason": "too late"})
    assert refused.status_code == 409, refused.text
    assert "already ended (succeeded)" in refused.json()["detail"]
    assert client.get(f"/tasks/{tid}").json()["state"] == "running"  # not aborting: no abort was sent
    gw.call(gw.fake.release.set)
    task = wait_task(client, tid, {"succeeded", "failed", "aborted"})
    assert task["state"] == "succeeded" and task["steps"] == 3
    assert fleet.ended(tid) is None


def test_in_a_fleet_a_task_names_its_vehicle(tmp_path) -> None:
    """With two reasoners alive, a task without a vehicle is refused (the gateway's own id is no default) and
    nothing starts; named, it runs on that vehicle."""
    from tests.gateway.fakes import Harness

    h = Harness(tmp_path, gateway_settings={"token": TOKEN}, steps=1, step_delay_s=0.05).start()
    try:
        am2 = h.add_vehicle("am2", steps=1, step_delay_s=0.05)
        with httpx.Client(base_url=h.base_url + "/api/v1", timeout=30.0,
                          headers={"Authorization": f"Bearer {TOKEN}"}) as c:
            _wait_for("both reasoners", lambda: sorted(v["vehicle_id"] for v in c.get("/health").json()["vehicles"]
                                                       if v["services"].get("reasoner")) == ["am1", "am2"])
            r = c.post("/tasks", json={"command": "pick up the red cup"})
            assert r.status_code == 422 and "am1, am2" in r.json()["detail"], r.text
            assert c.get("/tasks").json()["total"] == 0
            assert h.fake.current_req is None and am2.current_req is None
            r = c.post("/tasks", json={"command": "pick up the red cup", "vehicle_id": "am2"})
            assert r.status_code == 202 and r.json()["vehicle_id"] == "am2", r.text
            assert wait_task(c, r.json()["task_id"], {"succeeded"})["vehicle_id"] == "am2"
            assert h.fake.current_req is None
    finally:
        h.stop()
