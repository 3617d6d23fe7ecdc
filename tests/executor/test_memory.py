"""Working memory across a world reset (issue 26): detections of a frame taken before the reset, arriving or
computed after it, must not bring the old layout's objects back (they leaked into 3 of 78 episodes)."""

from __future__ import annotations

import pytest

from services.executor.memory import Memory
from shared.messages import Detection, Detections, Vec3


def _dets(frame_ns: int, *labels: str) -> Detections:
    return Detections(frame_stamp_ns=frame_ns, items=tuple(
        Detection(label=lb, category="object", centroid=Vec3(x=1.0 + i), size=Vec3(x=0.1, y=0.1, z=0.1))
        for i, lb in enumerate(labels)))


def test_detections_of_frames_before_a_reset_are_not_let_back_in() -> None:
    mem = Memory()
    mem.set_visible(_dets(1_000, "red cup", "banana"))
    assert {o.label for o in mem.snapshot().seen} == {"red cup", "banana"}
    mem.world_reset(reset_ns=2_000)
    snap = mem.snapshot()
    assert snap.seen == () and snap.visible == () and snap.objects == ()
    mem.set_visible(_dets(1_500, "red cup", "banana"))  # the old world's frame, late
    mem.set_visible(_dets(2_000, "banana"))  # the frame of the reset instant itself is the old world's too
    snap = mem.snapshot()
    assert snap.seen == () and snap.visible == (), snap
    mem.set_visible(_dets(2_001, "apple"))  # the new world
    snap = mem.snapshot()
    assert [o.label for o in snap.seen] == ["apple"] and snap.visible == ("apple",)
    # an older reset notice arriving late never moves the boundary back
    mem.world_reset(reset_ns=1_000)
    mem.set_visible(_dets(1_800, "red cup"))
    assert mem.snapshot().seen == ()


def test_a_restored_memory_keeps_each_sighting_s_age_and_is_the_task_s() -> None:
    """A flight fork puts the recorded memory back: each entry as old as it was when recorded, the held object
    with its size, the newest entries as the last ones, and the fork's first skill does not clear it."""
    from shared.messages import MemoryObject, WorkingMemory

    def obj(label: str, seen_ns: int) -> MemoryObject:
        return MemoryObject(label=label, position=Vec3(x=1.0), size=Vec3(x=0.08, y=0.08, z=0.11),
                            last_seen_ns=seen_ns)

    recorded = WorkingMemory(objects=(obj("red cup", 9_000), obj("banana", 7_000)), placements=(obj("table", 9_500),),
                             seen=(obj("red cup", 9_900),), held_object="red cup", visible=("table",),
                             executed=("obj_localization(red cup)", "grasp(red cup)"))
    mem = Memory()
    mem.restore(recorded, "task-fork", shift_ns=1_000_000 - 10_000, now_ns=1_000_000)
    mem.begin_task("task-fork")  # the fork's first skill
    snap = mem.snapshot()
    assert {o.label: o.last_seen_ns for o in snap.objects} == {"red cup": 999_000, "banana": 997_000}
    assert snap.placements[0].last_seen_ns == 999_500 and snap.held_object == "red cup"
    assert mem.held_size == Vec3(x=0.08, y=0.08, z=0.11) and snap.executed == recorded.executed
    assert mem.find_object(None).label == "red cup" and mem.find_placement(None).label == "table"
    mem.set_visible(_dets(999_999, "apple"))  # a frame from before the restore: the world before it
    assert "apple" not in {o.label for o in mem.snapshot().seen}
    mem.begin_task("task-next")  # another task starts clean, as ever; only the held object carries over
    assert mem.snapshot().objects == () and mem.snapshot().held_object == "red cup"


def test_estimates_of_frames_before_a_reset_are_not_stored() -> None:
    """The part that leaked besides `seen`: a localization answered from a frame taken before the reset (perception
    still holding the old world's frame) must not put the old layout's object or spot into memory, and the skill
    fails as not detected, so the policy looks again."""
    from services.executor.context import SkillFailed
    from services.executor.memory import StaleEstimate
    from shared.messages import ObjectEstimate, OutcomeCode, PlacementEstimate, Pose

    def obj(frame_ns: int, label: str = "red cup") -> ObjectEstimate:
        return ObjectEstimate(query=label, found=True, label=label, pose=Pose(position=Vec3(x=1.0, y=0.5, z=0.8)),
                              size=Vec3(x=0.08, y=0.08, z=0.11), frame_stamp_ns=frame_ns)

    def spot(frame_ns: int) -> PlacementEstimate:
        return PlacementEstimate(query="table", found=True, label="table", pose=Pose(position=Vec3(x=2.0, z=0.76)),
                                 surface_z=0.75, frame_stamp_ns=frame_ns)

    mem = Memory()
    mem.store_object(obj(1_000), "red cup")
    mem.store_placement(spot(1_000), "table")
    mem.world_reset(reset_ns=2_000)
    for stamp in (1_500, 2_000):  # the old world's frames, the reset instant's included
        with pytest.raises(StaleEstimate) as err:
            mem.store_object(obj(stamp, "banana"), "banana")
        assert isinstance(err.value, SkillFailed) and err.value.code is OutcomeCode.NOT_DETECTED
        assert "before the world was reset" in str(err.value)
        with pytest.raises(StaleEstimate):
            mem.store_placement(spot(stamp), "table")
    snap = mem.snapshot()
    assert snap.objects == () and snap.placements == ()
    assert mem.find_object("banana") is None and mem.find_placement(None) is None
    # frames of the new world are stored as before, and an unstamped estimate is taken as new
    assert mem.store_object(obj(2_001, "apple"), "apple").label == "apple"
    assert mem.store_placement(spot(0), "table").label == "table"
    assert [o.label for o in mem.snapshot().objects] == ["apple"] and mem.find_placement("table") is not None
