"""The executor with the real sim, autopilot bridge and perception processes over real Zenoh and MAVLink/UDP.

One stack serves the module (start-up is the expensive part); every test resets the world with `sim/reset`.
The simulator's ground truth (`sim/judge`) is read only by the tests, never by the executor."""

from __future__ import annotations

import asyncio
import math
import signal
import time

import pytest

from services.executor.settings import ExecutorSettings
from shared.bus import Bus
from shared.errors import NoResponder
from shared.keys import Keys
from shared.messages import (
    Abort,
    AbortAck,
    JudgeRequest,
    JudgeResult,
    Scenario,
    SimResetResult,
    SkillAccept,
    SkillRequest,
    SkillState,
    SkillStatus,
)
from shared.sensors import parse_color
from shared.tasks import ask_judge
from tests.helpers import bus_for, run_stack, skill_outcome, wait_until

pytestmark = [pytest.mark.integration, pytest.mark.slow]

SERVICES = ["sim", "autopilot_bridge", "perception", "executor"]
KEYS = Keys("am1")


# The kinematic body: these tests assert what one skill call does (a grasp that must hold, a slip, an abort mid-grasp,
# a fault's outcome). On the multirotor's realistic hover a grasp call succeeds at the rate benchmarks/grasp.py
# measures, not always, and a pass/fail test of one call would be a draw; the subject here is the skill's logic,
# with the camera's realism and perception unchanged. The multirotor flies the policy-level stack tests
# (tests/reasoner/test_demo.py, tests/faults, tests/evaluation; those that assert a task's success fly it in the
# ideal world, where no gust decides the grasp) and the grasp benchmark.
@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    with run_stack(SERVICES, tmp_path_factory.mktemp("executor_stack"),
                   env={"AERMANI_SIM_SPEED_FACTOR": "3", "AERMANI_SIM_DYNAMICS": "kinematic"}) as s:
        yield s


class Client:
    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.statuses = bus.subscribe(KEYS.skill_status, maxsize=1000)
        self.states = bus.subscribe(KEYS.autopilot_state, maxsize=2)
        self.acks = bus.subscribe(KEYS.abort_ack, maxsize=100)
        """Subscribed long before any abort: one subscribed just before it raced its way through the router."""

    async def reset(self, **kw) -> SimResetResult:
        # The sim announces liveliness before its queryables are up (its renderer starts in a child process).
        deadline = time.monotonic() + 90
        while True:
            try:
                res = await self.bus.query(KEYS.sim_reset, Scenario(**kw), timeout=30)
                break
            except NoResponder:
                if time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.5)
        assert res.ok, res.message
        await asyncio.sleep(1.0)  # let the bridge and camera see the new world
        return res

    async def judge(self, **kw) -> JudgeResult:
        """The simulator's verdict; one that only waits on the task's rest or hold time is asked again then."""
        return await ask_judge(self.bus, KEYS, JudgeRequest(**kw), timeout=10)

    async def request(self, skill: str, argument: str | None = None) -> SkillAccept:
        return await self.bus.query(KEYS.run_skill, SkillRequest(skill=skill, argument=argument),
                                    timeout=10)

    async def terminal(self, goal_id: str, timeout: float = 150.0) -> SkillStatus:
        return await skill_outcome(self.statuses, goal_id, timeout)

    async def run(self, skill: str, argument: str | None = None) -> SkillStatus:
        acc = await self.request(skill, argument)
        return await self.terminal(acc.goal_id)

    async def ok(self, skill: str, argument: str | None = None) -> SkillStatus:
        st = await self.run(skill, argument)
        assert st.state == SkillState.SUCCEEDED, f"{skill}({argument}): {st.state.value}: {st.message}"
        return st

    async def takeoff(self) -> None:
        for _ in range(20):  # the bridge may need a moment after a reset before it accepts arming
            st = await self.run("takeoff")
            if st.state == SkillState.SUCCEEDED:
                return
            await asyncio.sleep(1.0)
        raise AssertionError(f"takeoff failed: {st.message}")

    async def look_around(self, skill: str, argument: str, turns: int) -> SkillStatus:
        """Yaw left until the localization succeeds (the paper's active search), at most `turns` times; the
        last localization's status."""
        for _ in range(turns):
            st = await self.run(skill, argument)
            if st.state == SkillState.SUCCEEDED:
                return st
            await self.ok("yaw_left")
        return st

    async def search(self, skill: str, argument: str, turns: int = 13) -> SkillStatus:
        st = await self.look_around(skill, argument, turns)
        if st.state != SkillState.SUCCEEDED:
            raise AssertionError(f"{argument} never found: {st.message}; {await self.where(argument)}")
        return st

    async def search_near(self, skill: str, surface: str, within: float = 1.6) -> SkillStatus:
        """Fly toward `surface` (where the simulator has it) until within `within` m of its centre, then look
        around for it. For tests whose subject is what comes after the search: seed 5's table stands 2.6 m from
        the shelf the cup is taken from, where its top is found in some frames only (a grazing view of a
        noisy depth image; a CI run once looked all round from there without finding it)."""
        where = next(o for o in (await self.judge(op="world")).objects if o.name == surface)
        for _ in range(16):
            if await self.step_toward(where.position, within):
                return await self.search(skill, surface)
        raise AssertionError(f"could not approach the {surface}")

    async def search_backing_off(self, skill: str, argument: str, steps: int) -> SkillStatus:
        """Back off one step and look around a full circle (yaw_left turns 40 deg), up to `steps` times; where a
        step back is refused (the room's end, an obstacle behind) the look from there is the last."""
        st: SkillStatus | None = None
        back: SkillStatus | None = None
        for _ in range(steps):
            back = await self.run("backward")
            st = await self.look_around(skill, argument, turns=9)
            if st.state == SkillState.SUCCEEDED:
                return st
            if back.state != SkillState.SUCCEEDED:
                break
        raise AssertionError(f"{argument} never found backing off {steps} steps: {st.message if st else '-'}; "
                             f"last backward: {back.message if back else '-'}; {await self.where(argument)}")

    async def where(self, label: str) -> str:
        """The simulator's truth beside the vehicle's own state and the camera's newest frame (a failure's facts)."""
        truth = await self.judge(op="held")
        v = truth.vehicle
        obj = next((o for o in truth.objects if o.name == label), None)
        st = self.states.latest_nowait() or await self.states.recv(timeout=5)
        frames = self.bus.subscribe(KEYS.camera_color, maxsize=1)
        try:
            frame_age = f"{(time.time_ns() - parse_color(await frames.recv(timeout=5))[0]) / 1e9:.2f} s"
        except TimeoutError:
            frame_age = "no frame in 5 s"
        finally:
            frames.close()
        return (f"truth: vehicle {v}, {label} {obj}; state: {st.position} yaw {st.yaw:.2f} mode {st.mode}; "
                f"newest camera frame {frame_age} old")

    async def approach(self, label: str, skill: str = "obj_localization", within: float = 1.6) -> SkillStatus:
        """What a policy does after "too far: approach first": turn toward the localized object, fly forward
        steps until it is within `within` m, and localize it again from there."""
        loc = await self.search(skill, label)
        for _ in range(16):
            if await self.step_toward(loc.outcome.estimate.pose.position, within):
                return loc
            loc = await self.search(skill, label)
        raise AssertionError(f"could not approach the {label}")

    async def step_toward(self, target, within: float) -> bool:
        """True when `target` (x, y) is within `within` m; otherwise one turn toward it or one step forward."""
        st = self.states.latest_nowait() or await self.states.recv(timeout=5)
        dx, dy = target.x - st.position.x, target.y - st.position.y
        if math.hypot(dx, dy) <= within:
            return True
        bearing = math.atan2(math.sin(math.atan2(dy, dx) - st.yaw), math.cos(math.atan2(dy, dx) - st.yaw))
        if abs(bearing) > math.radians(25):
            await self.ok("yaw_left" if bearing > 0 else "yaw_right")
        else:
            await self.ok("forward")
        return False

    async def speed(self) -> float:
        s = await self.states.recv(timeout=5)
        s = self.states.latest_nowait() or s
        return math.sqrt(s.velocity.x ** 2 + s.velocity.y ** 2 + s.velocity.z ** 2)


async def test_pick_and_place_sequence_judged_by_ground_truth(stack):
    async with bus_for(stack) as bus:
        c = Client(bus)
        # seed 5: the cup is on the shelf, 2.9 m from the table; both within perception range of the search
        await c.reset(seed=5, target_object="red cup", destination="table")
        await c.takeoff()
        await c.search("obj_localization", "red cup")
        far = await c.run("grasp")  # localized from the take-off spot, beyond the reach
        assert far.state == SkillState.REJECTED and "too far: approach first" in far.message, far.message
        for _attempt in range(3):
            # Like the policy after a failed grasp (paper Sec. III-D): re-localize, then grasp again.
            await c.approach("red cup")
            st = await c.run("grasp")
            if st.state == SkillState.SUCCEEDED:
                break
            assert "localize it again" in st.message or "grasp again" in st.message, st.message
        assert st.state == SkillState.SUCCEEDED, st.message
        # Verified by the gripper's own sensing (finger width and contact over MAVLink), not by looking.
        assert "in contact" in st.message, st.message
        assert st.outcome.held_object == "red cup"
        assert (await c.judge(op="held")).held == "red cup"
        await c.search_near("placement_localization", "table")
        st = await c.ok("place")
        verdict = await c.judge(op="on_surface", object="red cup", surface="table")
        assert verdict.ok, verdict.message
        world = await c.judge(op="world")
        assert world.collisions == (), world.collisions
        # land is the operator's call: the executor cannot see below, so it may sit over furniture
        await c.ok("land")


async def test_motion_primitives_and_operator_skills(stack):
    async with bus_for(stack) as bus:
        c = Client(bus)
        await c.reset(seed=3)
        await c.takeoff()
        for skill in ("up", "down", "yaw_left", "yaw_right", "backward", "left", "right", "hold", "done"):
            st = await c.ok(skill)
            a, b = st.outcome.start_pose, st.outcome.end_pose
            moved = math.dist(a.position.as_tuple(), b.position.as_tuple())
            if skill in ("up", "down"):
                assert abs(abs(b.position.z - a.position.z) - 0.3) < 0.1, (skill, a, b)
            elif skill in ("backward", "left", "right"):
                assert abs(moved - 0.5) < 0.12, (skill, moved)
            elif skill.startswith("yaw"):
                turn = math.degrees((b.yaw - a.yaw + math.pi) % (2 * math.pi) - math.pi)
                assert abs(abs(turn) - ExecutorSettings().yaw_step_deg) < 8, (skill, turn)
        # forward needs free depth ahead: turn until the corridor is clear (a rejection moves nothing)
        for _ in range(12):
            acc = await c.request("forward")
            if acc.accepted:
                st = await c.terminal(acc.goal_id)
                assert st.state == SkillState.SUCCEEDED, st.message
                break
            assert "obstacle" in acc.reason or "geofence" in acc.reason, acc.reason
            await c.ok("yaw_left")
        else:
            raise AssertionError("forward was never possible")
        await c.ok("land")


async def _abort(c: Client, goal_id: str) -> AbortAck:
    abort = Abort(reason="integration test", source="test")
    c.bus.publish(KEYS.abort, abort)
    ack = await c.acks.recv(timeout=10)
    while ack.service != "executor" or ack.abort_stamp_ns != abort.stamp_ns:
        # the autopilot bridge acknowledges too (it holds on its own); acks of an earlier abort are passed over
        assert ack.abort_stamp_ns != abort.stamp_ns or "holding" in ack.message, ack
        ack = await c.acks.recv(timeout=10)
    assert ack.abort_stamp_ns == abort.stamp_ns and ack.goal_id == goal_id and "holding" in ack.message
    st = await c.terminal(goal_id, 15)
    assert st.state == SkillState.ABORTED
    deadline = time.monotonic() + 15
    while await c.speed() > 0.1:
        assert time.monotonic() < deadline, "vehicle did not stop after abort"
    return ack


async def test_abort_during_translation_and_during_grasp(stack):
    async with bus_for(stack) as bus:
        c = Client(bus)
        await c.reset(seed=1, target_object="red cup", destination="table")
        await c.takeoff()
        acc = await c.request("backward")
        assert acc.accepted, acc.reason
        await asyncio.sleep(0.2)
        await _abort(c, acc.goal_id)
        await c.ok("yaw_left")  # ready for the next skill
        await c.approach("red cup")
        acc = await c.request("grasp")
        assert acc.accepted, acc.reason
        await asyncio.sleep(1.0)
        await _abort(c, acc.goal_id)
        assert (await c.judge(op="held")).held is None
        await c.ok("hold")
        await c.ok("land")


async def test_world_reset_clears_working_memory_so_no_grasp_runs_on_the_old_layout(stack):
    """The simulator's reset notice makes the executor forget the old world: a grasp of what was localized
    before the reset is refused (localize first) instead of flying to an empty spot; no process restart."""
    async with bus_for(stack) as bus:
        c = Client(bus)
        await c.reset(seed=1, target_object="red cup", destination="table")
        await c.takeoff()
        loc = await c.search("obj_localization", "red cup")
        await c.ok("land")
        # The world changes under the executor: the cup is now elsewhere (a new layout).
        await c.reset(seed=7, target_object="red cup", destination="table")
        truth = {o.name: o for o in (await c.judge(op="world")).objects}
        remembered = loc.outcome.estimate.pose.position
        assert math.hypot(truth["red cup"].position.x - remembered.x,
                          truth["red cup"].position.y - remembered.y) > 0.3
        await c.takeoff()
        # The reset notice cleared the executor's memory (the world it described is gone): the grasp is
        # refused before anything moves instead of flying to where the cup was.
        st = await c.run("grasp", "red cup")
        assert st.state == SkillState.REJECTED, st.message
        assert "run obj_localization first" in st.message, st.message
        assert (await c.judge(op="held")).held is None
        await c.ok("land")


async def test_abort_mid_takeoff_lands_disarmed_and_the_next_takeoff_is_clean(stack):
    """An abort while the take-off climbs lands the vehicle (a hold would leave it armed a few centimetres up,
    where no skill can move it); once down and disarmed, the next take-off reaches the flight altitude."""
    async with bus_for(stack) as bus:
        c = Client(bus)
        await c.reset(seed=2)
        acc = await c.request("takeoff")
        assert acc.accepted, acc.reason
        deadline = time.monotonic() + 60
        while (st := await c.states.recv(timeout=5)).position.z < 0.05:  # climbing
            assert time.monotonic() < deadline, "the take-off never climbed"
        abort = Abort(reason="abort mid-takeoff", source="test")
        c.bus.publish(KEYS.abort, abort)
        said = {}
        while set(said) != {"executor", "autopilot_bridge"}:  # the bridge obeys the abort on its own too
            ack = await c.acks.recv(timeout=10)
            if ack.abort_stamp_ns == abort.stamp_ns:  # (acks of an abort before this one are passed over)
                said[ack.service] = ack.message
        assert all("landing" in m for m in said.values()), said  # neither holds low: one lands, the other lets it
        assert (await c.terminal(acc.goal_id, 15)).state == SkillState.ABORTED
        deadline = time.monotonic() + 60
        while (st := await c.states.recv(timeout=5)).armed or st.landed_state.value != "on_ground":
            assert time.monotonic() < deadline, f"not down: {st.landed_state} armed={st.armed} z={st.position.z:.2f}"
        await c.takeoff()
        st = c.states.latest_nowait() or await c.states.recv(timeout=5)
        assert st.position.z > ExecutorSettings().min_altitude, st.position
        await c.ok("land")


async def test_bridge_and_executor_killed_while_holding_then_another_grasp_keeps_the_cup(stack):
    """Gripper truth survives restarts: with the cup held, the autopilot bridge and the executor are killed and
    started again (the executor's memory is empty, the bridge has never commanded the gripper); the new
    bridge reports the gripper closed on an object from the gripper's own telemetry at once, the executor
    takes that over memory, and a grasp of another object is refused instead of opening the fingers."""
    async with bus_for(stack) as bus:
        c = Client(bus)
        await c.reset(seed=1, target_object="red cup", destination="table", extra_objects=["apple"])
        await c.takeoff()
        await c.approach("red cup")
        await c.ok("grasp", "red cup")
        assert (await c.judge(op="held")).held == "red cup"
        for name in ("autopilot_bridge", "executor"):
            p = stack.find(name)
            stack.kill(name, signal.SIGKILL)
            p.proc.wait(timeout=10)
        # The router drops a killed session's liveliness token only once it sees the connection gone: until then
        # wait_alive would take the dead executor's token for the new one's, and ask a queryable not yet declared.
        killed = {("am1", "autopilot_bridge"), ("am1", "executor")}
        await wait_until(lambda: not killed & stack.alive(), 30, what="the killed services' tokens gone")
        restarted_ns = time.time_ns()
        for name in ("autopilot_bridge", "executor"):
            stack.find(name).start()
        stack.wait_alive(timeout=120)
        deadline = time.monotonic() + 60
        while not ((st := await c.states.recv(timeout=10)).link_ok and st.gripper_holding
                   and st.gripper.value == "closed" and st.stamp_ns > restarted_ns
                   and st.landed_state.value != "unknown"):  # unknown until the first EXTENDED_SYS_STATE
            assert time.monotonic() < deadline, f"the new bridge does not report the held cup: {st.gripper}"
        skills = await bus.query(KEYS.skills, None, timeout=10)  # the new executor answers
        assert skills.skills
        # The bridge's death was an offboard loss for PX4: its failsafe (the simulator's COM_OBL_RC_ACT=5, Hold)
        # holds in the air with the cup, and the new bridge leaves it there until an operator command.
        assert st.armed and st.landed_state.value == "in_air" and st.mode == "AUTO.LOITER", st
        st = await c.run("grasp", "apple")
        assert st.state == SkillState.REJECTED, f"{st.state.value}: {st.message}"
        assert "already holding" in st.message or "between its fingers" in st.message, st.message
        assert (await c.judge(op="held")).held == "red cup", "the cup was dropped"
        await c.ok("land")


async def test_bridge_killed_while_holding_over_the_table_holds_then_an_operator_place_works(stack):
    """The bridge dies with the cup held over the table: PX4's offboard-loss failsafe (COM_OBL_RC_ACT=5, Hold)
    keeps the vehicle in the air with the cup well past the 3 s after which Land would have put it down on
    the table (the user's 5 of 5); the restarted bridge finds it holding, latches that as PX4's control and
    moves nothing, and the operator's placement then flies: the cup ends on the table, the vehicle lands."""
    async with bus_for(stack) as bus:
        c = Client(bus)
        # seed 11: the cup stands on the round table, so it is held over the table (the user's case)
        await c.reset(seed=11, target_object="red cup", destination="round table")
        await c.takeoff()
        await c.approach("red cup")
        await c.ok("grasp", "red cup")
        before = await c.judge(op="held")
        assert before.held == "red cup" and before.vehicle is not None
        p = stack.find("autopilot_bridge")
        stack.kill("autopilot_bridge", signal.SIGKILL)
        p.proc.wait(timeout=10)
        await wait_until(lambda: ("am1", "autopilot_bridge") not in stack.alive(), 30,
                         what="the killed bridge's token gone")
        # Well past COM_OF_LOSS_T + COM_FAIL_ACT_T (0.5 + 3 s of wall time): Land would be on the table by now.
        await asyncio.sleep(6.0)
        during = await c.judge(op="held")
        assert during.held == "red cup", "the cup was put down or dropped while the bridge was dead"
        assert during.vehicle is not None and abs(during.vehicle.position.z - before.vehicle.position.z) < 0.15, \
            (before.vehicle, during.vehicle)
        restarted_ns = time.time_ns()
        p.start()
        stack.wait_alive(timeout=120)
        deadline = time.monotonic() + 60
        while not ((st := await c.states.recv(timeout=10)).link_ok and st.stamp_ns > restarted_ns
                   and st.gripper_holding is not None  # the gripper's telemetry follows the first HEARTBEAT
                   and st.landed_state.value != "unknown"):  # unknown until the first EXTENDED_SYS_STATE
            assert time.monotonic() < deadline, f"the new bridge has no link or no gripper telemetry: {st}"
        assert st.armed and st.landed_state.value == "in_air" and st.mode == "AUTO.LOITER", st
        assert "found PX4 flying in AUTO.LOITER" in st.override and st.gripper_holding, st
        # Nothing moves on its own after the restart.
        await asyncio.sleep(1.0)
        st = await c.states.recv(timeout=10)
        assert st.mode == "AUTO.LOITER" and abs(st.position.z - before.vehicle.position.z) < 0.2, st
        # The operator's commands take the vehicle back: localize the table and place the cup on it. The vehicle
        # holds right above the table, where the held cup hides it from the camera: back off and look around,
        # a step further each time, as an operator would. Where it ends up depends on the grasp: its pad
        # alignment may have turned the vehicle to face the cup from beside the table (yaw 86 deg in one full
        # run), and from two steps back it then saw only a rim of the table, 'no spot ... with 0.08 m
        # clearance (best 0.05 m)', at every yaw of a full circle.
        await c.search_backing_off("placement_localization", "round table", steps=5)
        st = await c.run("place")
        # It flew and released: "placed ..." when its own look afterwards saw the cup at rest, a failure saying it
        # "released ..." when that look missed the cup right below the camera. Either way the hand is empty and
        # the judge rules.
        assert st.state != SkillState.REJECTED and st.outcome.facts.holding is None, (st.message, st.outcome.facts)
        verdict = await c.judge(op="on_surface", object="red cup", surface="round table")
        assert verdict.ok, verdict.message
        await c.ok("land")


async def test_a_slip_in_flight_is_noticed_and_reported(stack):
    """The held cup drops out of the gripper between skills (sim/fault object slip): the executor sees the
    pads lose contact, forgets the cup, and the next skill's status says it slipped (code `slipped`); a place
    is then refused instead of releasing nothing."""
    async with bus_for(stack) as bus:
        c = Client(bus)
        await c.reset(seed=1, target_object="red cup", destination="table")
        await c.takeoff()
        await c.approach("red cup")
        await c.ok("grasp", "red cup")
        await c.ok("up")
        memory = bus.subscribe(KEYS.memory, maxsize=100)
        res = await bus.query(KEYS.sim_fault, {"unit": "object", "type": "slip", "name": "red cup"}, timeout=10)
        assert res["ok"], res
        deadline = time.monotonic() + 30
        while (await memory.recv(timeout=10)).held_object is not None:
            assert time.monotonic() < deadline, "the executor never noticed the slip"
        st = await c.ok("hold")
        assert st.outcome.code.value == "slipped" and "red cup slipped out of the gripper" in st.message, st
        assert st.outcome.held_object is None and (await c.judge(op="held")).held is None
        placed = await c.run("place")
        assert placed.state == SkillState.REJECTED, placed.message
        await c.ok("land")
