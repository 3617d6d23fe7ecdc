"""The gateway's store under a kill: every event the API has handed out survives a SIGKILL during a burst, and
each task status is stored together with its event (one transaction, never one without the other)."""

from __future__ import annotations

import json
import signal
import sqlite3
import threading
from pathlib import Path

import anyio
import httpx
import pytest

from shared.bus import Bus
from shared.keys import Keys
from shared.messages import (
    DescriptiveReasoningTrace,
    ModelCall,
    ReasoningStep,
    SkillToExecute,
    TaskState,
    TaskStatus,
)
from tests.gateway.conftest import TOKEN, read_sse
from tests.gateway.test_process import GatewayProcess

pytestmark = pytest.mark.integration

VID = "am1"
TASK = "task-durable01"
BURST = 400


class LiveGateway(GatewayProcess):
    """The gateway process, up as soon as its HTTP API answers (no reasoner runs in this test)."""

    def ready(self) -> bool:
        return httpx.get(f"{self.url}/live", timeout=5).status_code == 200


def _status(state: TaskState, steps: int) -> TaskStatus:
    return TaskStatus(vehicle_id=VID, task_id=TASK, command="pick up the red cup", state=state, steps=steps)


def _step(i: int) -> ReasoningStep:
    return ReasoningStep(
        vehicle_id=VID, task_id=TASK, step=i, backend="rules", prompt={"command": "pick up the red cup"},
        calls=(ModelCall(raw_answer="{}", valid=True, latency_s=0.01),),
        drt=DescriptiveReasoningTrace(image_description=f"frame {i}", summary=f"{i - 1} skills so far",
                                      action_predictions={"forward": "closer"}, reasoning="approach"),
        ste=SkillToExecute(skill="forward"), valid=True)


def _acknowledged(url: str, stop: threading.Event, seen: dict[int, int]) -> None:
    """Follow the task's SSE stream and note every (event id -> step) the API handed out, until the kill."""
    headers = {"Authorization": f"Bearer {TOKEN}"}
    try:
        with httpx.stream("GET", f"{url}/tasks/{TASK}/events", headers=headers, timeout=30) as r:
            cur: dict[str, str] = {}
            for line in r.iter_lines():
                if stop.is_set():
                    return
                if line == "":
                    if cur.get("event") == "step":
                        seen[int(cur["id"])] = json.loads(cur["data"])["step"]
                    cur = {}
                elif not line.startswith(":"):
                    field, _, value = line.partition(":")
                    cur[field] = value[1:] if value.startswith(" ") else value
    except httpx.HTTPError:
        return  # the gateway was killed under the stream


async def test_sigkill_during_a_burst_loses_no_acknowledged_event(router: str, tmp_path: Path) -> None:
    gw = LiveGateway(tmp_path, router)
    gw.start()
    bus = await Bus.open(connect=[router])
    keys = Keys(VID)
    seen: dict[int, int] = {}
    stop = threading.Event()
    try:
        # The task exists first (its running status), then a burst of steps while a client follows it.
        for _ in range(50):
            bus.publish(keys.task_status, _status(TaskState.RUNNING, 0))
            await anyio.sleep(0.1)
            if httpx.get(f"{gw.url}/tasks/{TASK}", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200:
                break
        follower = threading.Thread(target=_acknowledged, args=(gw.url, stop, seen), daemon=True)
        follower.start()
        await anyio.sleep(0.5)
        for i in range(1, BURST + 1):
            bus.publish(keys.reasoning_step, _step(i), reliable=True)
            if i % 10 == 0:
                bus.publish(keys.task_status, _status(TaskState.RUNNING, i))
                await anyio.sleep(0.01)
            if len(seen) >= 60 and gw.proc is not None and gw.proc.poll() is None:
                gw.stop(signal.SIGKILL)  # mid-burst, with writes in flight
        if gw.proc is not None and gw.proc.poll() is None:
            gw.stop(signal.SIGKILL)
        stop.set()
        follower.join(10)
    finally:
        await bus.close()
        if gw.proc is not None and gw.proc.poll() is None:
            gw.stop(signal.SIGKILL)
    assert len(seen) >= 60, f"the API acknowledged only {len(seen)} events before the kill"

    db = sqlite3.connect(tmp_path / "gateway.sqlite3")
    stored = {row[0]: row[1] for row in db.execute(
        "SELECT id, json_extract(data, '$.step') FROM events WHERE task_id = ? AND kind = 'step'", (TASK,))}
    lost = {i: s for i, s in seen.items() if stored.get(i) != s}
    assert not lost, f"acknowledged events missing or changed after the kill: {sorted(lost.items())[:10]}"
    # The task row and its newest status event agree: a status was never stored without its event or back.
    row = db.execute("SELECT state, json_extract(status, '$.steps') FROM tasks WHERE task_id = ?", (TASK,)).fetchone()
    last = db.execute("SELECT json_extract(data, '$.state'), json_extract(data, '$.steps') FROM events "
                      "WHERE task_id = ? AND kind = 'task_status' ORDER BY id DESC LIMIT 1", (TASK,)).fetchone()
    assert row == last, (row, last)
    db.close()

    # A restarted gateway keeps the history and, with no reasoner alive to finish the task, ends it with the
    # reason instead of leaving it running forever; the stream then replays every stored step.
    gw2 = LiveGateway(tmp_path, router)
    gw2.start()
    try:
        with httpx.Client(base_url=gw2.url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30) as client:
            task = client.get(f"/tasks/{TASK}").json()
            assert task["state"] in ("running", "failed"), task
            if task["state"] == "failed":
                assert "reasoner" in task["message"], task
                replay = {int(e["id"]): e["data"]["step"] for e in read_sse(client, f"/tasks/{TASK}/events")
                          if e.get("event") == "step"}
                assert all(replay.get(i) == s for i, s in seen.items())
    finally:
        gw2.stop()
