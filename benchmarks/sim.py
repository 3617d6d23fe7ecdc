"""Simulator figures: MuJoCo physics real-time factor with 15 objects, render fps at 640x480 (colour + depth, and
with segmentation) on one core, CPU per frame, the same on Zenoh with the stack running, and setpoint jitter.

Usage: .venv/bin/python benchmarks/sim.py [--seconds 10] [--services sim,autopilot_bridge,...] [--scale 1]
       [--no-stack] [--cpu 0] [--json PATH]

Prints figures only (targets from issue 13: physics >= 20x real time with 15 objects, >= 15 fps colour+depth
on one core; issue 3: p99 setpoint interval jitter <= 5 ms); never fails on them. `--cpu 0` pins the physics
and render figures to one core (software OpenGL would otherwise use every core); the stack part runs unpinned,
as deployed. The jitter is
measured by the sim itself from kernel receive timestamps of SET_POSITION_TARGET_LOCAL_NED
(queryable sim/stats), so it is what the vehicle sees, independent of the sim's own scheduling.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from aermani.launcher import Stack, available_services, free_udp_port  # noqa: E402
from benchmarks._figures import add_json_option, pin_all_threads, write_json  # noqa: E402
from services.sim.app import CameraPublisher  # noqa: E402
from services.sim.core import SimCore, Snapshot  # noqa: E402
from services.sim.layout import OBJECTS  # noqa: E402
from services.sim.settings import SimSettings  # noqa: E402
from shared.bus import Bus  # noqa: E402
from shared.keys import Keys  # noqa: E402
from shared.messages import ArmCommand, Scenario, TakeoffCommand  # noqa: E402


def physics(seconds: float, awake: bool = False) -> dict[str, float]:
    """One vehicle and all 14 catalogue objects, the vehicle flying a square at 1.5 m. `awake`: MuJoCo's sleeping
    is switched off, so every object is simulated on every step (the worst case: everything moving); else
    objects at rest sleep as they do in the simulator. The share of object-steps awake is measured, not assumed."""
    import mujoco

    core = SimCore(Scenario(seed=3, distractors=(), extra_objects=tuple(n for n in OBJECTS if n != "red cup"),
                            target_object="red cup"))
    v = core.vehicle
    n_obj = len(core.world.objects)
    world = core.world
    if awake:
        world.model.opt.enableflags &= ~int(mujoco.mjtEnableBit.mjENBL_SLEEP)
    bodies = [world.obj_body[e.name] for e in world.objects]
    awake_samples: list[float] = []
    dt, now = 0.005, 100.0
    v.arm(True)
    for _ in range(int(1.2 / dt)):
        now += dt
        v.setpoint(now, np.array([v.p[0], v.p[1], -1.5]), None, v.yaw, None)
        v.update_modes(now)
        v.step(dt)
    from services.sim.vehicle import MAIN_OFFBOARD

    v.set_mode(MAIN_OFFBOARD, 0, now)
    corners = [np.array([1.0, 1.0, -1.5]), np.array([1.0, -1.0, -1.5]), np.array([-1.0, -1.0, -1.5]),
               np.array([-1.0, 1.0, -1.5])]
    steps = int(seconds / dt)
    t0, c0 = time.perf_counter(), time.process_time()
    for i in range(steps):
        now += dt
        v.setpoint(now, corners[(i * 4) // steps], None, v.yaw, None)
        v.update_modes(now)
        v.step(dt)
        if i % 50 == 0:
            awake_samples.append(sum(bool(world.data.body_awake[b]) for b in bodies) / len(bodies))
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    share = 100 * sum(awake_samples) / max(len(awake_samples), 1)
    what = "sleeping off" if awake else "sleeping on, as simulated"
    print(f"physics ({what}): {n_obj} objects + vehicle (2 ms MuJoCo steps, controller at {1 / dt:.0f} Hz): "
          f"{seconds:.0f} s simulated in {wall:.2f} s wall = {seconds / wall:.0f}x real time (CPU {cpu:.2f} s, one "
          f"thread); objects awake {share:.0f} % of the time")
    pre = "physics_awake" if awake else "physics"
    return {f"{pre}_objects": n_obj, f"{pre}_rtf": seconds / wall, f"{pre}_cpu_rtf": seconds / max(cpu, 1e-9),
            f"{pre}_awake_share_pct": share}


def standalone(frames: int, scale: int) -> dict[str, float]:
    core = SimCore(Scenario(seed=1))
    settings = SimSettings(render_scale=scale, render_process=False)
    cam = CameraPublisher(None, core, settings)  # rendering needs no bus
    with core.lock:
        core.world.set_vehicle(np.array([core.vehicle.true_position_enu()[0], core.vehicle.true_position_enu()[1],
                                         1.5]), core.vehicle.true_yaw_enu())  # airborne view: tables in frame
    cam.render_frame(time.time_ns())
    out: dict[str, float] = {}
    for seg in (False, True):
        cam.segmentation_watched = lambda seg=seg: seg  # type: ignore[method-assign]
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(frames):
            cam.render_frame(time.time_ns())
        dt = (time.perf_counter() - t0) / frames
        cpu = (time.process_time() - c0) / frames
        what = "colour+depth+segmentation" if seg else "colour+depth"
        print(f"render {what} 640x480 (scale {scale}, realistic camera model, JPEG, tf): {dt * 1000:.1f} ms/frame "
              f"= {1 / dt:.1f} fps; CPU {cpu * 1000:.1f} ms/frame (all threads of this process)")
        name = "render_seg" if seg else "render"
        out |= {f"{name}_ms": dt * 1000, f"{name}_fps": 1 / dt, f"{name}_cpu_ms": cpu * 1000}
    snap: Snapshot = core.snapshot()
    r = cam.encoder.renderer
    r.segmentation = False
    t1 = time.perf_counter()
    for _ in range(frames):
        r.render(snap)
    rt = (time.perf_counter() - t1) / frames
    print(f"  of which MuJoCo colour+depth rendering and the noise model: {rt * 1000:.1f} ms")
    return out | {"render_mujoco_ms": rt * 1000}


async def on_stack(services: list[str], seconds: float, scale: int) -> dict[str, float]:
    api = free_udp_port()
    env = {"AERMANI_SIM_API_PORT": str(api), "AERMANI_SIM_API_LOCAL_PORT": str(free_udp_port()),
           "AERMANI_SIM_GCS_PORT": str(free_udp_port()), "AERMANI_SIM_GCS_LOCAL_PORT": str(free_udp_port()),
           "AERMANI_AUTOPILOT_BRIDGE_CONNECTION": f"udpin:127.0.0.1:{api}", "AERMANI_SIM_RENDER_SCALE": str(scale),
           "AERMANI_SIM_SEED": "1"}
    log_dir = Path(tempfile.mkdtemp(prefix="aermani-bench-sim-"))
    stack = Stack(services, env=env, log_dir=log_dir)
    stack.start(wait=True, timeout=120)
    keys = Keys("am1")
    out: dict[str, float] = {}
    try:
        bus = await Bus.open(connect=[stack.endpoint])
        try:
            if "autopilot_bridge" in services:
                await asyncio.sleep(3.0)  # link up, heartbeats exchanged
                for cmd in (ArmCommand(), TakeoffCommand(altitude=1.5)):
                    res = await bus.query(keys.autopilot_command, cmd, timeout=60)
                    print(f"bridge {cmd.kind}: ok={res.ok} {res.message}")
                await asyncio.sleep(3.0)
            sub = bus.subscribe(keys.camera_color, maxsize=5)
            await bus.query(keys.sim_stats, "reset", timeout=10)
            t0 = time.monotonic()
            n = 0
            while time.monotonic() - t0 < seconds:
                try:
                    await sub.recv(1.0)
                    n += 1
                except TimeoutError:
                    pass
            stats = await bus.query(keys.sim_stats, None, timeout=10)
            cam, sp = stats["camera"], stats["setpoints"]
            print(f"on Zenoh with {','.join(services)}: subscriber received {n / seconds:.1f} colour frames/s; sim "
                  f"published {cam['fps']:.1f} fps, mean frame work {cam['render_ms_mean']:.1f} ms")
            out |= {"stack_received_fps": n / seconds, "stack_published_fps": cam["fps"],
                    "stack_frame_work_ms": cam["render_ms_mean"], "stack_services": len(services)}
            if sp.get("n", 0) >= 3:
                print(f"setpoint stream as received by the sim ({sp['n']} samples): interval p50 "
                      f"{sp['interval_ms_p50']:.2f} ms, p99 {sp['interval_ms_p99']:.2f} ms, max "
                      f"{sp['interval_ms_max']:.2f} ms; |interval - median| p99 = jitter {sp['jitter_ms_p99']:.2f} ms")
                out |= {f"setpoint_{k}": sp[k] for k in ("interval_ms_p50", "interval_ms_p99", "interval_ms_max",
                                                          "jitter_ms_p99", "n")}
            else:
                print("no setpoint stream received (no bridge running)")
        finally:
            await bus.close()
    finally:
        stack.stop()
        print(f"(service logs in {log_dir})")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--scale", type=int, default=1)
    ap.add_argument("--services", default="", help="comma-separated; default: every service in this checkout")
    ap.add_argument("--physics-seconds", type=float, default=20.0)
    ap.add_argument("--no-stack", action="store_true", help="standalone figures only")
    ap.add_argument("--cpu", type=int, default=-1,
                    help="pin the physics and render figures to this core (the stack part is not pinned); -1: no pin")
    add_json_option(ap)
    args = ap.parse_args()
    services = [s for s in args.services.split(",") if s] or list(available_services())
    if "sim" not in services:
        services.insert(0, "sim")
    cores = os.sched_getaffinity(0)
    if args.cpu >= 0:
        pin_all_threads(args.cpu)
    figures = physics(args.physics_seconds) | physics(args.physics_seconds, awake=True)
    figures |= standalone(args.frames, args.scale)
    figures["standalone_cores"] = len(os.sched_getaffinity(0))
    os.sched_setaffinity(0, cores)
    if not args.no_stack:
        np.random.seed(0)
        figures |= asyncio.run(on_stack(services, args.seconds, args.scale))
    figures["sim_fps_setting"] = SimSettings().fps
    write_json(args.json, "sim", figures, args, services=services)


if __name__ == "__main__":
    main()
