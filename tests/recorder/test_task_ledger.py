"""The recorder's account of each task (health details `tasks`): the steps it took and whether the task's end is in
the log, read off the raw samples as they are recorded; what a stack's stopper waits on (shared.tasks.recorded_end)
so the last step is never lost to a stop a few milliseconds too early (ci26: the demo's log lacked its last step)."""

from __future__ import annotations

from services.recorder.service import TaskLedger
from shared.keys import Keys
from shared.messages import TaskState, TaskStatus
from tests.recorder.samples import step_message

K = Keys("am1")


def status(task_id: str, state: TaskState) -> bytes:
    return TaskStatus(task_id=task_id, command="pick up the red cup", state=state).model_dump_json().encode()


def step(task_id: str, n: int) -> bytes:
    return step_message(task_id, n, "forward").model_dump_json().encode()


def test_steps_and_the_end_of_each_task_are_counted_and_the_end_and_late_steps_are_announced() -> None:
    ledger = TaskLedger()
    assert ledger.note(K.task_status, status("t1", TaskState.RUNNING)) is False
    assert [ledger.note(K.reasoning_step, step("t1", n)) for n in (5, 6, 6)] == [False] * 3  # a re-published step once
    assert ledger.tasks == {"t1": {"steps": 6, "ended": None}}
    assert ledger.note(K.task_status, status("t1", TaskState.SUCCEEDED)) is True
    assert ledger.tasks["t1"] == {"steps": 6, "ended": "succeeded"}
    assert ledger.note(K.reasoning_step, step("t1", 7)) is True  # a step after the end: announced too
    assert ledger.tasks["t1"] == {"steps": 7, "ended": "succeeded"}
    # Other keys and payloads that are not what their key says are recorded, never counted.
    assert ledger.note(K.health("sim"), b"{}") is False
    assert ledger.note(K.task_status, b"not json") is False
    assert ledger.note(K.reasoning_step, b'{"task_id": "t2"}') is False
    assert ledger.note(K.task_status, b'{"task_id": "t3", "state": "exploded"}') is False
    for i in range(40):
        ledger.note(K.task_status, status(f"x{i}", TaskState.FAILED))
    assert len(ledger.tasks) == TaskLedger.KEEP and "x39" in ledger.tasks and "t1" not in ledger.tasks
