"""Rendering in a child process: MuJoCo's OpenGL rendering (software GL on most machines here) and the camera
model take tens of milliseconds per frame and own an OpenGL context; in the simulator's process they would
compete with the MAVLink/physics thread for the GIL and the core."""

from __future__ import annotations

import contextlib
import logging
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path

import cv2

from services.sim.core import Snapshot
from shared.frames import DEFAULT_INTRINSICS
from shared.sensors import Intrinsics, color_message, depth_message, encode_jpeg, raw16_message

log = logging.getLogger("aermani.sim.render")


@dataclass
class Encoded:
    """A rendered frame encoded as foxglove messages, with the time spent rendering and encoding."""

    color: bytes  # serialized foxglove.CompressedImage
    depth: bytes  # serialized foxglove.CompressedImage, 16-bit PNG (mm)
    segmentation: bytes | None  # serialized foxglove.RawImage 16UC1 (instance ids); None when not asked for
    render_s: float  # time spent in the renderer and encoders


def coarse_intrinsics(scale: int, full: Intrinsics = DEFAULT_INTRINSICS) -> Intrinsics:
    """Pinhole whose pixel (i, j) looks through the centre of the full-resolution block of scale x scale pixels
    starting at (scale*i, scale*j); nearest upsampling then keeps the published calibration right to half a
    block."""
    if scale == 1:
        return full
    return Intrinsics(full.width // scale, full.height // scale, full.fx / scale, full.fy / scale,
                      (full.cx - (scale - 1) / 2) / scale, (full.cy - (scale - 1) / 2) / scale)


class FrameEncoder:
    """Render + upsample + encode one frame (runs in the worker process, or in-process for tests)."""

    def __init__(self, scale: int = 1, jpeg_quality: int = 85, realism: str = "realistic", seed: int = 0,
                 unit: int = 0) -> None:
        from services.sim.render import Renderer

        self.scale, self.quality = scale, jpeg_quality
        self.renderer = Renderer(coarse_intrinsics(scale), realism=realism, seed=seed, unit=unit)

    def __call__(self, snap: Snapshot, stamp_ns: int, segmentation: bool = True) -> Encoded:
        t0 = time.perf_counter()
        self.renderer.segmentation = segmentation
        frame = self.renderer.render(snap)
        rgb, depth, inst = frame.rgb, frame.depth_mm, frame.instance
        if self.scale > 1:
            full = (DEFAULT_INTRINSICS.width, DEFAULT_INTRINSICS.height)
            rgb = cv2.resize(rgb, full, interpolation=cv2.INTER_LINEAR)
            depth = cv2.resize(depth, full, interpolation=cv2.INTER_NEAREST)
            inst = cv2.resize(inst, full, interpolation=cv2.INTER_NEAREST)
        color = color_message(rgb, stamp_ns, jpeg=encode_jpeg(rgb, self.quality))
        return Encoded(color, depth_message(depth, stamp_ns), raw16_message(inst, stamp_ns) if segmentation else None,
                       time.perf_counter() - t0)


def _worker(conn, scale: int, quality: int, realism: str, seed: int = 0, unit: int = 0) -> None:  # in the child
    encoder = FrameEncoder(scale, quality, realism, seed, unit)
    conn.send("ready")
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            return  # parent gone
        if job is None:
            return
        snap, stamp, seg = job
        try:
            conn.send(encoder(snap, stamp, seg))
        except Exception as exc:  # report, keep serving
            conn.send(exc)


class RenderWorker:
    """One child process (`python -m services.sim.render_worker`) that renders frames on request over a
    socketpair; call `render` from a worker thread. A plain subprocess rather than multiprocessing's spawn,
    which would re-import whatever script happens to be the parent's __main__."""

    def __init__(self, scale: int = 1, jpeg_quality: int = 85, realism: str = "realistic", seed: int = 0,
                 start_timeout: float = 120.0, unit: int = 0) -> None:
        parent, child = socket.socketpair()
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "services.sim.render_worker", str(child.fileno()), str(scale), str(jpeg_quality),
             realism, str(seed), str(unit)],
            pass_fds=(child.fileno(),), cwd=str(Path(__file__).resolve().parents[2]))
        child.close()
        self._conn = Connection(parent.detach())
        self._lock = threading.Lock()
        try:
            ready = self._conn.poll(start_timeout) and self._conn.recv() == "ready"
        except (EOFError, OSError):
            ready = False
        if not ready:
            self.close()
            raise RuntimeError(f"the render worker process did not start (exit code {self._proc.poll()})")

    def render(self, snap: Snapshot, stamp_ns: int, segmentation: bool = True) -> Encoded:
        with self._lock:
            self._conn.send((snap, stamp_ns, segmentation))
            out = self._conn.recv()
        if isinstance(out, Exception):
            raise out
        return out

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._conn.send(None)
        try:
            self._proc.wait(5.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(5.0)
        self._conn.close()


if __name__ == "__main__":
    # Import by name so pickled frames reference services.sim.render_worker.Encoded, not __main__.Encoded.
    from services.sim.render_worker import _worker as worker

    worker(Connection(int(sys.argv[1])), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], int(sys.argv[5]),
           int(sys.argv[6]))
