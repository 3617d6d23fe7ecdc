"""Cancelling a task mid-grasp on the real stack (MuJoCo simulator, autopilot bridge over MAVLink/UDP,
perception, executor and the reasoner with the rules policy, all real processes over Zenoh): the grasp
stops, the vehicle holds, and the task ends `aborted` with the reason."""

from __future__ import annotations

import math
import time

import pytest

from shared.action import task_client
from shared.errors import NoResponder
from shared.keys import Keys
from shared.messages import JudgeRequest, Scenario, SkillState, TaskRequest, TaskState
from tests.helpers import bus_for, run_stack

pytestmark = [pytest.mark.integration, pytest.mark.slow]

SERVICES = ["sim", "autopilot_bridge", "perception", "executor", "reasoner"]
KEYS = Keys("am1")
ENV = {"AERMANI_SIM_SPEED_FACTOR": "3", "AERMANI_REASONER_BACKEND": "rules", "AERMANI_REASONER_T_MAX_S": "400",
       "AERMANI_REASONER_MAX_STEPS": "60"}


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    with run_stack(SERVICES, tmp_path_factory.mktemp("task_cancel_stack"), env=ENV) as s:
        yield s


async def test_cancel_a_task_mid_grasp_stops_the_grasp_and_holds(stack):
    async with bus_for(stack) as bus:
        deadline = time.monotonic() + 90
        while True:  # the sim announces liveliness before its queryables are up
            try:
                await bus.query(KEYS.sim_reset, Scenario(seed=1, target_object="red cup", destination="table"),
                                timeout=30)
                break
            except NoResponder:
                assert time.monotonic() < deadline, "the simulator never served sim/reset"
        skills = bus.subscribe(KEYS.skill_status, maxsize=2000)
        states = bus.subscribe(KEYS.autopilot_state, maxsize=2, overflow="latest")
        async with task_client(bus, "am1") as tasks:
            goal = await tasks.send_goal(TaskRequest(command="Pick up the red cup and place it on the table."),
                                         ready_timeout=60)
            assert goal.accepted, goal.reason
            # Follow the skills until the grasp is running (the policy takes off, searches, approaches first).
            grasp = None
            end = time.monotonic() + 400
            while grasp is None:
                st = await skills.recv(timeout=max(1.0, end - time.monotonic()))
                if st.task_id == goal.goal_id and st.skill == "grasp" and st.state == SkillState.RUNNING:
                    grasp = st
                assert not (st.task_id == goal.goal_id and st.skill == "done"), "the task ended before any grasp"
            cancelled_at = time.monotonic()
            reply = await goal.cancel(reason="operator stop mid-grasp", source="test")
            assert reply.accepted, reply.reason
            final = await goal.result(timeout=60)
            ended_after = time.monotonic() - cancelled_at
        assert final is not None and final.state == TaskState.ABORTED, final
        assert "operator stop mid-grasp" in final.message and "skill grasp aborted" in final.message, final.message
        # The grasp itself was stopped by the cancel (its terminal status came before the task's end).
        stopped = None
        while stopped is None:
            st = await skills.recv(timeout=10)
            if st.goal_id == grasp.goal_id and st.state.terminal:
                stopped = st
        assert stopped.state == SkillState.ABORTED, stopped
        assert stopped.outcome.code is not None and stopped.outcome.code.value == "aborted", stopped.outcome
        assert stopped.ended_ns <= final.ended_ns
        # The vehicle holds: its speed goes to about zero and the bridge is in PX4 Hold (or holds in OFFBOARD).
        deadline = time.monotonic() + 20
        while True:
            s = await states.recv(timeout=5)
            speed = math.sqrt(s.velocity.x ** 2 + s.velocity.y ** 2 + s.velocity.z ** 2)
            if speed < 0.05:
                break
            assert time.monotonic() < deadline, f"the vehicle did not come to rest after the cancel ({speed:.2f} m/s)"
        print(f"cancel -> task aborted {ended_after:.2f} s, cancel -> at rest {time.monotonic() - cancelled_at:.2f} s "
              f"(sim speed factor {ENV['AERMANI_SIM_SPEED_FACTOR']}, seed 1, mode {s.mode})")
        assert s.mode in ("AUTO.LOITER", "OFFBOARD"), s.mode
        assert s.landed_state.value == "in_air", s.landed_state
        assert (await bus.query(KEYS.sim_judge, JudgeRequest(op="held"), timeout=10)).held is None
