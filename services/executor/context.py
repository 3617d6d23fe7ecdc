"""What a running skill may use: vehicle state with a safety monitor, autopilot commands, perception, memory."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from typing import Any

from services.executor.envelope import (
    DepthClearance,
    altitude_problem,
    geofence_problem,
    outside_geofence,
    state_problem,
    wrap,
)
from services.executor.failures import SkillFailed
from services.executor.memory import Memory
from services.executor.settings import ExecutorSettings
from shared.bus import Bus
from shared.errors import BusError
from shared.keys import Keys
from shared.messages import (
    AutopilotCommand,
    AutopilotResult,
    GotoCommand,
    GripperCommand,
    GripperState,
    LocalizeRequest,
    ObjectEstimate,
    OutcomeCode,
    PlacementEstimate,
    Pose,
    Vec3,
    VehicleState,
)

STALE_GRACE_S = 0.25
"""A state that reads stale gets this long for a newer sample before a skill fails on it (`SkillContext.fresh`)."""


class AuthorityLost(SkillFailed):
    """PX4, the pilot or an abort took control while the skill ran: the stack must not fight it (no hold, no
    retry); the task ends with this reason."""

    def __init__(self, message: str) -> None:
        super().__init__(message, OutcomeCode.ABORTED)


class AbortSeen(SkillFailed):
    """The bridge stopped or refused a command because of an abort it obeyed first: the skill ends ABORTED."""

    def __init__(self, message: str) -> None:
        super().__init__(message, OutcomeCode.ABORTED)


class StateTracker:
    """Newest VehicleState with its receive time, and a way to wait for the next one."""

    def __init__(self) -> None:
        self.value: VehicleState | None = None
        self.receive_ns = 0
        self._event = asyncio.Event()

    def update(self, state: VehicleState, receive_ns: int | None = None) -> None:
        self.value = state
        self.receive_ns = receive_ns or time.time_ns()
        ev, self._event = self._event, asyncio.Event()
        ev.set()

    @property
    def age_s(self) -> float:
        return float("inf") if not self.receive_ns else (time.time_ns() - self.receive_ns) / 1e9

    async def next(self, timeout: float) -> bool:
        """Wait for a newer sample; False on timeout."""
        # asyncio.timeout, not wait_for: on 3.11 wait_for can swallow a cancellation (an abort) that races
        # with the event firing, and samples fire at 50 Hz.
        try:
            async with asyncio.timeout(timeout):
                await self._event.wait()
            return True
        except TimeoutError:
            return False


def pose_of(state: VehicleState | None) -> Pose | None:
    return None if state is None else Pose(position=state.position, yaw=state.yaw)


class SkillContext:
    """Shared by all skills; one instance lives as long as the executor."""

    def __init__(self, bus: Bus, settings: ExecutorSettings, memory: Memory, state: StateTracker,
                 clearance: DepthClearance) -> None:
        self.bus = bus
        self.settings = settings
        self.keys = Keys(settings.vehicle_id)
        self.memory = memory
        self.state = state
        self.clearance = clearance
        self.settled_ns = 0  # when the vehicle last arrived somewhere: perception must use a later frame
        self.stop_requested = False  # set by an abort: a skill that missed its cancellation stops at the next check
        self.perceived: list[str] = []  # filled by the running skill, reported in its outcome
        self.estimate: ObjectEstimate | PlacementEstimate | None = None
        self.task_id = ""  # the running skill's task: sent with motion commands so the bridge knows whose they are
        self.override_ns_at_start = 0  # a takeover older than the skill is the bridge's business, not the skill's
        self.overspeed_since_ns = 0

    def reset_outcome(self, task_id: str = "") -> None:
        self.stop_requested = False
        self.perceived = []
        self.estimate = None
        self.task_id = task_id
        st = self.state.value
        self.override_ns_at_start = st.override_ns if st is not None else 0

    # ---- state

    def current(self) -> VehicleState:
        """The newest state, or SkillFailed when it breaks a health rule."""
        if self.stop_requested:
            raise asyncio.CancelledError("aborted")
        problem = state_problem(self.state.value, self.state.age_s, self.settings)
        if problem:
            raise SkillFailed(problem.replace("nothing was moved", "the skill stopped and holds"), OutcomeCode.BLOCKED)
        assert self.state.value is not None
        return self.state.value

    def _monitor(self, st: VehicleState) -> None:
        """Envelope rules checked on every state sample while a skill waits on the vehicle."""
        if st.override and st.override_ns != self.override_ns_at_start and not st.taken_by_abort():
            # (an abort's takeover is this executor's own abort too: it cancels the skill itself)
            raise AuthorityLost(f"the autopilot took control: {st.override}")
        s = self.settings
        if outside_geofence(st.position, s, s.geofence_exit_margin):
            p = st.position
            raise SkillFailed(f"vehicle left the geofence at ({p.x:.2f}, {p.y:.2f}, {p.z:.2f}); holding",
                              OutcomeCode.BLOCKED)
        speed = math.sqrt(st.velocity.x ** 2 + st.velocity.y ** 2 + st.velocity.z ** 2)
        if speed <= s.max_speed + s.overspeed_margin:
            self.overspeed_since_ns = 0
            return
        self.overspeed_since_ns = self.overspeed_since_ns or st.stamp_ns
        if (st.stamp_ns - self.overspeed_since_ns) / 1e9 >= s.overspeed_persist_s:
            raise SkillFailed(f"vehicle speed {speed:.2f} m/s exceeds the limit {s.max_speed:.2f} m/s "
                              f"for {s.overspeed_persist_s:.1f} s; holding", OutcomeCode.BLOCKED)

    async def fresh(self) -> VehicleState:
        """`current()`, except that a state that reads stale gets one short wait for a newer sample first. When
        this process was not scheduled for a while (a loaded machine: seen at load 9 on 2 cores, a place failed
        'state is stale (0.50 s old)' right after releasing its object), the samples that arrived meanwhile are
        still queued behind the wait that timed out; a bridge that really went silent sends none, and the skill
        fails at most STALE_GRACE_S later than the limit."""
        st = self.state.value
        if st is not None and self.state.age_s > self.settings.state_max_age_s and not self.stop_requested:
            await self.state.next(STALE_GRACE_S)
        return self.current()

    async def wait_for(self, pred: Callable[[VehicleState], bool], timeout: float, what: str) -> VehicleState:
        """Wait until `pred(state)`, checking health and the envelope on every sample."""
        deadline = time.monotonic() + timeout
        while True:
            st = await self.fresh()
            self._monitor(st)
            if pred(st):
                return st
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"{what} not reached within {timeout:.1f} s")
            await self.state.next(min(remaining, self.settings.state_max_age_s / 2))

    # ---- autopilot

    async def command(self, cmd: AutopilotCommand, timeout: float | None = None) -> AutopilotResult:
        if self.stop_requested:
            raise asyncio.CancelledError("aborted")
        t = timeout or self.settings.command_timeout_s
        if self.task_id and "task_id" in type(cmd).model_fields and getattr(cmd, "task_id", None) is None:
            cmd = cmd.model_copy(update={"task_id": self.task_id})
        try:
            res = await self.bus.query(self.keys.autopilot_command, cmd, timeout=t)
        except BusError as exc:
            raise SkillFailed(f"autopilot did not take the {cmd.kind} command: {exc}") from exc
        if not res.ok:
            text = f"autopilot refused {cmd.kind}: {res.message or res.ack_name or 'no reason given'}"
            raise AbortSeen(text) if res.aborted else SkillFailed(text)
        return res

    async def goto(self, target: Vec3, yaw: float, speed: float, *, low: float | None = None,
                   what: str = "target", timeout: float | None = None,
                   until: Callable[[VehicleState], bool] | None = None) -> VehicleState:
        """Fly to `target` and wait for arrival (or, with `until`, for whichever of arrival and `until(state)`
        comes first). The envelope is checked first: a violating target raises SkillFailed before any setpoint
        is sent."""
        s = self.settings
        fence = geofence_problem(target, s, what)
        problem = fence or altitude_problem(target.z, s, low, what)
        if problem:
            raise SkillFailed(problem.replace("nothing was moved", "the routine stopped before that leg"),
                              OutcomeCode.OUT_OF_REACH if fence else OutcomeCode.BLOCKED)
        speed = min(speed, s.max_speed)
        start = await self.fresh()
        dist = math.dist(start.position.as_tuple(), target.as_tuple())
        turn = abs(wrap(yaw - start.yaw))
        await self.command(GotoCommand(position=target, yaw=wrap(yaw), max_speed=speed))
        tol, ytol = s.position_tolerance, math.radians(s.yaw_tolerance_deg)

        def arrived(st: VehicleState) -> bool:
            v = st.velocity
            return (math.dist(st.position.as_tuple(), target.as_tuple()) <= tol and abs(wrap(st.yaw - yaw)) <= ytol
                    and math.sqrt(v.x ** 2 + v.y ** 2 + v.z ** 2) <= s.settle_speed)

        budget = timeout or (dist / speed + turn / math.radians(45.0) + s.motion_slack_s)
        done = arrived if until is None else (lambda st: arrived(st) or until(st))
        try:
            return await self.wait_for(done, budget, what)
        finally:
            self.settled_ns = time.time_ns()

    async def gripper(self, action: str) -> None:
        await self.command(GripperCommand(action=action))  # type: ignore[arg-type]
        want = GripperState.CLOSED if action == "close" else GripperState.OPEN
        try:
            await self.wait_for(lambda st: st.gripper == want, self.settings.gripper_timeout_s, f"gripper {action}")
        except TimeoutError as exc:
            raise SkillFailed(f"gripper did not report {want.value} after the {action} command",
                              OutcomeCode.TIMED_OUT) from exc

    # ---- perception

    async def _fresh(self, key: str, query: str, object_size: Vec3 | None, model: type) -> Any:
        """Ask perception about a frame captured after the vehicle last settled: a frame from mid-motion
        (the camera pipeline lags) would show the scene from the wrong place, e.g. report a grasped object
        as gone when the camera just had not arrived yet."""
        after = self.settled_ns
        deadline = time.monotonic() + self.settings.fresh_frame_timeout_s
        while True:
            age = max(0.05, (time.time_ns() - after) / 1e9)
            try:
                request = LocalizeRequest(query=query, object_size=object_size, max_frame_age_s=min(age, 5.0))
                est = await self.bus.query(key, request, timeout=self.settings.localize_timeout_s)
            except BusError as exc:
                raise SkillFailed(f"perception did not answer the localization of {query!r}: {exc}") from exc
            old = est.reason in ("stale_frame", "no_frame") or (est.frame_stamp_ns and est.frame_stamp_ns < after)
            if not old or time.monotonic() > deadline:
                self.estimate = est
                return est
            await asyncio.sleep(0.05)

    async def localize_object(self, query: str) -> ObjectEstimate:
        return await self._fresh(self.keys.localize_object, query, None, ObjectEstimate)

    async def localize_placement(self, query: str, object_size: Vec3 | None) -> PlacementEstimate:
        return await self._fresh(self.keys.localize_placement, query, object_size, PlacementEstimate)

    def note(self, text: str) -> None:
        self.perceived.append(text)
