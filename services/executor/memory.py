"""Working memory: localized objects and placement spots in the world frame, the held object, history."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

from services.executor.failures import SkillFailed
from shared.messages import (
    Detections,
    MemoryObject,
    ObjectEstimate,
    OutcomeCode,
    PlacementEstimate,
    Vec3,
    WorkingMemory,
)

SEEN_MOVE_M = 0.25  # a detection centroid that moved less than this is the same sighting


def _norm(label: str) -> str:
    return " ".join(label.strip().lower().split())


def _find(table: dict[str, MemoryObject], last: str | None, label: str | None) -> MemoryObject | None:
    """The entry of `table` named `label` (exact, then substring of its key or query, newest first), or the
    entry `last` when no label is given."""
    if not label:
        return table.get(last) if last else None
    key = _norm(label)
    if key in table:
        return table[key]
    matches = [e for k, e in table.items() if key in k or k in key or key in _norm(e.query)]
    return max(matches, key=lambda e: e.last_seen_ns) if matches else None


class StaleEstimate(SkillFailed):
    """An estimate computed from a frame taken before the world was last reset: it describes the old layout, so
    memory refuses it and the skill fails as not detected (a fresh look sees the new world)."""

    def __init__(self, what: str, frame_ns: int, reset_ns: int) -> None:
        super().__init__(f"the {what} estimate comes from a frame taken {(reset_ns - frame_ns) / 1e9:.2f} s before "
                         "the world was reset: not stored; localize it again", OutcomeCode.NOT_DETECTED)


class Memory:
    """Mutable store behind the published WorkingMemory. Entries are world-frame, so they survive motion;
    `last_seen_ns` lets skills judge freshness. `on_change` fires after every mutation."""

    def __init__(self, on_change: Callable[[], None] | None = None, max_executed: int = 200) -> None:
        self.objects: dict[str, MemoryObject] = {}
        self.placements: dict[str, MemoryObject] = {}
        self.held: str | None = None
        self.held_size: Vec3 | None = None
        self.held_upright: bool | None = None
        self.visible: tuple[str, ...] = ()
        self.seen: dict[str, MemoryObject] = {}
        self.executed: list[str] = []
        self.task_id = ""
        self.last_object: str | None = None
        self.last_placement: str | None = None
        self.reset_ns = 0  # when the world was last reset: detections of older frames belong to the old world
        self._on_change = on_change
        self._max_executed = max_executed

    def _changed(self) -> None:
        if self._on_change is not None:
            self._on_change()

    # ---- updates

    def begin_task(self, task_id: str) -> None:
        """A new task starts from a clean memory: the world may have changed since the last one (people move
        things; evaluation resets the room), and a stale position would send a grasp to an empty spot. Only
        what the gripper holds carries over, since that is physical."""
        if task_id and task_id != self.task_id:
            self.task_id = task_id
            self.executed.clear()
            self.objects.clear()
            self.placements.clear()
            self.seen.clear()
            self.last_object = self.last_placement = None
            self._changed()

    def world_reset(self, reset_ns: int = 0) -> None:
        """The world was laid out anew (a simulator reset, finished at `reset_ns`): nothing seen or held belongs
        to it any more, and detections of a frame taken before it (in flight, or computed late) are not let back
        in (they leaked the old layout's objects into 3 of 78 evaluation episodes)."""
        self.reset_ns = max(self.reset_ns, reset_ns)
        self.task_id = ""
        self.executed.clear()
        self.objects.clear()
        self.placements.clear()
        self.seen.clear()
        self.visible = ()
        self.held, self.held_size, self.held_upright = None, None, None
        self.last_object = self.last_placement = None
        self._changed()

    def restore(self, wm: WorkingMemory, task_id: str, shift_ns: int, now_ns: int) -> None:
        """A recorded memory put back as `task_id`'s (a flight fork): every sighting is moved by `shift_ns`, so
        it is as old now as it was when recorded, and detections of frames from before `now_ns` (the world before
        the restore) are not let in. The last object and placement are the newest of each table."""
        def moved(o: MemoryObject) -> MemoryObject:
            return o.model_copy(update={"last_seen_ns": o.last_seen_ns + shift_ns}) if o.last_seen_ns else o

        self.task_id = task_id
        self.reset_ns = max(self.reset_ns, now_ns)
        self.objects = {_norm(o.label): moved(o) for o in wm.objects}
        self.placements = {_norm(o.label): moved(o) for o in wm.placements}
        self.seen = {_norm(o.label): moved(o) for o in wm.seen}
        self.visible = tuple(wm.visible)
        self.executed = list(wm.executed)[-self._max_executed:]
        held = self.objects.get(_norm(wm.held_object)) if wm.held_object else None
        self.held, self.held_size = wm.held_object, held.size if held is not None else None
        self.held_upright = None  # not in the published memory: unknown after a restore

        def newest(table: dict[str, MemoryObject]) -> str | None:
            return max(table, key=lambda k: table[k].last_seen_ns) if table else None

        self.last_object, self.last_placement = newest(self.objects), newest(self.placements)
        self._changed()

    def record_executed(self, entry: str) -> None:
        self.executed.append(entry)
        del self.executed[:-self._max_executed]
        self._changed()

    def _check_fresh(self, frame_ns: int, what: str) -> None:
        """Raises StaleEstimate for an estimate of a frame from before the last reset (a frame of the reset
        instant itself is the old world's too, as in `set_visible`); an unstamped estimate is taken as new."""
        if frame_ns and frame_ns <= self.reset_ns:
            raise StaleEstimate(what, frame_ns, self.reset_ns)

    def store_object(self, est: ObjectEstimate, query: str) -> MemoryObject:
        """Stores a found object's estimate; raises StaleEstimate (nothing stored) for a pre-reset frame's."""
        assert est.found and est.pose is not None
        self._check_fresh(est.frame_stamp_ns, est.label or query)
        label = _norm(est.label or query)
        size = est.size
        top = est.top_z if est.top_z is not None else (
            est.pose.position.z + size.z / 2 if size is not None else None)
        mo = MemoryObject(label=label, query=query, position=est.pose.position, yaw=est.pose.yaw, size=size,
                          top_z=top, last_seen_ns=est.frame_stamp_ns or time.time_ns(), confidence=est.confidence)
        self.objects[label] = mo
        self.last_object = label
        self._changed()
        return mo

    def store_placement(self, est: PlacementEstimate, query: str) -> MemoryObject:
        """Stores a placement spot; raises StaleEstimate (nothing stored) for a pre-reset frame's."""
        assert est.found and est.pose is not None
        self._check_fresh(est.frame_stamp_ns, f"placement spot on the {est.label or query}")
        label = _norm(est.label or query)
        mo = MemoryObject(label=label, query=query, position=est.pose.position, yaw=est.pose.yaw,
                          top_z=est.surface_z, last_seen_ns=est.frame_stamp_ns or time.time_ns(),
                          confidence=est.confidence)
        self.placements[label] = mo
        self.last_placement = label
        self._changed()
        return mo

    def forget_object(self, label: str) -> None:
        if self.objects.pop(_norm(label), None) is not None:
            if self.last_object == _norm(label):
                self.last_object = None
            self._changed()

    def set_held(self, label: str | None, size: Vec3 | None = None, upright: bool | None = None) -> None:
        """What the gripper holds, its size as found and whether it stood upright when grasped (None: unknown)."""
        self.held = label
        self.held_size = size if label else None
        self.held_upright = upright if label else None
        self._changed()

    def set_visible(self, det: Detections) -> None:
        if det.frame_stamp_ns and det.frame_stamp_ns <= self.reset_ns:
            return  # the old world's frame
        labels = tuple(dict.fromkeys(d.label for d in det.items))
        changed = labels != self.visible
        self.visible = labels
        stamp = det.frame_stamp_ns or time.time_ns()
        for d in det.items:
            if d.centroid is None:
                continue
            label = _norm(d.label)
            old = self.seen.get(label)
            # Publish only when something new appears or moves noticeably: detections arrive at frame rate.
            if old is None or horizontal_distance(old.position, d.centroid) > SEEN_MOVE_M:
                changed = True
            self.seen[label] = MemoryObject(label=label, position=d.centroid, size=d.size, last_seen_ns=stamp,
                                            confidence=d.confidence)
        if changed:
            self._changed()

    # ---- lookups

    def find_object(self, label: str | None) -> MemoryObject | None:
        """The object named `label` (exact, then substring match), or the last localized one."""
        return _find(self.objects, self.last_object, label)

    def find_placement(self, label: str | None) -> MemoryObject | None:
        """The placement spot on the surface named `label` (exact, then substring match), or the last one."""
        return _find(self.placements, self.last_placement, label)

    def snapshot(self) -> WorkingMemory:
        return WorkingMemory(objects=tuple(self.objects.values()), placements=tuple(self.placements.values()),
                             held_object=self.held, visible=self.visible, executed=tuple(self.executed),
                             seen=tuple(self.seen.values()))


def age_s(obj: MemoryObject, now_ns: int | None = None) -> float:
    return ((now_ns or time.time_ns()) - obj.last_seen_ns) / 1e9


def horizontal_distance(a: Vec3, b: Vec3) -> float:
    return math.hypot(a.x - b.x, a.y - b.y)
