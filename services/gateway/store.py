"""SQLite persistence of tasks and their events (steps, skill statuses, task statuses) for the gateway."""

from __future__ import annotations

import asyncio
import contextlib
import json
import sqlite3
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

NONTERMINAL = ("pending", "running")

SCHEMA = """
CREATE TABLE IF NOT EXISTS tasks (
    task_id TEXT PRIMARY KEY,
    vehicle_id TEXT NOT NULL,
    command TEXT NOT NULL,
    state TEXT NOT NULL,
    message TEXT NOT NULL DEFAULT '',
    created_ns INTEGER NOT NULL,
    updated_ns INTEGER NOT NULL,
    request TEXT NOT NULL DEFAULT '{}',
    status TEXT
);
CREATE INDEX IF NOT EXISTS tasks_created ON tasks(created_ns);
CREATE INDEX IF NOT EXISTS tasks_vehicle_state ON tasks(vehicle_id, state);
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    task_id TEXT NOT NULL,
    kind TEXT NOT NULL,
    stamp_ns INTEGER NOT NULL,
    data TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS events_task ON events(task_id, id);
"""


def _inserted_id(cur: sqlite3.Cursor) -> int:
    """The id of the row an INSERT just added (the sqlite3 stubs type `lastrowid` as optional)."""
    assert cur.lastrowid is not None
    return cur.lastrowid


@dataclass
class Event:
    """One stored task event (step, skill status or task status) with its row id and stamp."""

    id: int
    task_id: str
    kind: str
    stamp_ns: int
    data: dict[str, Any]


def _row_task(row: sqlite3.Row) -> dict[str, Any]:
    d = dict(row)
    d["request"] = json.loads(d["request"] or "{}")
    d["status"] = json.loads(d["status"]) if d["status"] else None
    return d


class Store:
    """One connection used from one worker thread, so writes are serialized and never block the loop.
    AUTOINCREMENT keeps event ids strictly increasing (never reused), which the SSE resume relies on.

    Durability: WAL journal. `synchronous=NORMAL` (the default) makes every committed write survive the
    gateway being killed at any instant; only an OS crash or power loss can lose the last commits.
    `synchronous=FULL` (setting `db_synchronous`) also survives those, at one fsync per write."""

    def __init__(self, path: str, synchronous: str = "NORMAL") -> None:
        if synchronous.upper() not in ("NORMAL", "FULL"):
            raise ValueError(f"db_synchronous must be NORMAL or FULL, not {synchronous!r}")
        self.path = path
        self.synchronous = synchronous.upper()
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="gateway-db")
        self._db: sqlite3.Connection | None = None

    async def _run(self, fn: Any, *args: Any) -> Any:
        return await asyncio.get_running_loop().run_in_executor(self._pool, fn, *args)

    async def open(self) -> None:
        await self._run(self._open)

    def _open(self) -> None:
        if self.path != ":memory:":
            Path(self.path).parent.mkdir(parents=True, exist_ok=True)
        db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        db.row_factory = sqlite3.Row
        db.execute("PRAGMA journal_mode=WAL")
        db.execute(f"PRAGMA synchronous={self.synchronous}")
        db.executescript(SCHEMA)
        self._db = db

    async def close(self) -> None:
        def close() -> None:
            if self._db is not None:
                self._db.close()
                self._db = None

        await self._run(close)
        self._pool.shutdown(wait=True)

    @property
    def db(self) -> sqlite3.Connection:
        if self._db is None:
            raise RuntimeError("store is not open")
        return self._db

    @contextlib.contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        """One real transaction. The connection is in autocommit mode (isolation_level=None), where
        `with connection:` opens none and every statement commits on its own; BEGIN IMMEDIATE takes the
        write lock up front so the statements inside commit together or not at all."""
        db = self.db
        db.execute("BEGIN IMMEDIATE")
        try:
            yield db
        except BaseException:
            db.execute("ROLLBACK")
            raise
        db.execute("COMMIT")

    # ---- tasks

    async def create_task(self, task_id: str, vehicle_id: str, command: str, request: dict[str, Any]) -> None:
        now = time.time_ns()
        await self._run(lambda: self.db.execute(
            "INSERT INTO tasks(task_id, vehicle_id, command, state, created_ns, updated_ns, request) "
            "VALUES (?, ?, ?, 'pending', ?, ?, ?)", (task_id, vehicle_id, command, now, now, json.dumps(request))))

    async def delete_task(self, task_id: str) -> None:
        def delete() -> None:
            with self._tx():
                self.db.execute("DELETE FROM events WHERE task_id = ?", (task_id,))
                self.db.execute("DELETE FROM tasks WHERE task_id = ?", (task_id,))

        await self._run(delete)

    async def get_task(self, task_id: str) -> dict[str, Any] | None:
        def get() -> dict[str, Any] | None:
            row = self.db.execute("SELECT * FROM tasks WHERE task_id = ?", (task_id,)).fetchone()
            return _row_task(row) if row else None

        return await self._run(get)

    async def list_tasks(self, offset: int, limit: int, vehicle_id: str | None = None,
                         state: str | None = None) -> tuple[list[dict[str, Any]], int]:
        def query() -> tuple[list[dict[str, Any]], int]:
            where, args = [], []
            if vehicle_id:
                where.append("vehicle_id = ?")
                args.append(vehicle_id)
            if state:
                where.append("state = ?")
                args.append(state)
            cond = f"WHERE {' AND '.join(where)}" if where else ""
            total = self.db.execute(f"SELECT COUNT(*) FROM tasks {cond}", args).fetchone()[0]
            rows = self.db.execute(f"SELECT * FROM tasks {cond} ORDER BY created_ns DESC, task_id LIMIT ? OFFSET ?",
                                   [*args, limit, offset]).fetchall()
            return [_row_task(r) for r in rows], total

        return await self._run(query)

    async def running_tasks(self, vehicle_id: str | None = None) -> list[dict[str, Any]]:
        def query() -> list[dict[str, Any]]:
            sql = "SELECT * FROM tasks WHERE state IN ('pending', 'running')"
            args: list[Any] = []
            if vehicle_id:
                sql += " AND vehicle_id = ?"
                args.append(vehicle_id)
            return [_row_task(r) for r in self.db.execute(sql + " ORDER BY created_ns", args).fetchall()]

        return await self._run(query)

    async def record_status(self, vehicle_id: str, status: dict[str, Any]) -> tuple[int, bool]:
        """Upsert the task from a TaskStatus and append the event. Returns (event id, state changed)."""

        def write() -> tuple[int, bool]:
            now = time.time_ns()
            with self._tx():
                row = self.db.execute("SELECT state FROM tasks WHERE task_id = ?", (status["task_id"],)).fetchone()
                if row is None:
                    self.db.execute(
                        "INSERT INTO tasks(task_id, vehicle_id, command, state, message, created_ns, updated_ns, "
                        "status) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                        (status["task_id"], vehicle_id, status.get("command", ""), status["state"],
                         status.get("message", ""), status.get("started_ns") or now, now, json.dumps(status)))
                    changed = True
                elif row["state"] not in NONTERMINAL:
                    # A terminal state is final: a late or duplicated status must not revive the task.
                    changed = False
                else:
                    self.db.execute("UPDATE tasks SET state = ?, message = ?, updated_ns = ?, status = ? "
                                    "WHERE task_id = ?", (status["state"], status.get("message", ""), now,
                                                          json.dumps(status), status["task_id"]))
                    changed = row["state"] != status["state"]
                cur = self.db.execute("INSERT INTO events(task_id, kind, stamp_ns, data) VALUES (?, ?, ?, ?)",
                                      (status["task_id"], "task_status", status.get("stamp_ns") or now,
                                       json.dumps(status)))
                return _inserted_id(cur), changed

        return await self._run(write)

    # ---- events

    async def add_event(self, task_id: str, kind: str, stamp_ns: int, data: dict[str, Any]) -> int:
        def write() -> int:
            with self._tx():
                cur = self.db.execute("INSERT INTO events(task_id, kind, stamp_ns, data) VALUES (?, ?, ?, ?)",
                                      (task_id, kind, stamp_ns, json.dumps(data)))
                self.db.execute("UPDATE tasks SET updated_ns = ? WHERE task_id = ?", (time.time_ns(), task_id))
                return _inserted_id(cur)

        return await self._run(write)

    async def events(self, task_id: str, after: int = 0, kinds: tuple[str, ...] | None = None,
                     limit: int = 1000) -> list[Event]:
        def query() -> list[Event]:
            sql = "SELECT * FROM events WHERE task_id = ? AND id > ?"
            args: list[Any] = [task_id, after]
            if kinds:
                sql += f" AND kind IN ({','.join('?' * len(kinds))})"
                args.extend(kinds)
            rows = self.db.execute(sql + " ORDER BY id LIMIT ?", [*args, limit]).fetchall()
            return [Event(r["id"], r["task_id"], r["kind"], r["stamp_ns"], json.loads(r["data"])) for r in rows]

        return await self._run(query)

    async def step_counts(self, task_ids: list[str]) -> dict[str, int]:
        if not task_ids:
            return {}

        def query() -> dict[str, int]:
            rows = self.db.execute(
                "SELECT task_id, COUNT(DISTINCT json_extract(data, '$.step')) FROM events WHERE kind = 'step' "
                f"AND task_id IN ({','.join('?' * len(task_ids))}) GROUP BY task_id", task_ids).fetchall()
            return {r[0]: r[1] for r in rows}

        return await self._run(query)

    async def ping(self) -> bool:
        try:
            await self._run(lambda: self.db.execute("SELECT 1").fetchone())
            return True
        except Exception:
            return False
