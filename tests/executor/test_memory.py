"""Working memory across a world reset (issue 26): detections of a frame taken before the reset, arriving or
computed after it, must not bring the old layout's objects back (they leaked into 3 of 78 episodes)."""

from __future__ import annotations

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
