"""PX4's authority over the stack, with real processes over real UDP, Zenoh and HTTP.

- A PX4 failsafe mid-task (an injected critical battery through the simulator's ground-station link, so PX4
  switches OFFBOARD -> AUTO.RTL) fails the running skill, ends the task with that reason, and nothing in the
  stack re-enters OFFBOARD, arms or takes off again; the simulated PX4 would accept OFFBOARD, so this is the
  stack's restraint, not PX4's refusal.
- With the executor killed, an abort through the gateway's HTTP API still holds the vehicle: the bridge
  obeys safety/abort itself, and the answer names the services that acknowledged.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mav

from aermani.launcher import free_udp_port
from shared.bus import Bus, Latest
from shared.keys import Keys
from shared.messages import (
    GotoCommand,
    Scenario,
    SkillState,
    SkillStatus,
    TakeoffCommand,
    TaskRequest,
    TaskState,
    TaskStatus,
    Vec3,
)
from tests.gateway.conftest import TOKEN
from tests.gateway.test_process import GatewayProcess
from tests.helpers import bus_for, run_stack, wait_until
from tests.sim.test_mavlink import Client

pytestmark = [pytest.mark.integration, pytest.mark.slow]

KEYS = Keys("am1")
COMMAND = "Pick up the red cup and place it on the table."
RULES = {"AERMANI_REASONER_BACKEND": "rules", "AERMANI_REASONER_T_MAX_S": "300", "AERMANI_SIM_FPS": "5"}
MODE_NAMES = {(4, 5): "AUTO.RTL", (4, 6): "AUTO.LAND", (4, 3): "AUTO.LOITER", (6, 0): "OFFBOARD", (3, 0): "POSCTL"}


def mode_of(hb) -> str:
    main, sub = (hb.custom_mode >> 16) & 0xFF, (hb.custom_mode >> 24) & 0xFF
    return MODE_NAMES.get((main, sub), f"{main}.{sub}")


async def reset(bus: Bus, seed: int) -> None:
    res = await bus.query(KEYS.sim_reset, Scenario(seed=seed, target_object="red cup", destination="table"), timeout=30)
    assert res.ok, res.message


@pytest.mark.timeout(900)
async def test_px4_failsafe_mid_task_ends_the_task_and_nothing_reenters_offboard(tmp_path: Path) -> None:
    gcs_port = free_udp_port()
    env = {**RULES, "AERMANI_SIM_SPEED_FACTOR": "3", "AERMANI_SIM_GCS_PORT": str(gcs_port)}
    services = ["sim", "autopilot_bridge", "perception", "executor", "reasoner"]
    with run_stack(services, tmp_path, env=env, timeout=180) as stack:
        gcs: Client | None = None

        def failsafe() -> None:
            """PX4's low-battery failsafe: the battery goes critical, PX4 switches to AUTO.RTL on its own."""
            nonlocal gcs
            # A ground station on PX4's GCS link, as QGroundControl would be; connected only now, so its socket
            # buffer is not full of a minute of unread telemetry (which would drop the answers).
            gcs = Client(gcs_port)
            gcs.conn.mav.param_set_send(1, 1, b"SYS_FAILURE_EN", 1.0, mav.MAV_PARAM_TYPE_REAL32)
            gcs.recv("PARAM_VALUE", lambda m: m.param_id == "SYS_FAILURE_EN" and m.param_value == 1.0)
            assert gcs.command(mav.MAV_CMD_INJECT_FAILURE, mav.FAILURE_UNIT_SYSTEM_BATTERY,
                               mav.FAILURE_TYPE_OFF) == 0

        def watch() -> tuple[list[str], list[bool], float]:
            """Every autopilot heartbeat from the failsafe until the vehicle is down and disarmed, then 3 s more."""
            assert gcs is not None

            def hb():
                return gcs.recv("HEARTBEAT", lambda m: m.get_srcSystem() == 1 and m.get_srcComponent() == 1)

            modes: list[str] = []
            deadline = time.monotonic() + 150
            while True:
                m = hb()
                modes.append(mode_of(m))
                if any(x != "OFFBOARD" for x in modes) and not m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED:
                    break
                assert time.monotonic() < deadline, f"RTL did not end on the ground: {modes[-20:]}"
            armed_after: list[bool] = []
            quiet_end = time.monotonic() + 3.0
            while time.monotonic() < quiet_end:
                m = hb()
                modes.append(mode_of(m))
                armed_after.append(bool(m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED))
            return modes, armed_after, gcs.recv("LOCAL_POSITION_NED").z

        async def body() -> None:
            async with bus_for(stack) as bus:
                state = Latest(bus.subscribe(KEYS.autopilot_state))
                statuses: list[TaskStatus] = []
                skills: list[SkillStatus] = []
                sub = bus.subscribe(KEYS.task_status, maxsize=100)
                skill_sub = bus.subscribe(KEYS.skill_status, maxsize=200)

                async def collect() -> None:
                    while True:
                        statuses.append(await sub.recv())

                async def collect_skills() -> None:
                    while True:
                        skills.append(await skill_sub.recv())

                tasks = [asyncio.create_task(state.run()), asyncio.create_task(collect()),
                         asyncio.create_task(collect_skills())]
                try:
                    await reset(bus, seed=1)
                    await wait_until(lambda: state.value is not None and state.value.link_ok
                                     and not state.value.armed, 60, what="grounded after the reset")
                    acc = await bus.query(KEYS.start_task, TaskRequest(command=COMMAND), timeout=30)
                    assert acc.accepted, acc.reason
                    tid = acc.task_id

                    def grasping() -> SkillStatus | None:
                        return next((k for k in skills if k.task_id == tid and k.skill == "grasp"
                                     and k.state is SkillState.RUNNING), None)

                    # Mid-skill: the grasp flies in OFFBOARD for several seconds.
                    await wait_until(lambda: grasping() is not None, 240, what="the task's grasp running")
                    await asyncio.sleep(1.0)
                    goal = grasping().goal_id
                    assert state.value.offboard_ok and state.value.position.z > 0.5
                    assert not any(t.task_id == tid and t.state.terminal for t in statuses), statuses[-1]
                    await asyncio.to_thread(failsafe)
                    modes, armed_after, z = await asyncio.to_thread(watch)
                    # PX4 flies RTL then lands (at 1 Hz heartbeats a short RTL may show as AUTO.LAND only).
                    after_switch = modes[next(i for i, x in enumerate(modes) if x != "OFFBOARD"):]
                    assert after_switch[0] in ("AUTO.RTL", "AUTO.LAND"), modes
                    assert "OFFBOARD" not in after_switch, f"the stack re-entered OFFBOARD: {after_switch}"
                    assert not any(armed_after), "the stack armed again after PX4's landing"
                    # Landed, the realistic world's estimate reads the height with its vertical bias (sigma 3.1 cm,
                    # wandering): a 5 cm bound failed at 6.3 cm (ci39; P(bias > 5 cm) is about 5 %). A take-off
                    # climbs to 1 m.
                    assert z > -0.3, f"the vehicle took off again: estimated {-z:.2f} m up"
                    # The task ended with PX4's reason (while PX4 flew home), not with a retry.
                    await wait_until(lambda: any(t.task_id == tid and t.state.terminal for t in statuses), 30,
                                     what="the task's terminal status")
                    final = next(t for t in statuses if t.task_id == tid and t.state.terminal)
                    grasp = next(k for k in skills if k.goal_id == goal and k.state.terminal)
                    assert grasp.state is SkillState.FAILED, grasp
                    took = "the autopilot took control: PX4 switched from OFFBOARD to AUTO."
                    assert grasp.message.startswith(took), grasp
                    assert final.state is TaskState.FAILED, final
                    assert took in final.message and "a new command is needed" in final.message, final
                    st = state.value
                    assert st is not None and st.override.startswith("PX4 switched from OFFBOARD to AUTO.")
                    assert not st.armed and not st.offboard_ok
                    # The same task cannot take the vehicle back; a new operator command could.
                    res = await bus.query(KEYS.autopilot_command, TakeoffCommand(altitude=1.0, task_id=tid), timeout=10)
                    assert not res.ok and "a new operator command is needed" in res.message, res
                finally:
                    for t in tasks:
                        t.cancel()

        try:
            await body()
        finally:
            if gcs is not None:
                gcs.close()


@pytest.mark.timeout(600)
async def test_abort_through_the_api_holds_the_vehicle_with_the_executor_dead(tmp_path: Path) -> None:
    env = {**RULES, "AERMANI_SIM_SPEED_FACTOR": "2"}
    with run_stack(["sim", "autopilot_bridge", "executor", "reasoner"], tmp_path, env=env, timeout=180) as stack:
        gw = GatewayProcess(tmp_path, stack.endpoint)
        try:
            gw.start(timeout=120)

            async with bus_for(stack) as bus:
                state = Latest(bus.subscribe(KEYS.autopilot_state))
                pump = asyncio.create_task(state.run())
                try:
                    await reset(bus, seed=1)
                    await wait_until(lambda: state.value is not None and state.value.link_ok
                                     and not state.value.armed, 60, what="grounded after the reset")
                    # An operator flies by hand: take off, then a slow climb that takes ~10 s.
                    res = await bus.query(KEYS.autopilot_command, TakeoffCommand(altitude=1.0), timeout=60)
                    assert res.ok, res.message
                    p = state.value.position
                    goal = Vec3(x=p.x, y=p.y, z=2.4)
                    res = await bus.query(KEYS.autopilot_command,
                                          GotoCommand(position=goal, yaw=state.value.yaw, max_speed=0.12), timeout=10)
                    assert res.ok, res.message
                    await wait_until(lambda: state.value.position.z > 1.15, 20, what="climbing")

                    stack.kill("executor")  # SIGKILL: no goodbye, nothing holds on its behalf
                    with httpx.Client(base_url=gw.url, timeout=30,
                                      headers={"Authorization": f"Bearer {TOKEN}"}) as c:
                        await wait_until(lambda: not next(v for v in c.get("/health").json()["vehicles"]
                                                          if v["vehicle_id"] == "am1")["services"].get("executor"),
                                         30, what="the gateway sees the executor gone")
                        ab = c.post("/abort", json={"reason": "executor dead, stop now"})
                    assert ab.status_code == 202, ab.text
                    out = ab.json()
                    assert out["acknowledged"] == ["am1"], out
                    assert set(out["services"]["am1"]) == {"autopilot_bridge"}, out
                    assert "holding" in out["services"]["am1"]["autopilot_bridge"], out
                    # The vehicle stops climbing and stays put, well short of the goal.
                    await asyncio.sleep(1.5)
                    z0 = state.value.position.z
                    samples = []
                    t_end = time.monotonic() + 3.0
                    while time.monotonic() < t_end:
                        st = await state.wait(2.0)
                        samples.append((time.monotonic(), st.position.z))
                    assert all(abs(z - z0) < 0.05 for _, z in samples), samples[-5:]
                    # Held, not climbing: the height's trend over the 3 s, not any one velocity sample (the
                    # realistic multirotor's hover jitters a few cm/s in gusts; the cut climb was 0.12 m/s).
                    slope = float(np.polyfit([t for t, _ in samples], [z for _, z in samples], 1)[0])
                    assert abs(slope) < 0.03, f"still moving vertically at {slope:.3f} m/s: {samples[-5:]}"
                    assert z0 < goal.z - 0.5, f"the vehicle kept climbing to {z0:.2f} m"
                    st = state.value
                    assert st.armed and st.landed_state == "in_air"
                    assert st.override.startswith("aborted by gateway: executor dead, stop now"), st.override
                    # The bridge's own hold stays in force: the old goto is not resumed.
                    await asyncio.sleep(2.0)
                    assert abs(state.value.position.z - z0) < 0.05
                finally:
                    pump.cancel()
        finally:
            if gw.proc is not None and gw.proc.poll() is None:
                gw.stop()
