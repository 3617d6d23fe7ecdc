"""The perception service as a real process over real Zenoh: against the real sim (and autopilot bridge to
fly the camera), with bad requests, without frames, with stale frames, and with a segmenter that cannot start.

Ground truth comes from `sim/judge`; whether a thing is in view is decided by rendering the same seeded
layout locally from the vehicle pose the judge reports (tests only)."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from aermani.launcher import free_port
from services.sim.scenarios import generate
from shared.bus import Bus, Latest
from shared.errors import NoResponder
from shared.keys import Keys
from shared.messages import (
    ArmCommand,
    GotoCommand,
    JudgeRequest,
    LocalizeRequest,
    ObjectEstimate,
    PlacementEstimate,
    Scenario,
    SimLabel,
    SimLabels,
    TakeoffCommand,
    Vec3,
)
from shared.sensors import color_message, depth_message, raw16_message, transforms_message
from tests.helpers import arun, bus_for, run_stack, wait_until
from tests.perception.scenes import aim_at, projected_corners_in_view, render_view, unoccluded_pixels

pytestmark = pytest.mark.integration

KEYS = Keys("am1")


async def ask(bus: Bus, key, payload, timeout: float = 20.0):
    """Query; a queryable may be declared a moment after its service's liveliness token: retry NoResponder."""
    deadline = time.monotonic() + 30
    while True:
        try:
            return await bus.query(key, payload, timeout=timeout)
        except NoResponder:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.2)


CUP_LABELS = SimLabels(labels=(SimLabel(id=100, name="red cup", category="object", color="red",
                                        size=Vec3(x=0.08, y=0.08, z=0.11)),))


def publish_cup_frame(bus: Bus) -> int:
    """One synthetic frame set for the `sim` segmenter: a grey plane 1.5 m ahead with the red cup's instance id
    (label 100, CUP_LABELS) 1.4 m away, tf and all, under one stamp; the stamp."""
    from shared.frames import base_to_camera
    from shared.sensors import pose_matrix

    stamp = time.time_ns()
    depth = np.full((480, 640), 1500, np.uint16)
    seg = np.zeros((480, 640), np.uint16)
    seg[200:260, 300:340] = 100
    depth[200:260, 300:340] = 1400
    bus.publish(KEYS.tf, transforms_message([("world", "base_link", pose_matrix(0, 0, 1.5, 0)),
                                             ("base_link", "camera", base_to_camera())], stamp))
    bus.publish(KEYS.camera_segmentation, raw16_message(seg, stamp))
    bus.publish(KEYS.camera_depth, depth_message(depth, stamp))
    bus.publish(KEYS.camera_color, color_message(np.full((480, 640, 3), 120, np.uint8), stamp))
    return stamp


# --------------------------------------------------------------------------- against the real simulator


@pytest.mark.slow
@pytest.mark.parametrize("segmenter", ["sim", "color"])
def test_real_sim_objects_surfaces_and_detections(segmenter: str, tmp_path) -> None:
    # The kinematic body (its estimate still drifts, by up to 3 cm): the test compares each answer, in the estimated
    # frame, with the truth through one estimate/truth pair read once; the multirotor's estimate bias (sigma 2.5 cm
    # horizontal, 3.1 cm vertical, tau 10 s) moves centimetres between that read and the frames perception
    # answers from, and its hover tilts the view a fraction of a degree (ci33 and a local loop: 5.4 cm, 5.7 cm and
    # 4.7 cm over their tolerances in about 1 run of 6). Perception on the multirotor's frames is measured by
    # benchmarks/detection_recall.py and the grasp benchmark, and flown by the demo and evaluation tests.
    env = {"AERMANI_SIM_FPS": "4", "AERMANI_SIM_SPEED_FACTOR": "3", "AERMANI_PERCEPTION_SEGMENTER": segmenter,
           "AERMANI_SIM_SEED": "3", "AERMANI_SIM_DYNAMICS": "kinematic"}
    with run_stack(["sim", "autopilot_bridge", "perception"], tmp_path, env=env) as stack:
        arun(_fly_and_check(stack, segmenter), timeout=400)


async def _fly_and_check(stack, segmenter: str) -> None:
    async with bus_for(stack) as bus:
        state = Latest(bus.subscribe(KEYS.autopilot_state))
        dets = Latest(bus.subscribe(KEYS.detections))
        tasks = [asyncio.create_task(state.run()), asyncio.create_task(dets.run())]
        try:
            scenario = Scenario(seed=11, target_object="red cup")
            reset = await ask(bus, KEYS.sim_reset, scenario, 30)
            assert reset.ok, reset.message
            world, _, _ = generate(scenario)  # the same input the sim got: the same layout
            await wait_until(lambda: state.value is not None and state.value.link_ok, 60, what="bridge link")
            res = await ask(bus, KEYS.autopilot_command, ArmCommand(), 60)
            assert res.ok, res.message
            res = await ask(bus, KEYS.autopilot_command, TakeoffCommand(altitude=1.5), 120)
            assert res.ok, res.message
            target = world.by_name("red cup")
            x, y, z, yaw = aim_at(world, target.center, 1.1, np.random.default_rng(0))
            res = await ask(bus, KEYS.autopilot_command, GotoCommand(position=Vec3(x=x, y=y, z=z), yaw=yaw), 60)
            assert res.ok, res.message

            def settled() -> bool:
                s = state.value
                return (math.dist(s.position.as_tuple(), (x, y, z)) < 0.05 and math.hypot(s.velocity.x, s.velocity.y)
                        < 0.05 and abs(math.atan2(math.sin(s.yaw - yaw), math.cos(s.yaw - yaw))) < 0.03)

            await wait_until(settled, 90, what=f"hover at the viewpoint: {state.value}")
            await asyncio.sleep(1.0)  # a fresh frame from the settled pose
            judge = await ask(bus, KEYS.sim_judge, JudgeRequest(op="world"))
            v = judge.vehicle
            view = render_view(world, v.position.x, v.position.y, v.position.z, v.yaw)
            believed = state.value  # the bridge's estimate of the same settled pose

            def in_truth_frame(p: Vec3, top_z: float, believed=believed, v=v) -> tuple[float, float, float]:
                """A point perception gave in the estimated frame, moved into the true one (by the estimate and the
                truth of the vehicle's pose read at about the same moment: their difference drifts over ~10 s)."""
                dyaw = believed.yaw - v.yaw
                dx, dy = p.x - believed.position.x, p.y - believed.position.y
                c, s_ = math.cos(-dyaw), math.sin(-dyaw)
                return (v.position.x + c * dx - s_ * dy, v.position.y + s_ * dx + c * dy,
                        top_z - (believed.position.z - v.position.z))

            checked = 0
            for truth in judge.objects:
                e = world.by_name(truth.name)
                px = int((view.instance == e.id).sum())
                if truth.category == "object":
                    est = await ask(bus, KEYS.localize_object, LocalizeRequest(query=truth.name, max_frame_age_s=2.0))
                    assert est.reason not in ("no_frame", "stale_frame", "error", "bad_query"), est
                    in_view = (px >= 100 and projected_corners_in_view(e, view.frame)
                               and px >= 0.5 * unoccluded_pixels(view, e)
                               and np.linalg.norm(e.center - view.frame.world_from_camera[:3, 3]) <= 3.0)
                    if px == 0:
                        assert not est.found and est.reason == "not_visible", est
                    elif in_view and (segmenter == "sim" or truth.name in COLOR_SET):
                        assert est.found, est
                        # Perception answers in the vehicle's estimated frame, which drifts from the truth (the
                        # realistic estimate: bias up to 3 cm, yaw up to 1 deg): judge it in that frame.
                        px_, py_, pz_ = in_truth_frame(est.pose.position, est.top_z)
                        # 4 cm: the centre of an object seen from one side comes from its visible half; at 1.1 m
                        # the colour segmenter's centre error reached 3.2-3.3 cm in about 1 run of 4 (measured
                        # over 12 runs on 2026-12-02), so 3 cm failed on camera noise alone.
                        assert math.hypot(px_ - truth.position.x, py_ - truth.position.y) <= 0.04, (truth, est)
                        assert abs(pz_ - truth.top_z) <= 0.03, (truth, est)
                        checked += 1
                elif truth.category == "surface":
                    est = await ask(bus, KEYS.localize_placement, LocalizeRequest(
                        query=truth.name, object_size=Vec3(x=0.08, y=0.08, z=0.11), max_frame_age_s=2.0))
                    if px == 0:
                        assert not est.found and est.reason == "not_visible", est
                    elif est.found:
                        # in the estimated frame, like the objects: the estimate's bias moves the measured height
                        sx, sy, sz = in_truth_frame(est.pose.position, est.surface_z)
                        assert est.label == truth.name
                        assert abs(sz - truth.top_z) <= 0.05, (truth, est, believed, v)
                        assert e.contains_xy(sx, sy, 0.0), (truth, est)
                        for o in world.objects:
                            if o.support == e.name:
                                assert math.hypot(sx - o.center[0], sy - o.center[1]) >= o.footprint_radius()
                        checked += 1
            assert checked >= 2, "the viewpoint should show the target and its surface"
            await wait_until(lambda: dets.value is not None and any(d.label == "red cup" for d in dets.value.items),
                             30, what="red cup in the detections")
            red = next(d for d in dets.value.items if d.label == "red cup")
            # in the estimated frame too, seconds after the pair above: corrected by the pose read now
            now_truth = (await ask(bus, KEYS.sim_judge, JudgeRequest(op="world"))).vehicle
            rx, ry, _ = in_truth_frame(red.centroid, red.centroid.z, believed=state.value, v=now_truth)
            assert math.hypot(rx - target.center[0], ry - target.center[1]) < 0.05, (red, now_truth, state.value)
            assert dets.value.segmenter == segmenter
        finally:
            for t in tasks:
                t.cancel()


COLOR_SET = {"red cup", "green bottle", "purple cup", "orange", "banana", "coke can", "tissue box"}


# --------------------------------------------------------------------------- bad input, no frames, stale frames


def test_bad_queries_no_frame_stale_frame(tmp_path) -> None:
    # The oracle segmenter: the synthetic frame below marks the cup by its instance id (the default colour
    # segmenter would need rendered pixels of a cup).
    with run_stack(["perception"], tmp_path, env={"AERMANI_PERCEPTION_FRAME_WAIT_S": "0.3",
                                                  "AERMANI_PERCEPTION_SEGMENTER": "sim"}) as stack:
        arun(_bad_and_stale(stack), timeout=200)


async def _bad_and_stale(stack) -> None:
    async with bus_for(stack) as bus:
        # Nothing publishes frames yet.
        est = await ask(bus, KEYS.localize_object, LocalizeRequest(query="red cup"))
        assert not est.found and est.reason == "no_frame" and "colour" in est.message
        est = await ask(bus, KEYS.localize_placement, LocalizeRequest(query="table"))
        assert est.reason == "no_frame"

        bad = [b"", b"not json", b"[1, 2]", json.dumps({"query": ""}).encode(),
               json.dumps({"query": "x" * 10_240}).encode(), json.dumps({"query": "red\x00cup\x1b[2J"}).encode(),
               json.dumps({"query": 42}).encode(), json.dumps({"nothing": "here"}).encode(),
               json.dumps({"query": "red cup", "max_frame_age_s": "soon"}).encode()]
        for payload in bad:
            for key, model in ((KEYS.localize_object, ObjectEstimate), (KEYS.localize_placement, PlacementEstimate)):
                est = await ask(bus, key, payload, timeout=10)
                assert isinstance(est, model) and not est.found and est.reason == "bad_query", (payload[:40], est)
                assert est.message and len(est.query) <= 200

        # One frame set: a grey plane 1.5 m ahead with a red cup's instance id... published once, then silence.
        bus.publish(KEYS.sim_labels, CUP_LABELS)
        await asyncio.sleep(0.5)
        stamp = publish_cup_frame(bus)

        async def fresh() -> ObjectEstimate:
            return await ask(bus, KEYS.localize_object, LocalizeRequest(query="red cup", max_frame_age_s=30))

        deadline = time.monotonic() + 30
        est = await fresh()
        while est.reason == "no_frame" and time.monotonic() < deadline:
            await asyncio.sleep(0.2)
            est = await fresh()
        assert est.found and est.label == "red cup" and est.frame_stamp_ns == stamp, est
        await asyncio.sleep(1.2)
        est = await ask(bus, KEYS.localize_object, LocalizeRequest(query="red cup", max_frame_age_s=0.5))
        assert not est.found and est.reason == "stale_frame" and "old" in est.message
        # Unknown words with a frame present: still a clear bad_query.
        est = await fresh()
        assert est.found
        est = await ask(bus, KEYS.localize_object, LocalizeRequest(query="flux capacitor", max_frame_age_s=30))
        assert est.reason == "bad_query" and "no known object" in est.message


# --------------------------------------------------------------------------- the observation after a skill


def test_detections_for_the_first_frame_after_a_skill_ends_without_waiting_for_the_rate(tmp_path) -> None:
    """Issue 27: the reasoner's next step waits for detections of a frame received after the skill ended. With
    detections at 0.01 Hz (one pass per 100 s), the only way a detection of the frame sent after the skill's
    terminal status arrives within the test's 30 s is the skill-end trigger."""
    env = {"AERMANI_PERCEPTION_SEGMENTER": "sim", "AERMANI_PERCEPTION_DETECTIONS_HZ": "0.01"}
    with run_stack(["perception"], tmp_path, env=env) as stack:
        arun(_after_skill_end(stack), timeout=200)


async def _after_skill_end(stack) -> None:
    from shared.messages import SkillState, SkillStatus

    async with bus_for(stack) as bus:
        dets = bus.subscribe(KEYS.detections, maxsize=20)
        bus.publish(KEYS.sim_labels, CUP_LABELS)
        frame_set = functools.partial(publish_cup_frame, bus)

        before = frame_set()
        # the service has the frame (a query answers from it)
        deadline = time.monotonic() + 30
        while not (await ask(bus, KEYS.localize_object, LocalizeRequest(query="red cup", max_frame_age_s=60))).found:
            assert time.monotonic() < deadline, "perception never took the first frame"
            await asyncio.sleep(0.2)
            before = frame_set()
        # A skill ends; then the next frame arrives: its detections come at once, not at the next 100 s tick.
        bus.publish(KEYS.skill_status, SkillStatus(goal_id="g1", skill="left", state=SkillState.SUCCEEDED,
                                                   task_id="t1", step=1, ended_ns=time.time_ns()))
        await asyncio.sleep(0.3)
        after = frame_set()
        got = None
        with contextlib.suppress(TimeoutError):
            while got is None or got.frame_stamp_ns < after:
                got = await dets.recv(timeout=30)
        assert got is not None and got.frame_stamp_ns == after, (got, before, after)
        assert [d.label for d in got.items] == ["red cup"], got


# --------------------------------------------------------------------------- a segmenter that cannot start


def test_sam3_without_torch_fails_at_start_with_install_hint() -> None:
    pytest.importorskip("zenoh")
    import importlib.util

    if importlib.util.find_spec("torch") is not None:
        pytest.skip("torch is installed here; the failure path needs it missing")

    async def body() -> subprocess.CompletedProcess:
        port = free_port()
        router = await Bus.open(mode="router", listen=[f"tcp/127.0.0.1:{port}"], connect=[])
        try:
            env = {**os.environ, "AERMANI_ZENOH_CONNECT": f"tcp/127.0.0.1:{port}",
                   "AERMANI_PERCEPTION_SEGMENTER": "sam3"}
            return await asyncio.to_thread(subprocess.run, [sys.executable, "-m", "services.perception"], env=env,
                                           capture_output=True, text=True, timeout=120)
        finally:
            await router.close()

    proc = arun(body(), timeout=150)
    assert proc.returncode != 0
    out = proc.stdout + proc.stderr
    assert "sam3" in out and "torch" in out and "pip install" in out
    assert "AERMANI_PERCEPTION_SEGMENTER=color" in out
