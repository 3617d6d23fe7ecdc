"""/tasks: start a task, list and inspect tasks, follow one task's events, abort it."""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import APIRouter, Header, Path, Query, Request
from sse_starlette import EventSourceResponse, ServerSentEvent

from services.gateway.deps import Authorized, FleetDep, SettingsDep, StoreDep
from services.gateway.errors import ApiError, responses
from services.gateway.fleet import Fleet
from services.gateway.models import (
    AbortIn,
    AbortOut,
    Metrics,
    StepOut,
    TaskCreate,
    TaskCreated,
    TaskDetail,
    TaskLinks,
    TaskPage,
    TaskPhase,
    TaskSummary,
    abort_summary,
)
from shared.errors import NoResponder, QueryTimeout, RemoteError
from shared.keys import Keys
from shared.messages import TaskRequest, TaskState, new_id
from shared.stats import percentile_or_none

router = APIRouter(prefix="/tasks", tags=["tasks"])

TaskId = Annotated[str, Path(pattern=r"^[A-Za-z0-9_.-]{1,64}$", description="Task id, e.g. task-1a2b3c4d5e6f.",
                             examples=["task-1a2b3c4d5e6f"])]
TERMINAL = {s.value for s in TaskState if s.terminal}


def links(task_id: str) -> TaskLinks:
    base = f"/api/v1/tasks/{task_id}"
    return TaskLinks(self=base, events=f"{base}/events", abort=f"{base}/abort")


def pick_vehicle(fleet: FleetDep, wanted: str | None) -> str:
    """`wanted`, or the only vehicle whose reasoner is alive. With several, the caller must name one: the
    gateway's own vehicle id is no default then, a task sent to the wrong vehicle would fly it."""
    alive = fleet.reasoner_vehicles()
    if wanted is not None:
        if wanted not in alive:
            known = ", ".join(alive) or "none"
            raise ApiError(404, f"unknown vehicle {wanted!r}: no reasoner is alive for it (vehicles with a "
                                f"reasoner: {known})")
        return wanted
    if len(alive) == 1:
        return alive[0]
    if not alive:
        raise ApiError(503, "no reasoner is running on any vehicle; start the stack (`aermani up`) first")
    raise ApiError(422, f"several vehicles are available ({', '.join(alive)}); name one in vehicle_id")


@router.post("", status_code=202, response_model=TaskCreated, dependencies=[Authorized],
             summary="Start a task", responses=responses(401, 404, 409, 422, 502, 503, 504))
async def create_task(body: TaskCreate, request: Request, fleet: FleetDep, store: StoreDep,
                      settings: SettingsDep) -> TaskCreated:
    """Send a natural-language command to a vehicle's reasoner. Answers 202 once the reasoner has accepted
    the task; follow it at `links.events`."""
    vehicle = pick_vehicle(fleet, body.vehicle_id)
    # A task the store still shows running may have ended while this gateway was away (its final status was
    # never received). The reasoner, which runs one task at a time, is the authority: it refuses the new task
    # while one runs (409 with its reason); when it accepts, the stored rows were stale and are closed.
    stale = await store.running_tasks(vehicle)
    task_id = new_id("task-")
    req = TaskRequest(command=body.command, task_id=task_id, backend=body.backend, variant=body.variant,
                      t_max_s=body.t_max_s, takeoff=body.takeoff)
    # The row exists before the reasoner hears of the task, so no early step or status can miss it.
    await store.create_task(task_id, vehicle, body.command, body.model_dump(mode="json"))
    try:
        accept = await fleet.bus.query(Keys(vehicle).start_task, req, timeout=settings.start_timeout_s)
    except NoResponder:
        await store.delete_task(task_id)
        raise ApiError(503, f"the reasoner of {vehicle} did not answer; is it running?")
    except QueryTimeout:
        await store.delete_task(task_id)
        raise ApiError(504, f"the reasoner of {vehicle} did not accept the task within "
                            f"{settings.start_timeout_s:.0f} s")
    except RemoteError as exc:
        await store.delete_task(task_id)
        raise ApiError(502, f"the reasoner of {vehicle} refused the request: {exc.payload[:300]}")
    if not accept.accepted:
        await store.delete_task(task_id)
        why = accept.reason or "no reason given"
        if stale:
            raise ApiError(409, f"task {stale[0]['task_id']} is still {stale[0]['state']} on {vehicle} (the reasoner: "
                                f"{why}); wait for it to end or abort it (POST {links(stale[0]['task_id']).abort})")
        raise ApiError(409, f"the reasoner of {vehicle} refused the task: {why}")
    for old in stale:
        await fleet.end_orphan(old, f"its end was not received (the gateway was away); the reasoner of {vehicle} "
                                    f"was idle when task {task_id} started")
    row = await store.get_task(task_id)
    state = TaskPhase(fleet.phase(row)) if row else TaskPhase.PENDING
    return TaskCreated(task_id=task_id, vehicle_id=vehicle, state=state, links=links(task_id))


@router.get("", response_model=TaskPage, summary="List tasks", responses=responses(422))
async def list_tasks(store: StoreDep, settings: SettingsDep, fleet: FleetDep,
                     offset: Annotated[int, Query(ge=0, le=1_000_000, description="Items to skip.")] = 0,
                     limit: Annotated[int, Query(ge=1, le=1000, description="Page size.")] = 20,
                     vehicle_id: Annotated[str | None, Query(pattern=r"^[A-Za-z0-9_-]{1,32}$")] = None,
                     state: Annotated[TaskPhase | None, Query(description="Only tasks in this state.")] = None,
                     ) -> TaskPage:
    """Tasks, newest first, from the gateway's database (survives restarts)."""
    limit = min(limit, settings.page_size_max)
    if state is not None and state.value not in TERMINAL:
        # `aborting` is not stored (the abort path writes nothing): the unfinished tasks, at most a few per
        # vehicle, are filtered by the state the API shows.
        unfinished = [r for r in reversed(await store.running_tasks(vehicle_id)) if fleet.phase(r) == state.value]
        rows, total = unfinished[offset:offset + limit], len(unfinished)
    else:
        rows, total = await store.list_tasks(offset, limit, vehicle_id, state.value if state else None)
    counts = await store.step_counts([r["task_id"] for r in rows])
    return TaskPage(items=[summary(r, counts.get(r["task_id"], 0), fleet) for r in rows], total=total,
                    offset=offset, limit=limit)


def summary(row: dict[str, Any], steps: int, fleet: Fleet) -> TaskSummary:
    return TaskSummary(task_id=row["task_id"], vehicle_id=row["vehicle_id"], command=row["command"],
                       state=TaskPhase(fleet.phase(row)), message=row["message"], created_ns=row["created_ns"],
                       updated_ns=row["updated_ns"], steps=steps)


@router.get("/{task_id}", response_model=TaskDetail, summary="Get a task with every step",
            responses=responses(404, 422))
async def get_task(task_id: TaskId, store: StoreDep, fleet: FleetDep) -> TaskDetail:
    """Status, every reasoning step (DRT and STE), skill results and metrics so far."""
    row = await store.get_task(task_id)
    if row is None:
        raise ApiError(404, f"no task {task_id!r}; GET /api/v1/tasks lists them")
    events = await store.events(task_id, limit=100_000)
    steps: dict[int, StepOut] = {}
    skills: dict[str, dict[str, Any]] = {}
    for ev in events:
        if ev.kind == "step":
            # A step may be published twice (chosen, then with the skill's result): keep the newest.
            steps[int(ev.data.get("step", 0))] = StepOut(event_id=ev.id, step=ev.data)
        elif ev.kind == "skill_status" and ev.data.get("state") != "running":
            skills[ev.data.get("goal_id", str(ev.id))] = ev.data
    ordered = [steps[k] for k in sorted(steps)]
    calls = [c for s in ordered for c in s.step.get("calls", [])]
    latencies = sorted(float(c.get("latency_s", 0.0)) for c in calls)
    invalid = sum(1 for c in calls if not c.get("valid", False))
    by_state: dict[str, int] = {}
    for s in skills.values():
        by_state[s["state"]] = by_state.get(s["state"], 0) + 1
    skill_time = sum(max(0, s.get("ended_ns", 0) - s.get("started_ns", 0)) for s in skills.values()
                     if s.get("ended_ns") and s.get("started_ns")) / 1e9
    status = row["status"] or {}
    start = status.get("started_ns") or row["created_ns"]
    end = status.get("ended_ns") or (row["updated_ns"] if row["state"] in TERMINAL else None)
    metrics = Metrics(steps=len(ordered), model_calls=len(calls), invalid_answers=invalid,
                      iar=(invalid / len(calls)) if calls else None, latency_p50_s=percentile_or_none(latencies, 50),
                      latency_p95_s=percentile_or_none(latencies, 95), skills=by_state, skill_time_s=skill_time,
                      duration_s=((end or _now()) - start) / 1e9,
                      speculative_steps=sum(1 for s in ordered if s.step.get("speculative")))
    return TaskDetail(**summary(row, len(ordered), fleet).model_dump(), request=row["request"], status=row["status"],
                      reasoning_steps=ordered, skill_results=list(skills.values()), metrics=metrics,
                      last_event_id=events[-1].id if events else 0)


def _now() -> int:
    import time

    return time.time_ns()


SSE_DOC: dict[int | str, dict[str, Any]] = {
    200: {"description": "Server-Sent Events. Each event has `id` (increasing per task; send it back "
                          "as Last-Event-ID to resume), `event` (step, skill_status, task_status) and "
                          "`data` (JSON: the ReasoningStep, SkillStatus or TaskStatus). The stream ends "
                          "after the terminal task_status.",
          "content": {"text/event-stream": {"schema": {"type": "string"}, "example":
                      'id: 7\nevent: step\ndata: {"task_id": "task-1a2b3c4d5e6f", "step": 1, ...}\n\n'}}}}


@router.get("/{task_id}/events", dependencies=[Authorized], summary="Follow a task (Server-Sent Events)",
            response_class=EventSourceResponse, responses={**SSE_DOC, **responses(401, 404, 422)})
async def task_events(task_id: TaskId, store: StoreDep, fleet: FleetDep, settings: SettingsDep,
                      last_event_id: Annotated[int | None, Header(alias="Last-Event-ID", ge=0,
                                                                  description="Resume after this event id.")]
                      = None) -> EventSourceResponse:
    """Every reasoning step, skill status and task status of the task as it happens, from the database
    first (so a late or reconnecting client misses nothing), then live."""
    if await store.get_task(task_id) is None:
        raise ApiError(404, f"no task {task_id!r}")

    async def stream():
        last = last_event_id or 0
        while True:
            seen = fleet.version
            events = await store.events(task_id, after=last, limit=500)
            for ev in events:
                last = ev.id
                yield ServerSentEvent(data=json.dumps(ev.data), event=ev.kind, id=str(ev.id))
                if ev.kind == "task_status" and ev.data.get("state") in TERMINAL:
                    return
            if events:
                continue
            row = await store.get_task(task_id)
            if row is None or row["state"] in TERMINAL or fleet.closing.is_set():
                # The terminal status may have landed since the query above (row and event are written in
                # one transaction): send what is left, else we resumed after the end or are shutting down.
                if await store.events(task_id, after=last, limit=1):
                    continue
                return
            await fleet.wait_change(seen, settings.sse_ping_s)

    return EventSourceResponse(stream(), ping=int(max(1, settings.sse_ping_s)),
                               headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})


@router.post("/{task_id}/abort", status_code=202, response_model=AbortOut, dependencies=[Authorized],
             summary="Abort a task", responses=responses(401, 404, 409, 422))
async def abort_task(task_id: TaskId, store: StoreDep, fleet: FleetDep, settings: SettingsDep,
                     body: AbortIn | None = None) -> AbortOut:
    """Tell the task's vehicle to hold and the reasoner to end the task as aborted."""
    row = await store.get_task(task_id)
    if row is None:
        raise ApiError(404, f"no task {task_id!r}")
    held = fleet.ended(task_id)
    ended = row["state"] if row["state"] in TERMINAL else (held.state.value if held else None)
    if ended is not None:
        # Also while its end waits for its last steps to be stored: the task is over, nothing to stop.
        raise ApiError(409, f"task {task_id} has already ended ({ended}); POST /api/v1/abort stops "
                            "every vehicle")
    reason = (body or AbortIn()).reason
    acked = await fleet.abort([row["vehicle_id"]], reason, task_id, settings.abort_ack_timeout_s)
    return AbortOut(vehicles=[row["vehicle_id"]], acknowledged=sorted(acked), messages=abort_summary(acked),
                    services=acked, task_id=task_id)
