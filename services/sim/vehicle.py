"""A PX4-like multirotor: mode logic, offboard failsafe, point-mass dynamics in NED, gripper and collisions."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mav

from services.sim.world import World
from shared.frames import GRIPPER_OFFSET_BODY

log = logging.getLogger("aermani.sim.vehicle")

MAIN_POSCTL = mavutil.PX4_CUSTOM_MAIN_MODE_POSCTL
MAIN_AUTO = mavutil.PX4_CUSTOM_MAIN_MODE_AUTO
MAIN_OFFBOARD = mavutil.PX4_CUSTOM_MAIN_MODE_OFFBOARD
SUB_TAKEOFF = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_TAKEOFF
SUB_LOITER = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_LOITER
SUB_LAND = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_LAND
SUB_RTL = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_RTL

MODE_NAMES = {
    (MAIN_POSCTL, 0): "POSCTL",
    (MAIN_OFFBOARD, 0): "OFFBOARD",
    (MAIN_AUTO, SUB_TAKEOFF): "AUTO.TAKEOFF",
    (MAIN_AUTO, SUB_LOITER): "AUTO.LOITER",
    (MAIN_AUTO, SUB_LAND): "AUTO.LAND",
    (MAIN_AUTO, SUB_RTL): "AUTO.RTL",
}

ACCEPTED = mav.MAV_RESULT_ACCEPTED
TEMPORARILY_REJECTED = mav.MAV_RESULT_TEMPORARILY_REJECTED
DENIED = mav.MAV_RESULT_DENIED
UNSUPPORTED = mav.MAV_RESULT_UNSUPPORTED
FAILED = mav.MAV_RESULT_FAILED
FORCE_MAGIC = 21196

GRAVITY = 9.81


def ned_to_enu(p: np.ndarray) -> np.ndarray:
    return np.array([p[1], p[0], -p[2]], dtype=float)


def enu_to_ned(p: np.ndarray) -> np.ndarray:
    return np.array([p[1], p[0], -p[2]], dtype=float)


def yaw_ned_to_enu(yaw: float) -> float:
    return wrap(math.pi / 2 - yaw)


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


@dataclass
class VehicleParams:
    max_speed_h: float = 2.0  # m/s (MPC_XY_VEL_MAX)
    max_speed_up: float = 1.0  # m/s (MPC_Z_VEL_MAX_UP)
    max_speed_down: float = 1.0  # m/s (MPC_Z_VEL_MAX_DN)
    land_speed: float = 0.7  # m/s (MPC_LAND_SPEED)
    accel_h: float = 3.0  # m/s^2
    accel_v: float = 2.0  # m/s^2
    yaw_rate: float = math.radians(90.0)  # rad/s (MPC_YAWRAUTO_MAX)
    takeoff_alt: float = 1.5  # m (MIS_TAKEOFF_ALT)
    offboard_loss_timeout: float = 0.5  # s (COM_OF_LOSS_T)
    failsafe_land_delay: float = 3.0  # s in hold after offboard loss before landing
    disarm_after_land: float = 2.0  # s (COM_DISARM_LAND)
    offboard_stream_min: float = 0.0  # s of setpoints before OFFBOARD is allowed (PX4: one within COM_OF_LOSS_T)
    battery_drain_per_s: float = 0.05  # % per second while armed (~33 min flight)
    kp: float = 1.5  # position gain, 1/s
    rtl_alt: float = 2.0  # m above home (RTL_RETURN_ALT; PX4's 60 m default makes no sense indoors)
    gripper_offset: tuple[float, float, float] = GRIPPER_OFFSET_BODY  # body FLU, metres (settings.mount)


class Vehicle:
    """All state in NED (PX4's local frame, origin at the world origin so ENU = the stack's world frame).

    Timers that concern the link (setpoint stream, offboard loss) use the caller's wall clock `now`; the
    dynamics integrate simulated time `dt`, which runs `speed_factor` times faster than wall time.
    Not thread-safe: the caller holds its lock.
    """

    def __init__(self, world: World, params: VehicleParams | None = None) -> None:
        self.params = params or VehicleParams()
        self.world = world
        self.events: list[tuple[int, str]] = []  # (MAV_SEVERITY, text) for STATUSTEXT, drained by the link
        self.reset(np.zeros(3), 0.0)

    # ------------------------------------------------------------------ state

    def reset(self, p_ned: np.ndarray, yaw_ned: float, world: World | None = None) -> None:
        if world is not None:
            self.world = world
        self.p = np.array(p_ned, dtype=float)
        self.p[2] = 0.0
        self.home = self.p.copy()
        self.v = np.zeros(3)
        self.yaw = wrap(yaw_ned)
        self.armed = False
        self.main_mode, self.sub_mode = MAIN_AUTO, SUB_LOITER
        self.on_ground = True
        self.landing_touch_wall: float | None = None
        self.sp_pos: np.ndarray | None = None
        self.sp_vel: np.ndarray | None = None
        self.sp_yaw: float | None = None
        self.sp_yaw_rate: float | None = None
        self.last_sp_wall: float | None = None
        self.stream_start_wall: float | None = None
        self.failsafe_since: float | None = None
        self.hold_pos = self.p.copy()
        self.hold_yaw = self.yaw
        self.takeoff_target = self.p.copy()
        self.gripper_closed = False
        self.battery = 100.0
        self.sim_time = 0.0
        self.setpoints_received = 0
        self.estimate_valid = True  # PX4's local position estimate (cleared by an injected sensor failure)

    @property
    def mode_name(self) -> str:
        return MODE_NAMES.get((self.main_mode, self.sub_mode), f"UNKNOWN({self.main_mode},{self.sub_mode})")

    @property
    def custom_mode(self) -> int:
        return (self.main_mode << 16) | (self.sub_mode << 24)

    @property
    def landed_state(self) -> int:
        if self.on_ground:
            return mav.MAV_LANDED_STATE_ON_GROUND
        if self.main_mode == MAIN_AUTO and self.sub_mode == SUB_TAKEOFF:
            return mav.MAV_LANDED_STATE_TAKEOFF
        if self.main_mode == MAIN_AUTO and self.sub_mode == SUB_LAND:
            return mav.MAV_LANDED_STATE_LANDING
        return mav.MAV_LANDED_STATE_IN_AIR

    @property
    def battery_voltage(self) -> float:
        return 10.5 + 2.1 * self.battery / 100.0  # 3S pack, 12.6 V full

    def position_enu(self) -> np.ndarray:
        return ned_to_enu(self.p)

    def yaw_enu(self) -> float:
        return yaw_ned_to_enu(self.yaw)

    def gripper_enu(self) -> np.ndarray:
        y = self.yaw_enu()
        gx, gy, gz = self.params.gripper_offset
        c, s = math.cos(y), math.sin(y)
        return self.position_enu() + np.array([c * gx - s * gy, s * gx + c * gy, gz])

    def _event(self, severity: int, text: str) -> None:
        log.info("STATUSTEXT: %s", text)
        self.events.append((severity, text))

    def _set_mode(self, main: int, sub: int = 0) -> None:
        if (main, sub) != (self.main_mode, self.sub_mode):
            self.main_mode, self.sub_mode = main, sub
            if main in (MAIN_POSCTL, MAIN_AUTO) and sub in (0, SUB_LOITER):
                self.hold_pos, self.hold_yaw = self.p.copy(), self.yaw
            if not (main == MAIN_AUTO and sub == SUB_LOITER):
                self.failsafe_since = None

    # ------------------------------------------------------------------ commands

    def arm(self, arm: bool, force: bool = False) -> int:
        """MAV_CMD_COMPONENT_ARM_DISARM as PX4's commander answers it: a refused transition is
        MAV_RESULT_TEMPORARILY_REJECTED with the reason in a STATUSTEXT; param2 = 21196 skips the checks."""
        if arm:
            if self.armed:
                return ACCEPTED
            reason = None if force else self.arming_check()
            if reason is not None:
                self._event(mav.MAV_SEVERITY_CRITICAL, reason)
                return TEMPORARILY_REJECTED
            self.armed = True
            self.landing_touch_wall = None
            self.hold_pos, self.hold_yaw = self.p.copy(), self.yaw
            self._event(mav.MAV_SEVERITY_INFO, "Armed by external command")
            return ACCEPTED
        if not self.armed:
            return ACCEPTED
        if not self.on_ground and not force:
            self._event(mav.MAV_SEVERITY_CRITICAL, "Disarming denied: not landed")
            return TEMPORARILY_REJECTED
        self._disarmed()
        self._event(mav.MAV_SEVERITY_INFO, "Disarmed by external command")
        return ACCEPTED

    def battery_failsafe(self) -> None:
        """The battery dropped to its critical level (an injected battery failure): PX4's low-battery failsafe
        (COM_LOW_BAT_ACT = Return at critical) takes over from whatever mode flies, OFFBOARD included."""
        self.battery = min(self.battery, 8.0)
        self._event(mav.MAV_SEVERITY_CRITICAL, "Critical battery level!")
        if self.armed and not self.on_ground and not (self.main_mode == MAIN_AUTO
                                                      and self.sub_mode in (SUB_RTL, SUB_LAND)):
            self._set_mode(MAIN_AUTO, SUB_RTL)
            self._event(mav.MAV_SEVERITY_CRITICAL, "Failsafe activated: critical battery, returning to launch")

    def _disarmed(self) -> None:
        self.armed = False
        if self.main_mode == MAIN_AUTO and self.sub_mode in (SUB_LAND, SUB_RTL):
            self._set_mode(MAIN_AUTO, SUB_LOITER)  # a finished landing leaves the vehicle in Hold, ready to arm

    def arming_check(self) -> str | None:
        """PX4's preflight/arming checks that this simulator models; None when arming is allowed."""
        if not self.on_ground:
            return "Arming denied: not landed"
        if self.battery < 5.0:
            return "Arming denied: battery critically low"
        if not self.estimate_valid:
            return "Preflight Fail: No valid local position estimate"
        if self.main_mode == MAIN_AUTO and self.sub_mode in (SUB_LAND, SUB_RTL):
            return f"Arming denied: not possible in {self.mode_name}"
        if self.main_mode == MAIN_OFFBOARD and self.last_sp_wall is None:
            return "Arming denied: no offboard setpoints"
        return None

    def set_estimate_valid(self, valid: bool) -> None:
        """A sensor failure (MAV_CMD_INJECT_FAILURE) took the position estimate away, or gave it back. In the
        air, every mode that needs a position fails over to landing, as PX4's failsafe does."""
        if valid == self.estimate_valid:
            return
        self.estimate_valid = valid
        if valid:
            self._event(mav.MAV_SEVERITY_INFO, "Local position estimate valid again")
            return
        self._event(mav.MAV_SEVERITY_CRITICAL, "No valid local position estimate")
        if self.armed and not self.on_ground and not (self.main_mode == MAIN_AUTO and self.sub_mode == SUB_LAND):
            self.hold_pos = self.p.copy()
            self._set_mode(MAIN_AUTO, SUB_LAND)
            self._event(mav.MAV_SEVERITY_CRITICAL, "Failsafe activated: no position estimate, landing")

    def offboard_stream_ok(self, now: float) -> bool:
        return (self.last_sp_wall is not None and self.stream_start_wall is not None
                and now - self.last_sp_wall <= self.params.offboard_loss_timeout
                and now - self.stream_start_wall >= self.params.offboard_stream_min)

    def set_mode(self, main: int, sub: int, now: float) -> int:
        """DO_SET_MODE / SET_MODE; a refused switch is TEMPORARILY_REJECTED, as PX4's commander answers."""
        needs_position = main in (MAIN_OFFBOARD, MAIN_POSCTL) or (
            main == MAIN_AUTO and sub in (SUB_LOITER, SUB_TAKEOFF, SUB_RTL))
        if needs_position and not self.estimate_valid:
            self._event(mav.MAV_SEVERITY_CRITICAL, f"Switching to {MODE_NAMES.get((main, sub), 'this mode')} "
                        "is currently not possible: no valid local position estimate")
            return TEMPORARILY_REJECTED
        if main == MAIN_OFFBOARD:
            if not self.offboard_stream_ok(now):
                self._event(mav.MAV_SEVERITY_WARNING, "Switching to Offboard is currently not available: "
                            "no setpoint stream")
                return TEMPORARILY_REJECTED
            self._set_mode(MAIN_OFFBOARD, 0)
            return ACCEPTED
        if main == MAIN_POSCTL:
            self._set_mode(MAIN_POSCTL, 0)
            return ACCEPTED
        if main == MAIN_AUTO and sub == SUB_LOITER:
            self._set_mode(MAIN_AUTO, SUB_LOITER)
            return ACCEPTED
        if main == MAIN_AUTO and sub == SUB_TAKEOFF:
            return self.takeoff(None)
        if main == MAIN_AUTO and sub == SUB_LAND:
            return self.land()
        if main == MAIN_AUTO and sub == SUB_RTL:
            return self.rtl()
        self._event(mav.MAV_SEVERITY_WARNING, f"Mode {main}.{sub} is not available in this simulator")
        return UNSUPPORTED

    def rtl(self) -> int:
        """AUTO.RTL: climb to rtl_alt above home (or stay higher), fly home, land there."""
        if not self.armed or self.on_ground:
            self._event(mav.MAV_SEVERITY_CRITICAL, "Return mode: not in air, nothing to return")
            return TEMPORARILY_REJECTED
        self._set_mode(MAIN_AUTO, SUB_RTL)
        self._event(mav.MAV_SEVERITY_INFO, "Returning to launch")
        return ACCEPTED

    def takeoff(self, altitude: float | None) -> int:
        if not self.armed:
            self._event(mav.MAV_SEVERITY_CRITICAL, "Takeoff denied: disarmed")
            return DENIED
        # Altitude is relative to home (home AMSL is 0 in this world, so AMSL and relative agree).
        alt = altitude if altitude is not None and math.isfinite(altitude) and altitude > 0 else \
            self.params.takeoff_alt
        self.takeoff_target = np.array([self.p[0], self.p[1], self.home[2] - alt])
        self._set_mode(MAIN_AUTO, SUB_TAKEOFF)
        self._event(mav.MAV_SEVERITY_INFO, f"Takeoff to {alt:.1f} m above home")
        return ACCEPTED

    def land(self) -> int:
        if not self.armed:
            return DENIED
        self.hold_pos = self.p.copy()
        self._set_mode(MAIN_AUTO, SUB_LAND)
        self._event(mav.MAV_SEVERITY_INFO, "Landing at current position")
        return ACCEPTED

    def gripper(self, grab: bool) -> int:
        if grab:
            self.gripper_closed = True
            obj = self.world.try_grab(self.gripper_enu())
            if obj is not None:
                self._event(mav.MAV_SEVERITY_INFO, f"Gripper closed: holding {obj.name}")
            else:
                self._event(mav.MAV_SEVERITY_INFO, "Gripper closed: nothing grasped")
        else:
            self.gripper_closed = False
            obj = self.world.release()
            if obj is not None:
                self._event(mav.MAV_SEVERITY_INFO, f"Gripper opened: {obj.name} dropped onto {obj.support}")
        return ACCEPTED

    def setpoint(self, now: float, pos: np.ndarray | None, vel: np.ndarray | None, yaw: float | None,
                 yaw_rate: float | None) -> None:
        if self.last_sp_wall is None or now - self.last_sp_wall > self.params.offboard_loss_timeout:
            self.stream_start_wall = now
        self.last_sp_wall = now
        self.sp_pos, self.sp_vel, self.sp_yaw, self.sp_yaw_rate = pos, vel, yaw, yaw_rate
        self.setpoints_received += 1

    # ------------------------------------------------------------------ failsafes and dynamics

    def update_modes(self, now: float) -> None:
        """Mode transitions driven by time (wall clock): offboard loss, failsafe land, auto-disarm."""
        p = self.params
        if self.main_mode == MAIN_OFFBOARD and (self.last_sp_wall is None
                                                or now - self.last_sp_wall > p.offboard_loss_timeout):
            self._set_mode(MAIN_AUTO, SUB_LOITER)
            self.failsafe_since = now
            self._event(mav.MAV_SEVERITY_WARNING, "Failsafe: offboard control lost, holding position")
        if self.failsafe_since is not None and now - self.failsafe_since > p.failsafe_land_delay:
            self.failsafe_since = None
            if self.armed:
                self._set_mode(MAIN_AUTO, SUB_LAND)
                self.hold_pos = self.p.copy()
                self._event(mav.MAV_SEVERITY_WARNING, "Failsafe: offboard still lost, landing")
        if self.armed and self.on_ground and self.main_mode == MAIN_AUTO and self.sub_mode == SUB_LAND:
            if self.landing_touch_wall is None:
                self.landing_touch_wall = now
            elif now - self.landing_touch_wall >= p.disarm_after_land:
                self._disarmed()
                self.landing_touch_wall = None
                self._event(mav.MAV_SEVERITY_INFO, "Landing detected, disarmed")

    def step(self, dt: float) -> None:
        """Integrate `dt` seconds of simulated time."""
        if dt <= 0:
            return
        self.sim_time += dt
        p = self.params
        prev_yaw = self.yaw
        if self.armed:
            self.battery = max(0.0, self.battery - p.battery_drain_per_s * dt)
        if not self.armed:
            if self.on_ground:
                self.v[:] = 0.0
            else:  # forced disarm in the air: it falls
                self.v[:2] *= max(0.0, 1.0 - dt)
                self.v[2] += GRAVITY * dt
                self._move(dt)
            self._carry(prev_yaw)
            return

        target, yaw_target, vmax_up, vmax_down = self.hold_pos, self.hold_yaw, p.max_speed_up, p.max_speed_down
        vel_cmd: np.ndarray | None = None
        if self.main_mode == MAIN_OFFBOARD:
            if self.sp_pos is not None:
                target = self.sp_pos
            elif self.sp_vel is not None:
                vel_cmd = self.sp_vel
            yaw_target = self.sp_yaw
        elif self.main_mode == MAIN_AUTO and self.sub_mode == SUB_TAKEOFF:
            target, yaw_target = self.takeoff_target, self.hold_yaw
            if abs(self.p[2] - self.takeoff_target[2]) < 0.05:
                self._set_mode(MAIN_AUTO, SUB_LOITER)
                self._event(mav.MAV_SEVERITY_INFO, "Takeoff complete, holding")
        elif self.main_mode == MAIN_AUTO and self.sub_mode == SUB_LAND:
            target = np.array([self.hold_pos[0], self.hold_pos[1], 1.0])  # below ground: descend to it
            vmax_down = p.land_speed
        elif self.main_mode == MAIN_AUTO and self.sub_mode == SUB_RTL:
            target = self._rtl_target()

        if self.on_ground and vel_cmd is None and target[2] > self.p[2] - 0.05:
            # A target at or below the ground keeps a landed vehicle on the ground (idle spin).
            self.v[:] = 0.0
            self._yaw_step(yaw_target, dt)
            self._carry(prev_yaw)
            return

        if vel_cmd is None:
            vel_cmd = self._position_control(target, vmax_up, vmax_down)
        vel_cmd = np.array(vel_cmd, dtype=float)
        h = np.linalg.norm(vel_cmd[:2])
        if h > p.max_speed_h:
            vel_cmd[:2] *= p.max_speed_h / h
        vel_cmd[2] = min(max(vel_cmd[2], -vmax_up), vmax_down)
        dv = vel_cmd - self.v
        dh = np.linalg.norm(dv[:2])
        if dh > p.accel_h * dt:
            dv[:2] *= p.accel_h * dt / dh
        dv[2] = min(max(dv[2], -p.accel_v * dt), p.accel_v * dt)
        self.v += dv
        if self.main_mode == MAIN_OFFBOARD and self.sp_yaw is None and self.sp_yaw_rate is not None:
            rate = min(max(self.sp_yaw_rate, -p.yaw_rate), p.yaw_rate)
            self.yaw = wrap(self.yaw + rate * dt)
        else:
            self._yaw_step(yaw_target, dt)
        self._move(dt)
        self._carry(prev_yaw)

    def _rtl_target(self) -> np.ndarray:
        z_rtl = min(self.p[2], self.home[2] - self.params.rtl_alt)  # NED: never descend on the way home
        if self.p[2] > z_rtl + 0.1:  # climb first
            return np.array([self.p[0], self.p[1], z_rtl])
        if math.hypot(self.p[0] - self.home[0], self.p[1] - self.home[1]) > 0.1:
            return np.array([self.home[0], self.home[1], z_rtl])
        self.hold_pos = np.array([self.home[0], self.home[1], self.p[2]])
        self._set_mode(MAIN_AUTO, SUB_LAND)
        self._event(mav.MAV_SEVERITY_INFO, "RTL: home reached, landing")
        return np.array([self.home[0], self.home[1], 1.0])

    def _position_control(self, target: np.ndarray, vmax_up: float, vmax_down: float) -> np.ndarray:
        p = self.params
        err = np.asarray(target, dtype=float) - self.p
        out = np.zeros(3)
        d = float(np.linalg.norm(err[:2]))
        if d > 1e-6:
            # sqrt profile: the speed from which the acceleration limit can still stop at the target.
            speed = min(p.max_speed_h, p.kp * d, math.sqrt(2 * p.accel_h * d) * 0.9)
            out[:2] = err[:2] / d * speed
        dz = float(err[2])
        vz = math.copysign(min(abs(dz) * p.kp, math.sqrt(2 * p.accel_v * abs(dz)) * 0.9), dz)
        out[2] = min(max(vz, -vmax_up), vmax_down)
        return out

    def _yaw_step(self, yaw_target: float | None, dt: float) -> None:
        if yaw_target is None or not math.isfinite(yaw_target):
            return
        err = wrap(yaw_target - self.yaw)
        step = self.params.yaw_rate * dt
        self.yaw = wrap(self.yaw + min(max(err, -step), step))

    def _move(self, dt: float) -> None:
        """Advance the position axis by axis; an axis whose motion would hit furniture or a wall stops."""
        new = self.p + self.v * dt
        if new[2] >= 0.0:  # ground contact
            new[2] = 0.0
            if self.v[2] > 0:
                self.v[2] = 0.0
            self.v[:2] = 0.0 if self.on_ground or not self.armed else self.v[:2]
        cur = self.p.copy()
        blocked_down = False
        before = set(self.world.vehicle_contacts(ned_to_enu(cur)))
        for i in range(3):
            cand = cur.copy()
            cand[i] = new[i]
            hits = set(self.world.vehicle_contacts(ned_to_enu(cand))) - before
            if hits:
                for h in sorted(hits):
                    if f"vehicle-{h}" not in self.world.collisions:
                        self._event(mav.MAV_SEVERITY_CRITICAL, f"Collision with {h}")
                        self.world.record_collision(h)
                blocked_down = blocked_down or (i == 2 and self.v[2] > 0)
                self.v[i] = 0.0
            else:
                cur = cand
        self.p = cur
        was = self.on_ground
        # Sitting on top of furniture counts as landed too (PX4's land detector sees no descent).
        self.on_ground = (self.p[2] >= -0.01 or blocked_down) and self.v[2] >= -1e-6 and (
            not self.armed or not self._climbing())
        if was and not self.on_ground:
            self.landing_touch_wall = None

    def _climbing(self) -> bool:
        if self.main_mode == MAIN_AUTO and self.sub_mode == SUB_TAKEOFF:
            return True
        return self.main_mode == MAIN_OFFBOARD and (
            (self.sp_pos is not None and self.sp_pos[2] < self.p[2] - 0.05)
            or (self.sp_vel is not None and self.sp_vel[2] < 0))

    def _carry(self, prev_yaw: float) -> None:
        obj = self.world.attached()
        if obj is not None:
            self.world.carry(self.gripper_enu(), -wrap(self.yaw - prev_yaw))
