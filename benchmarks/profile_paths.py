"""Profile of the two hot paths with pyinstrument, in-process: camera frames -> perception, and one reasoning step.

1. Camera frames -> perception: per frame, what a camera publishes (JPEG colour, 16-bit depth, tf) and what the
   perception service does with it (FrameStore ingest and frame build, detections, one localize_object), with
   the `color` segmenter on frames the MuJoCo simulator rendered with the realistic camera model (rendering
   itself is done before profiling: it is the simulator's cost, measured by benchmarks/sim.py).
2. One reasoning step: observation (decode the frame header), prompt compile, image encode, parse/validate of
   the answer and the History update, as in benchmarks/reasoner.py; the rules policy's answers are computed in
   a first, unprofiled pass, so the model stand-in is not in the profile.

Prints the top frames by own time per path (and, with --json, writes them). Run:

    .venv/bin/python benchmarks/profile_paths.py [--frames 20] [--steps 200] [--top 12] [--html DIR]
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks._figures import add_json_option, write_json  # noqa: E402

try:
    from pyinstrument import Profiler
except ImportError:  # pragma: no cover - a dev dependency
    raise SystemExit("pyinstrument is not installed: .venv/bin/pip install -e .[dev]") from None

INTERVAL_S = 0.0005


def top_frames(profiler: Profiler, n: int) -> tuple[float, list[dict[str, Any]]]:
    """(total seconds, the n functions with the most own time, aggregated over every call site)."""
    session = profiler.last_session
    root = session.root_frame() if session else None
    if root is None:
        return 0.0, []
    own: dict[tuple[str, str], float] = defaultdict(float)
    stack = [root]
    while stack:
        fr = stack.pop()
        stack.extend(fr.children)
        if fr.is_synthetic:
            continue  # pyinstrument's "[self]" leaves: already counted in their parent's total_self_time
        where = f"{fr.file_path_short or fr.file_path or '?'}:{fr.line_no}"
        own[(fr.function or "?", where)] += fr.total_self_time
    total = root.time
    rows = sorted(own.items(), key=lambda kv: -kv[1])[:n]
    return total, [{"function": f, "where": w, "self_ms": 1000 * t, "share_pct": 100 * t / total if total else 0.0}
                   for (f, w), t in rows]


def profiled(title: str, iterations: int, html_name: str, html: Path | None, top: int,
             work: Callable[[], object]) -> dict[str, Any]:
    """Run `work` under pyinstrument; its top frames, wall time per iteration (profiler on), HTML if asked."""
    profiler = Profiler(interval=INTERVAL_S)
    t0 = time.perf_counter()
    profiler.start()
    work()
    profiler.stop()
    wall = time.perf_counter() - t0
    if html:
        html.mkdir(parents=True, exist_ok=True)
        profiler.write_html(str(html / html_name))
    total, rows = top_frames(profiler, top)
    return {"title": title, "iterations": iterations, "per_iteration_ms": 1000 * wall / iterations,
            "profiled_s": total, "interval_ms": INTERVAL_S * 1000, "top": rows}


def _frames(n: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, str]]:
    """n rendered views (rgb, depth mm, camera_to_world, an object in view), rendered before profiling."""
    from services.perception.segmenters.color import DEFAULT_OBJECTS
    from services.sim.render import snapshot_at
    from tests.perception.scenes import aim_at, layout, renderer

    known = {c.name for c in DEFAULT_OBJECTS}
    rng = np.random.default_rng(3)
    out: list[tuple[np.ndarray, np.ndarray, np.ndarray, str]] = []
    seed = 0
    while len(out) < n:
        world = layout(seed)
        seed += 1
        for e in world.objects:
            if e.name not in known:
                continue
            x, y, z, yaw = aim_at(world, e.center, 1.1, rng)
            f = renderer().render(snapshot_at(world, np.array([x, y, z]), yaw))
            out.append((f.rgb, f.depth_mm, f.camera_to_world, e.name))
            if len(out) >= n:
                break
    return out


def camera_to_perception(frames: int, top: int, html: Path | None) -> dict[str, Any]:
    from services.perception import query as q
    from services.perception.frames import FrameStore
    from services.perception.pipeline import Perception
    from services.perception.segmenters import make_segmenter
    from services.perception.settings import PerceptionSettings
    from shared.frames import base_to_camera
    from shared.messages import LocalizeRequest
    from shared.sensors import color_message, depth_message, encode_jpeg, transforms_message

    views = _frames(frames)
    s = PerceptionSettings(segmenter="color")
    perception = Perception(make_segmenter(s), s)
    store = FrameStore(need_segmentation=perception.segmenter.needs_segmentation)
    cam_in_base = base_to_camera()

    def one_frame(rgb: np.ndarray, depth_mm: np.ndarray, cam_to_world: np.ndarray, name: str) -> None:
        stamp = time.time_ns()
        # camera side: the payloads a camera (or the simulator) publishes for one frame
        color = color_message(rgb, stamp, jpeg=encode_jpeg(rgb, 85))
        depth = depth_message(depth_mm, stamp)
        tf = transforms_message([("world", "base_link", cam_to_world @ np.linalg.inv(cam_in_base)),
                                 ("base_link", "camera", cam_in_base)], stamp)
        # perception side: ingest, build the frame, detections (published at detections_hz), one query
        store.add_tf(tf)
        store.add_depth(depth)
        store.add_color(color)
        frame = store.latest()
        if frame is None:
            raise SystemExit(f"perception built no frame (missing: {store.missing()})")
        perception.detections(frame)
        perception.localize_object(frame, LocalizeRequest(query=name), q.parse(name))

    def work() -> None:
        for view in views:
            one_frame(*view)

    return profiled("Camera frames -> perception (colour segmenter, 640x480)", len(views),
                    "camera_to_perception.html", html, top, work)


def reasoning_step(steps: int, top: int, html: Path | None) -> dict[str, Any]:
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

    from services.reasoner.backends.openai_backend import image_data_url
    from services.reasoner.backends.rules import RulesPolicy, render_answer
    from services.reasoner.library import default_library
    from services.reasoner.loop import policy_context
    from services.reasoner.parse import parse_answer
    from services.reasoner.prompt import History, HistoryEntry, Observation, PromptCompiler
    from shared.messages import Detection, MemoryObject, Vec3, VehicleState, WorkingMemory
    from shared.sensors import color_message, decode_proto, stamp_to_ns

    rgb = _frames(1)[0][0]
    payload = color_message(rgb, time.time_ns())
    lib = default_library()
    variant = "full"
    compiler = PromptCompiler(variant, lib)
    dets = tuple(Detection(label=n, size=Vec3(x=0.1, y=0.1, z=0.1), centroid=Vec3(x=1.0 + i))
                 for i, n in enumerate(("red cup", "table", "tissue box", "apple", "hammer")))
    memory = WorkingMemory(objects=(MemoryObject(label="red cup", position=Vec3(x=1.0)),), visible=("red cup",))
    state = VehicleState(position=Vec3(z=1.5))
    cmd = "pick up the red cup and place it on the table"

    def run(answers: list[str] | None) -> list[str]:
        history = History(6, 6000)
        policy = RulesPolicy()
        seen: list[str] = []
        for i in range(steps):
            msg = decode_proto(CompressedImage, payload)
            obs = Observation(image_jpeg=bytes(msg.data), image_stamp_ns=stamp_to_ns(msg.timestamp), state=state,
                              detections=dets, memory=memory)
            prompt = compiler.compile(cmd, history, obs)
            image_data_url(prompt.image_jpeg or b"")
            if answers is None:
                ctx = policy_context(cmd, variant, lib, history, obs)
                seen.append(render_answer(ctx, *policy.decide(ctx)))
            answer = seen[i] if answers is None else answers[i]
            parsed = parse_answer(answer, variant, lib)
            history.append(HistoryEntry(i + 1, parsed.ste.skill, parsed.ste.argument, "succeeded", "done", "",
                                        parsed.drt.summary or "", parsed.drt.reasoning or ""))
        return seen

    answers = run(None)  # the model stand-in, unprofiled
    return profiled("One reasoning step (framework only, full variant)", steps, "reasoning_step.html", html, top,
                    lambda: run(answers))


def show(p: dict[str, Any]) -> None:
    print(f"\n{p['title']}: {p['iterations']} iterations, {p['per_iteration_ms']:.2f} ms each (wall, profiler on)")
    print(f"  {'own ms':>9} {'share':>6}  function (where)")
    for r in p["top"]:
        print(f"  {r['self_ms']:9.1f} {r['share_pct']:5.1f}%  {r['function']} ({r['where']})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20, help="camera frames through perception")
    ap.add_argument("--steps", type=int, default=200, help="reasoning steps")
    ap.add_argument("--top", type=int, default=12, help="functions to list per path")
    ap.add_argument("--html", type=Path, default=None, help="also write pyinstrument's HTML reports into DIR")
    add_json_option(ap)
    args = ap.parse_args()
    figures = {"camera_to_perception": camera_to_perception(args.frames, args.top, args.html),
               "reasoning_step": reasoning_step(args.steps, args.top, args.html)}
    for p in figures.values():
        show(p)
    write_json(args.json, "profile_paths", figures, args)


if __name__ == "__main__":
    main()
