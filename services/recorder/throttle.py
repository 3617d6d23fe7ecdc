"""Which camera frames the log keeps: at most `frame_max_hz` colour+depth pairs per vehicle, and every frame a
reasoning step was decided on.

Frames are most of a log's bytes (a realistic 640x480 depth PNG is about 240 kB, its JPEG about 32 kB), and a
one-hour log must fit in 2 GB (docs/performance.md). A pair is kept or skipped together (see FrameThrottle).
Skipped frames wait in a ring per key, so when a `reasoner/step` names
the frame its model saw (`image_stamp_ns`), that colour frame and its depth are written after all: the log
always shows what each decision was made on. Zenoh orders nothing across keys, so a step can also arrive before
its frame (a `done` is published within milliseconds of its decision; under load its frame came later): the
stamps a step named and the ring did not hold are remembered, and such a frame is written when it comes.
Everything that is not a colour or depth frame passes.
"""

from __future__ import annotations

import collections
import json
from dataclasses import dataclass, field

from shared.errors import DecodeError
from shared.sensors import CompressedImage, decode_proto, stamp_to_ns

FRAME_SUFFIXES = ("/camera/color", "/camera/depth")
STEP_SUFFIX = "/reasoner/step"
RING = 64  # written stamps remembered per stream, for the pair's other half
# Skipped frames held per key, in bytes. A step is published when its skill has ended, up to minutes after
# its frame: 64 MB holds about 2 minutes of colour at 15 fps; depth, 8 times larger a frame, only seconds
# (the model saw the colour frame; the decision's depth is kept when the step comes soon enough).
RING_BYTES = {"/camera/color": 64 << 20, "/camera/depth": 16 << 20}
WANTED = 64  # stamps named by steps whose frames had not come yet, remembered per vehicle


Sample = tuple[str, bytes, str, int]  # key, payload, encoding, receive_ns


@dataclass
class _Vehicle:
    last_kept: dict[str, int] = field(default_factory=dict)  # suffix -> stamp of the last frame written
    kept: dict[str, collections.deque[int]] = field(default_factory=dict)  # suffix -> recent stamps written
    skipped: dict[str, collections.OrderedDict[int, Sample]] = field(default_factory=dict)
    held: collections.Counter[str] = field(default_factory=collections.Counter)  # bytes in each ring
    wanted: collections.OrderedDict[int, set[str]] = field(default_factory=collections.OrderedDict)
    """Stamps a step named before their frames came -> the streams still to write."""


class FrameThrottle:
    """`admit(sample)` -> the samples to write now (none, the sample, its pair's skipped half, or a step's
    frames and the step).

    Each stream (colour, depth) is written when its last written frame is a period old, or when its pair's other
    half was written. Written, a frame also pulls its skipped other half out of the ring. So full-rate streams
    give whole pairs at the limit, and a depth stream the link already thinned (the drone router sends depth at
    1 Hz, shared/routers/drone.json5) still finds its colour frame."""

    def __init__(self, max_hz: float) -> None:
        self.period_ns = int(1e9 / max_hz) if max_hz > 0 else 0
        self.vehicles: dict[str, _Vehicle] = {}
        self.skipped = 0

    def admit(self, key: str, payload: bytes, encoding: str, receive_ns: int) -> list[Sample]:
        sample = (key, payload, encoding, receive_ns)
        if not self.period_ns:
            return [sample]
        parts = key.rsplit("/", 2)
        suffix = "/" + "/".join(parts[1:])
        if suffix in FRAME_SUFFIXES:
            return self._frame(parts[0], suffix, sample)
        if key.endswith(STEP_SUFFIX):
            return [*self._step_frames(key[: -len(STEP_SUFFIX)], payload), sample]
        return [sample]

    def _frame(self, prefix: str, suffix: str, sample: Sample) -> list[Sample]:
        try:
            stamp = stamp_to_ns(decode_proto(CompressedImage, sample[1]).timestamp)
        except DecodeError:
            return [sample]  # the recorder keeps what it cannot read; readers skip it
        v = self.vehicles.setdefault(prefix, _Vehicle())
        other = FRAME_SUFFIXES[1 - FRAME_SUFFIXES.index(suffix)]
        last = v.last_kept.get(suffix)
        # 5 % slack: a 15 fps camera's 15th frame is a few ns short of the second, and stamps jitter; a clock
        # that steps back by more than a period restarts the count.
        due = last is None or stamp - last >= self.period_ns * 0.95 or stamp < last - self.period_ns
        if self._wanted(v, suffix, stamp):
            due = True
        if not (due or stamp in v.kept.get(other, ())):
            self._hold(v, suffix, stamp, sample)
            return []
        out = [sample]
        self._written(v, suffix, stamp)
        ring = v.skipped.get(other)
        partner = ring.pop(stamp, None) if ring is not None else None
        if partner is not None:
            v.held[other] -= len(partner[1])
            self.skipped -= 1
            self._written(v, other, stamp)
            out.append(partner)
        return out

    @staticmethod
    def _wanted(v: _Vehicle, suffix: str, stamp: int) -> bool:
        """Whether a step already named this frame (it came after the step); it is then no longer wanted."""
        streams = v.wanted.get(stamp)
        if streams is None or suffix not in streams:
            return False
        streams.discard(suffix)
        if not streams:
            del v.wanted[stamp]
        return True

    def _written(self, v: _Vehicle, suffix: str, stamp: int) -> None:
        last = v.last_kept.get(suffix)
        if last is None or stamp > last or stamp < last - self.period_ns:  # a clock stepped back: restart
            v.last_kept[suffix] = stamp
        v.kept.setdefault(suffix, collections.deque(maxlen=RING)).append(stamp)

    def _hold(self, v: _Vehicle, suffix: str, stamp: int, sample: Sample) -> None:
        ring = v.skipped.setdefault(suffix, collections.OrderedDict())
        old = ring.pop(stamp, None)
        v.held[suffix] += len(sample[1]) - (len(old[1]) if old else 0)
        self.skipped += old is None
        ring[stamp] = sample
        while v.held[suffix] > RING_BYTES[suffix] and ring:
            v.held[suffix] -= len(ring.popitem(last=False)[1][1])

    def _step_frames(self, prefix: str, payload: bytes) -> list[Sample]:
        try:
            stamp = int(json.loads(payload).get("image_stamp_ns") or 0)
        except (ValueError, AttributeError, TypeError):
            return []
        if not stamp:
            return []
        v = self.vehicles.setdefault(prefix, _Vehicle())
        out = []
        missing = set(FRAME_SUFFIXES)
        for suffix, ring in v.skipped.items():
            if (s := ring.pop(stamp, None)) is not None:
                v.held[suffix] -= len(s[1])
                out.append(s)
                missing.discard(suffix)
        missing -= {suffix for suffix in FRAME_SUFFIXES if stamp in v.kept.get(suffix, ())}
        if missing:  # not here yet: written when it comes
            v.wanted[stamp] = missing
            while len(v.wanted) > WANTED:
                v.wanted.popitem(last=False)
        self.skipped -= len(out)
        return out
