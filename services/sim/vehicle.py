"""A PX4-like multirotor: mode logic, offboard failsafe, the cascaded controller (position -> velocity ->
thrust vector at the caller's rate; attitude -> body rate -> mixer at the physics rate, services.sim.multirotor)
that flies the four-rotor body of the MuJoCo world (services.sim.physics), the gripper, crashes, the disturbances
of the realism level (services.sim.disturbances) and the estimated pose (truth plus a VIO-like error)."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mav

from services.sim.disturbances import PoseEstimator, Wind, downwash_force, ground_effect
from services.sim.multirotor import AttitudeRateController, InnerGains, Mixer, attitude_setpoint
from services.sim.physics import (
    FINGER_MAX_HALF,
    ROTOR_ARM,
    ROTOR_MAX_THRUST,
    ROTOR_RADIUS,
    ROTOR_SPIN,
    ROTOR_XY,
    ROTOR_YAW_MOMENT,
    TIMESTEP,
    VEHICLE_YAW_INERTIA,
    World,
)
from shared.frames import GRIPPER_OFFSET_BODY

log = logging.getLogger("aermani.sim.vehicle")

MAIN_POSCTL = mavutil.PX4_CUSTOM_MAIN_MODE_POSCTL
MAIN_AUTO = mavutil.PX4_CUSTOM_MAIN_MODE_AUTO
MAIN_OFFBOARD = mavutil.PX4_CUSTOM_MAIN_MODE_OFFBOARD
SUB_TAKEOFF = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_TAKEOFF
SUB_LOITER = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_LOITER
SUB_LAND = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_LAND
SUB_RTL = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_RTL

# COM_OBL_RC_ACT -> what PX4 flies. Position, Altitude and Manual need RC sticks; without RC (none in this
# simulator) PX4's failsafe falls back to Hold.
OFFBOARD_LOSS_ACTIONS = {0: "Hold", 1: "Hold", 2: "Hold", 3: "Return", 4: "Land", 5: "Hold", 6: "Terminate",
                         7: "Disarm"}

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
REALISM = ("realistic", "ideal", "harsh")
VEHICLE_YAW_INERTIA_TOTAL = VEHICLE_YAW_INERTIA + 0.01  # the kinematic body's, + finger armature/mass
KINEMATIC_YAW_ACCEL = 6.0  # rad/s^2: the kinematic body's yaw braking profile (its torque is unlimited)
# The multirotor's loop rates in physics steps (TIMESTEP 2 ms), as PX4 runs its modules: the rate loop and the
# mixer every step (500 Hz; PX4: at the gyro rate, 400 Hz-1 kHz), attitude every second (250 Hz, PX4's
# mc_att_control), position and velocity with the estimator and the disturbances every tenth (50 Hz: PX4's
# mc_pos_control follows the estimator's local position at about that rate).
ATTITUDE_DIV = 2
OUTER_DIV = 10
OUTER_DT = OUTER_DIV * TIMESTEP
ROTOR_SPACING = math.dist(ROTOR_XY[0], ROTOR_XY[2])  # adjacent rotors (front right, front left)
# PX4's multicopter land detector (src/modules/land_detector/MulticopterLandDetector.cpp), for a landing on
# something other than the gear (a held object reaches the floor first): three stages, each of which needs its
# condition to hold without a break for a third of LNDMC_TRIG_TIME (PX4's hysteresis restarts on any sample that
# breaks it). Ground contact: a descent commanded (AUTO.LAND), no vertical movement (|vz| at most
# min(0.45 x MPC_LAND_SPEED, LNDMC_Z_VEL_MAX)), no horizontal movement, low thrust. Maybe landed: ground contact
# and no rotation. Landed: maybe landed. Once landed (motors at idle), PX4 keeps the state until a climb is asked
# for or the vehicle moves vertically faster than LNDMC_Z_VEL_MAX, widened 2.5 times for the first 2 s
# (LAND_DETECTOR_LAND_PHASE_TIME_US): the settling of a vehicle that came down on something is not a take-off.
LNDMC_TRIG_TIME = 1.0  # s, the three stages together
LAND_PHASE_S = 2.0  # s after landing with the widened vertical threshold
LNDMC_Z_VEL_MAX = 0.25  # m/s
LNDMC_XY_VEL_MAX = 1.5  # m/s
LNDMC_ROT_MAX = math.radians(20.0)  # rad/s, roll and pitch rates
# Low thrust, as a fraction of the hover thrust: PX4 (with its hover thrust estimate, MPC_USE_HTE) takes 60 % of the
# range from MPC_THR_MIN (0.12) to the hover thrust (0.5 by default): 0.35 of full thrust, 0.70 of the hover thrust.
# PX4's maybe-landed stage also asks for the minimal thrust (10 % of that range), which its velocity integral
# reaches by winding down to MPC_THR_MIN; this simulator's integral is bounded (the thrust of a blocked descent
# settles near half the hover thrust), so that check is left out.
LAND_LOW_THRUST = 0.7


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
    """Flight limits of the simulated multicopter, named after the PX4 parameters they mirror, and its
    disturbances (all zero by default: `ideal`; `realism_params` sets them per realism level)."""

    max_speed_h: float = 2.0  # m/s (MPC_XY_VEL_MAX)
    max_speed_up: float = 1.0  # m/s (MPC_Z_VEL_MAX_UP)
    max_speed_down: float = 1.0  # m/s (MPC_Z_VEL_MAX_DN)
    land_speed: float = 0.7  # m/s (MPC_LAND_SPEED)
    accel_h: float = 3.0  # m/s^2
    accel_v: float = 2.0  # m/s^2
    yaw_rate: float = math.radians(90.0)  # rad/s (MPC_YAWRAUTO_MAX)
    yaw_accel: float = 3.0  # rad/s^2: the yaw rate's braking profile (the rotors' yaw torque is small)
    takeoff_alt: float = 1.5  # m (MIS_TAKEOFF_ALT)
    offboard_loss_timeout: float = 0.5  # s (COM_OF_LOSS_T)
    # What PX4 flies when offboard is lost (COM_OBL_RC_ACT): 0 Position, 1 Altitude, 2 Manual (no RC here, so
    # PX4 falls back to Hold), 3 Return, 4 Land, 5 Hold, 6 Terminate, 7 Disarm. Hold by default: landing in
    # place puts a held object down on whatever furniture is below (issue 31).
    offboard_loss_action: int = 5
    failsafe_land_delay: float = 3.0  # s (COM_FAIL_ACT_T): hold after a failsafe before an action beyond Hold
    disarm_after_land: float = 2.0  # s (COM_DISARM_LAND)
    offboard_stream_min: float = 0.0  # s of setpoints before OFFBOARD is allowed (PX4: one within COM_OF_LOSS_T)
    battery_drain_per_s: float = 0.05  # % per second while armed (~33 min flight)
    kp: float = 1.5  # position gain, 1/s (MPC_XY_P 0.95, MPC_Z_P 1.0; a little stiffer indoors)
    rtl_alt: float = 2.0  # m above home (RTL_RETURN_ALT; PX4's 60 m default makes no sense indoors)
    vel_tau: float = 0.3  # s, horizontal velocity loop time constant: accel = velocity error / tau (MPC_XY_VEL_P_ACC)
    vel_tau_z: float = 0.15  # s, the same vertically (no tilt to wait for: only the motors' lag)
    vel_ki: float = 2.0  # 1/s^2, horizontal velocity loop integral (a steady draft)
    vel_ki_z: float = 4.0  # 1/s^2, vertical (a payload's weight)
    # The kinematic body's velocity loop (a force straight on the body, no attitude to wait for: stiffer).
    kinematic_vel_tau: float = 0.12  # s (force = mass * velocity error / tau + integral)
    kinematic_vel_ki: float = 4.0  # 1/s^2 (carries a payload without sagging)
    max_thrust_accel: float = 2.2 * GRAVITY  # m/s^2: the kinematic body's thrust-to-weight
    jerk_max: float = 20.0  # m/s^3, horizontal (MPC_JERK_MAX)
    max_tilt_accel: float = 6.0  # m/s^2: horizontal acceleration the tilt limit allows (MPC_TILTMAX_AIR ~35 deg)
    inner: InnerGains = field(default_factory=InnerGains)
    # Disturbances (README "Realism": figures and sources).
    pose_bias_xy: float = 0.0  # m, sigma of the estimate's wandering horizontal bias (per axis)
    pose_bias_z: float = 0.0  # m, the same vertically
    pose_bias_tau: float = 10.0  # s, its correlation time
    pose_noise: float = 0.0  # m, white noise on the kinematic body's estimated position
    pose_drift: float = 0.0  # m/sqrt(s): random walk of the estimate's horizontal bias (visual odometry drift)
    pose_drift_max: float = 0.0  # m: the bias is bounded (loop closures / fused references)
    yaw_drift: float = 0.0  # rad/sqrt(s): random walk of the estimated yaw's bias
    yaw_drift_max: float = 0.0  # rad
    # m, ENU (x, y): where the vehicle settles relative to an OFFBOARD position setpoint, an error its own
    # estimate shows (wind, a mistrimmed controller); tests use it to make closed-loop skills correct
    hover_offset: tuple[float, float] = (0.0, 0.0)
    hover_wander: float = 0.0  # m: the settling point also circles the setpoint with this radius (gusts) ...
    hover_wander_period: float = 2.0  # s: ... once per this many seconds of simulated time
    # m, ENU (x, y): a step in the estimate (estimate - truth) on top of the drift: a relocalization jump, which
    # nothing on board sees (the camera's tf carries the same estimate); tests use it to send a release astray
    estimate_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    vio_noise: float = 0.0  # m, white noise on the multirotor's estimated position
    vel_noise: float = 0.0  # m/s, white noise on the multirotor's estimated velocity
    yaw_bias: float = 0.0  # rad, sigma of the estimated yaw's wandering bias
    yaw_bias_tau: float = 30.0  # s
    wind_mean: float = 0.0  # m/s, a steady draft in a seeded direction
    wind_sigma: float = 0.0  # m/s, horizontal turbulence (vertical: half)
    wind_tau: float = 1.5  # s, turbulence correlation time (small rooms: short scales)
    gust_rate: float = 0.0  # gusts per second
    gust_amp: tuple[float, float] = (0.0, 0.0)  # m/s, peak air speed of a gust, uniform in this range
    gust_s: tuple[float, float] = (1.0, 3.0)  # s, length of a gust
    rotor_drag: float = 0.0  # 1/s: horizontal drag force / (mass * air-relative speed) (rotor drag, linear)
    thrust_noise: float = 0.0  # relative sigma of each rotor's thrust (Gauss-Markov, thrust_noise_tau)
    thrust_noise_tau: float = 0.05  # s
    ground_effect: bool = False  # thrust gain near a surface under a rotor
    downwash: bool = False  # the rotors' slipstream pushes objects below them
    seed: int = 0


def realism_params(realism: str, **kw) -> VehicleParams:
    """The estimator and disturbances of a realism level, for either body (SimSettings.dynamics): each reads its
    own fields (the kinematic body `pose_noise` and the `pose_drift`/`yaw_drift` random walks; the multirotor the
    rest), so the same parameters serve a world of either dynamics.

    `ideal`: no disturbances, the estimate is the truth. `realistic`, kinematic body: a VIO-grade estimate (2 mm
    noise, bias drifting ~1 cm/min up to 3 cm, yaw up to 1 deg), nothing else. `realistic`, multirotor: an indoor
    VIO-grade estimate (bias sigma 2.5 cm horizontal, 3.1 cm vertical, wandering over ~10 s; 3 mm and 1 cm/s
    noise; yaw bias sigma 0.5 deg), indoor air (a 0.15 m/s draft, 0.25 m/s turbulence, a 0.5-1 m/s gust every
    ~30 s), rotor drag, 2 % thrust noise, ground effect, downwash; calibrated so a still hover's true position
    error is sigma 2-5 cm per axis (README "Dynamics"). `harsh`: the kinematic body as `realistic`; the
    multirotor with a worse estimate and stronger air, for stress tests."""
    if realism not in REALISM:
        raise ValueError(f"unknown realism {realism!r}: {', '.join(REALISM)}")
    if realism == "ideal":
        return VehicleParams(**kw)
    kinematic: dict = {"pose_noise": 0.002, "pose_drift": 0.0015, "pose_drift_max": 0.03, "yaw_drift": 0.0005,
                       "yaw_drift_max": math.radians(1.0)}
    common: dict = {**kinematic, "rotor_drag": 0.4, "ground_effect": True, "downwash": True,
                    "thrust_noise_tau": 0.05}
    if realism == "realistic":
        return VehicleParams(**common, pose_bias_xy=0.025, pose_bias_z=0.031, pose_bias_tau=10.0, vio_noise=0.003,
                             vel_noise=0.01, yaw_bias=math.radians(0.5), yaw_bias_tau=30.0, wind_mean=0.15,
                             wind_sigma=0.25, wind_tau=1.5, gust_rate=1 / 30, gust_amp=(0.5, 1.0),
                             gust_s=(1.0, 3.0), thrust_noise=0.02, **kw)
    return VehicleParams(**common, pose_bias_xy=0.06, pose_bias_z=0.04, pose_bias_tau=20.0, vio_noise=0.008,
                         vel_noise=0.03, yaw_bias=math.radians(2.0), yaw_bias_tau=30.0, wind_mean=0.5,
                         wind_sigma=0.7, wind_tau=1.0, gust_rate=1 / 8, gust_amp=(1.5, 3.0), gust_s=(0.8, 2.5),
                         thrust_noise=0.05, **kw)


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
        p0 = np.array(p_ned, dtype=float)
        p0[2] = 0.0
        self.world.set_vehicle(ned_to_enu(p0), yaw_ned_to_enu(wrap(yaw_ned)))
        self._init_disturbances()
        self.v_int = np.zeros(3)
        self.attitude = AttitudeRateController(self.world.vehicle_inertia, self.params.inner)
        self.mixer = Mixer(ROTOR_XY, ROTOR_SPIN, ROTOR_YAW_MOMENT, ROTOR_MAX_THRUST)
        self._force = (0.0, 0.0, 0.0)  # thrust vector the position loop asks for (world ENU, N)
        self._z_sp = (0.0, 0.0, 1.0)
        self._h_force_max = math.inf
        self._yaw_rate_sp = 0.0  # ENU, rad/s
        self._a_sp = np.zeros(3)
        self._yaw_accel_ff = 0.0
        self._downwashed: set[int] = set()
        self._running = self._flying = False  # the loops run (armed) / the rotors fly (not idling on the ground)
        self._tick = 0  # physics steps since the loops started
        self._qpos, self._qvel = self.world.data.qpos, self.world.data.qvel  # views (the hot loop reads them)
        self._objects = self.world.objects
        self._object_bodies = np.array([self.world.obj_body[e.name] for e in self._objects], dtype=int)
        self._largest_object_radius = max((max(e.size[0], e.size[1]) / 2 for e in self._objects), default=0.0)
        self.crashed = False
        self._read_state()
        self.home = self.p.copy()
        self.armed = False
        self.main_mode, self.sub_mode = MAIN_AUTO, SUB_LOITER
        self.on_ground = True
        self.landing_touch_wall: float | None = None
        self._thrust_z = 0.0  # N, the vertical thrust the controller asks for (the land detector's "throttle")
        self._land_stages = [0.0, 0.0, 0.0]  # s each stage's condition has held: ground contact, maybe, landed
        self._landed_at: float | None = None  # simulated time the land detector declared the landing (latched)
        self._incidents_seen = 0  # the world's incidents already announced
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
        self.held_name: str | None = None
        self.battery = 100.0
        self.sim_time = 0.0
        self.setpoints_received = 0
        self.estimate_valid = True  # PX4's local position estimate (cleared by an injected sensor failure)

    @property
    def max_step_s(self) -> float:
        """The longest `step` the controller flies well: the kinematic body's controller runs once per `step`
        (10 ms at most); the multirotor's loops run inside the physics steps at their own rates, so a `step`
        only bounds how often the land detector, the gripper's and the crash checks look (20 ms)."""
        return 0.02 if self.world.multirotor else 0.01

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
        """Gripper point from the estimated pose (what the autopilot believes)."""
        y = self.yaw_enu()
        gx, gy, gz = GRIPPER_OFFSET_BODY
        c, s = math.cos(y), math.sin(y)
        return self.position_enu() + np.array([c * gx - s * gy, s * gx + c * gy, gz])

    def true_position_enu(self) -> np.ndarray:
        return self.world.vehicle_position()

    def true_yaw_enu(self) -> float:
        return wrap(self.world.vehicle_yaw())

    @property
    def finger_width(self) -> float:
        return self.world.finger_width()

    @property
    def holding(self) -> bool:
        """Both finger pads touch the same object (the gripper's contact sensing)."""
        return self.world.holding() is not None

    def _init_disturbances(self) -> None:
        """One generator per disturbance, all from the seed: a change in one model leaves the others' draws
        (and so the other figures) as they were."""
        p = self.params
        # The kinematic body keeps its own estimator (a bounded random walk, `_drift`) and draws.
        self.drift_bias = np.zeros(3)  # NED, estimate - truth (kinematic)
        self.yaw_drift_bias = 0.0
        seeds = np.random.SeedSequence(p.seed).spawn(4)
        est_rng = np.random.default_rng(seeds[0])
        self.rng = est_rng if self.world.multirotor else np.random.default_rng(p.seed)
        self.estimator = PoseEstimator(est_rng, p.pose_bias_xy, p.pose_bias_z, p.pose_bias_tau, p.vio_noise,
                                       p.vel_noise, p.yaw_bias, p.yaw_bias_tau)
        self.wind = Wind(np.random.default_rng(seeds[1]), p.wind_mean, p.wind_sigma, p.wind_sigma / 2, p.wind_tau,
                         p.gust_rate, p.gust_amp, p.gust_s)
        self.wind_now = np.zeros(3)
        self._thrust_rng = np.random.default_rng(seeds[2])
        self.thrust_error = np.zeros(len(ROTOR_XY))

    @property
    def bias(self) -> np.ndarray:
        """Estimated minus true position (NED), the estimator's slowly wandering part."""
        return self.estimator.bias.x if self.world.multirotor else self.drift_bias

    def _read_state(self) -> None:
        """Estimated state = MuJoCo's truth + the estimator's error; attitude and rates are the IMU's (truth)."""
        w = self.world
        est = self.estimator
        self.p_true = enu_to_ned(w.vehicle_position())
        if not w.multirotor:
            # The kinematic body: MAIN's estimator (a bounded random-walk bias plus noise), level attitude.
            noise = self.rng.normal(0.0, self.params.pose_noise, 3) if self.params.pose_noise > 0 else 0.0
            self.p = self.p_true + self.drift_bias + noise
            self.v = enu_to_ned(w.vehicle_velocity())
            self.yaw = wrap(yaw_ned_to_enu(w.vehicle_yaw()) + self.yaw_drift_bias)
            self.roll = self.pitch = 0.0
            self.yaw_rate = -w.vehicle_yaw_rate()
            self.rates = (0.0, 0.0, self.yaw_rate)
        else:
            self.p = self.p_true + est.position_error()
            self.v = enu_to_ned(w.vehicle_velocity()) + est.velocity_error()
            roll, pitch, yaw_enu = w.vehicle_rpy()
            # MAVLink's FRD body in NED: roll keeps its sign, pitch (nose up positive) and yaw flip.
            self.roll, self.pitch = roll, -pitch
            self.yaw = wrap(yaw_ned_to_enu(yaw_enu) + est.yaw_error)  # ENU<->NED yaw map is its own inverse
            p, q, r = w.vehicle_rates()
            self.rates = (p, -q, -r)  # FRD
            self.yaw_rate = -w.vehicle_yaw_rate()
        ox, oy, oz = self.params.estimate_offset
        if ox or oy or oz:
            self.p = self.p + enu_to_ned(np.array([ox, oy, oz]))

    def attitude_quaternion(self) -> tuple[float, float, float, float]:
        """(w, x, y, z) of the FRD body in NED from the reported roll, pitch and (estimated) yaw."""
        cr, sr = math.cos(self.roll / 2), math.sin(self.roll / 2)
        cp, sp = math.cos(self.pitch / 2), math.sin(self.pitch / 2)
        cy, sy = math.cos(self.yaw / 2), math.sin(self.yaw / 2)
        return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
                cr * cp * sy - sr * sp * cy)

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
            self.failsafe_since = None  # commanded Hold during a failsafe's hold delay: the action is called off
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
        """Close (grab) or open (release) the fingers; what is held follows from the contacts."""
        self.gripper_closed = grab
        self.world.set_fingers(0.0 if grab else FINGER_MAX_HALF)
        self._event(mav.MAV_SEVERITY_INFO, "Gripper closing" if grab else "Gripper opening")
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
        """Mode transitions driven by time (wall clock): offboard loss, its failsafe action, auto-disarm."""
        p = self.params
        if self.main_mode == MAIN_OFFBOARD and (self.last_sp_wall is None
                                                or now - self.last_sp_wall > p.offboard_loss_timeout):
            # PX4 holds first; an action beyond Hold follows after COM_FAIL_ACT_T unless someone commands the
            # vehicle meanwhile (any mode switch clears failsafe_since). Hold itself lasts until then.
            self._set_mode(MAIN_AUTO, SUB_LOITER)
            action = OFFBOARD_LOSS_ACTIONS.get(int(p.offboard_loss_action), "Hold")
            self.failsafe_since = None if action == "Hold" else now
            then = "" if action == "Hold" else f", {action.lower()} in {p.failsafe_land_delay:g} s"
            self._event(mav.MAV_SEVERITY_WARNING, f"Failsafe: offboard lost, holding{then}")
        if self.failsafe_since is not None and now - self.failsafe_since > p.failsafe_land_delay:
            self.failsafe_since = None
            if self.armed and not self.on_ground:
                self._offboard_loss_action()
        if self.armed and self.on_ground and self.main_mode == MAIN_AUTO and self.sub_mode == SUB_LAND:
            if self.landing_touch_wall is None:
                self.landing_touch_wall = now
            elif now - self.landing_touch_wall >= p.disarm_after_land:
                self._disarmed()
                self.landing_touch_wall = None
                self._event(mav.MAV_SEVERITY_INFO, "Landing detected, disarmed")

    def _offboard_loss_action(self) -> None:
        """The action of COM_OBL_RC_ACT beyond Hold, once the failsafe's hold delay ran out."""
        action = OFFBOARD_LOSS_ACTIONS.get(int(self.params.offboard_loss_action), "Hold")
        if action == "Land":
            self.hold_pos = self.p.copy()
            self._set_mode(MAIN_AUTO, SUB_LAND)
            self._event(mav.MAV_SEVERITY_WARNING, "Failsafe: offboard still lost, landing")
        elif action == "Return":
            self._set_mode(MAIN_AUTO, SUB_RTL)
            self._event(mav.MAV_SEVERITY_WARNING, "Failsafe: offboard still lost, returning to launch")
        elif action in ("Terminate", "Disarm"):
            self.armed = False  # motors off in the air: the vehicle falls
            self._event(mav.MAV_SEVERITY_EMERGENCY, f"Failsafe: offboard still lost, {action.lower()}")

    def step(self, dt: float) -> None:
        """Run the controller once and advance the physics `dt` seconds of simulated time."""
        if dt <= 0:
            return
        self.sim_time += dt
        p = self.params
        if self.armed:
            self.battery = max(0.0, self.battery - p.battery_drain_per_s * dt)
        if self.world.multirotor:
            if self.armed and not self.crashed:
                if not self._running:  # just armed: the outer loop runs in the first physics step
                    self._running, self._tick = True, 0
                contacts = self.world.step(dt, self._physics_tick)
            else:
                if self._running:
                    self._running = self._flying = False
                    self.world.set_rotor_commands([0.0] * len(ROTOR_XY))
                    self.attitude.reset()
                self._disturb(dt)  # the air and the estimator go on while the motors are off
                contacts = self.world.step(dt)
        else:
            self._drift(dt)
            force, torque = np.zeros(3), 0.0
            if self.armed and not self.crashed:
                force, torque = self._kinematic_control(dt)
            self.world.apply_vehicle_force(force, torque)
            self._thrust_z = float(force[2])
            contacts = self.world.step(dt)
        for c in contacts:
            if c.crash and self.armed:
                self.crashed = True
                self.armed = False
                self._event(mav.MAV_SEVERITY_EMERGENCY,
                            f"Crash: hit the {c.name} at {c.speed:.1f} m/s, motors stopped")
            else:
                self._event(mav.MAV_SEVERITY_CRITICAL, f"Collision with {c.name} at {c.speed:.2f} m/s")
        self._announce_incidents()
        self._read_state()
        held = self.world.holding()
        name = held.name if held is not None else None
        if name != self.held_name:
            if name is not None:
                self._event(mav.MAV_SEVERITY_INFO, f"Gripper: holding {name} (width {self.finger_width:.3f} m)")
            else:
                self._event(mav.MAV_SEVERITY_INFO, f"Gripper: no longer holding {self.held_name}")
            self.held_name = name
        was = self.on_ground
        # Landed: PX4's land detector (whatever touched down first: the gear, or a payload hanging below the
        # gripper), or resting on the gear or the floor, or on anything at all once the motors are off and it no
        # longer moves.
        resting = (self.world.gear_on_something() or self.world.vehicle_position()[2] < 0.003
                   or (not self.armed and abs(self.v[2]) < 0.05))
        self.on_ground = self._land_detected(dt) or resting and abs(self.v[2]) < 0.15 and (
            not self.armed or not self._climbing())
        if was and not self.on_ground:
            self.landing_touch_wall = None

    def _announce_incidents(self) -> None:
        """STATUSTEXT for the world's new gripper strikes, knocked and dropped objects (the airframe's contacts
        have theirs above)."""
        texts = {"gripper": "Gripper struck the {thing} ({detail})", "knocked": "Knocked over the {thing} ({detail})",
                 "dropped": "Dropped the {thing} ({detail})"}
        new = self.world.incidents[self._incidents_seen:]
        self._incidents_seen += len(new)
        for i in new:
            if i.kind in texts:
                self._event(mav.MAV_SEVERITY_WARNING, texts[i.kind].format(thing=i.thing, detail=i.detail))

    def _land_detected(self, dt: float) -> bool:
        """PX4's multicopter land detector in AUTO.LAND (LNDMC_* above): commanded down, not moving and at low
        thrust means ground contact, whatever touches (the gear, or a payload hanging below the gripper that reached
        the floor first, slipping a little in the pads); maybe landed, then landed, each after a third of
        LNDMC_TRIG_TIME without a break."""
        p = self.params
        s = self._land_stages
        if self._landed_at is not None:
            widened = 2.5 if self.sim_time - self._landed_at < LAND_PHASE_S else 1.0
            if self.armed and not self._climbing() and abs(self.v[2]) <= widened * LNDMC_Z_VEL_MAX:
                return True
            self._landed_at = None
            s[:] = [0.0, 0.0, 0.0]
        landing = self.main_mode == MAIN_AUTO and self.sub_mode == SUB_LAND
        thrust = self._thrust_z if (self._flying or not self.world.multirotor) else 0.0
        contact = (landing and abs(self.v[2]) <= min(0.45 * p.land_speed, LNDMC_Z_VEL_MAX)
                   and math.hypot(self.v[0], self.v[1]) <= LNDMC_XY_VEL_MAX
                   and thrust <= LAND_LOW_THRUST * self.world.vehicle_mass * GRAVITY)
        still = math.hypot(self.rates[0], self.rates[1]) <= LNDMC_ROT_MAX
        stage = LNDMC_TRIG_TIME / 3
        s[0] = s[0] + dt if contact else 0.0
        s[1] = s[1] + dt if s[0] >= stage and still else 0.0
        s[2] = s[2] + dt if s[1] >= stage else 0.0
        if s[2] < stage:
            return False
        self._landed_at = self.sim_time
        return True

    def _disturb(self, dt: float) -> None:
        """Advance the disturbances `dt` and apply them: the estimator's error, wind and rotor drag on the body,
        thrust noise and ground effect on each rotor's gain, the downwash on the objects below."""
        p, w = self.params, self.world
        self.estimator.step(dt)
        if p.wind_sigma > 0 or p.wind_mean > 0 or p.gust_rate > 0:
            self.wind_now = self.wind.step(dt)
        if p.rotor_drag > 0:
            rel = self.wind_now - w.vehicle_velocity()
            k = p.rotor_drag * w.vehicle_mass
            w.apply_vehicle_force(np.array([k * rel[0], k * rel[1], 0.5 * k * rel[2]]))
        if p.thrust_noise > 0:
            a = math.exp(-dt / p.thrust_noise_tau)
            self.thrust_error = a * self.thrust_error + p.thrust_noise * math.sqrt(1 - a * a) * \
                self._thrust_rng.standard_normal(len(self.thrust_error))
        if p.ground_effect or p.thrust_noise > 0:
            ge = [ground_effect(h, ROTOR_RADIUS, ROTOR_SPACING, ROTOR_ARM) for h in w.rotor_clearance()] \
                if p.ground_effect else \
                [1.0] * len(ROTOR_XY)
            w.set_rotor_gains([g * (1.0 + float(e)) for g, e in zip(ge, self.thrust_error, strict=True)])
        if p.downwash:
            self._downwash()

    def _downwash(self) -> None:
        """Each rotor's slipstream on the objects under its disc (services.sim.disturbances.downwash_force)."""
        w = self.world
        d = w.data
        thrusts = w.rotor_thrusts()
        pushed: set[int] = set()
        if max(thrusts) > 0.1:
            rotors = [d.site_xpos[s].tolist() for s in w.rotor_sites]
            # Only objects under the rotor discs' footprint (one vectorised test; most steps none is).
            bodies = self._object_bodies
            reach = ROTOR_ARM + ROTOR_RADIUS + self._largest_object_radius
            dxy = d.xpos[bodies, :2] - d.xpos[w.vehicle_body, :2]
            near = np.flatnonzero((dxy * dxy).sum(axis=1) < reach * reach)
            for k in near.tolist():
                e = self._objects[k]
                b = bodies[k]
                cx, cy, cz = d.xpos[b].tolist()
                top = cz + e.size[2] / 2
                r_obj = max(e.size[0], e.size[1]) / 2
                area = e.size[0] * e.size[1] if e.shape == "box" else math.pi * r_obj * r_obj
                f = 0.0
                for (rx, ry, rz), t in zip(rotors, thrusts, strict=True):
                    f += downwash_force(t, ROTOR_RADIUS, rz - top, math.hypot(cx - rx, cy - ry), r_obj, area)
                if f > 0.02:  # below this it would only wake a sleeping object for nothing
                    d.xfrc_applied[b, 2] = -f
                    pushed.add(b)
        for b in self._downwashed - pushed:
            d.xfrc_applied[b, 2] = 0.0
        self._downwashed = pushed

    def _physics_tick(self) -> None:
        """Before every physics step while armed: the multirotor's loops at their rates (ATTITUDE_DIV,
        OUTER_DIV). The outer loop reads the estimate as it is at that step."""
        tick = self._tick
        self._tick = tick + 1
        if tick % OUTER_DIV == 0:
            self._read_state()
            self._disturb(OUTER_DT)
            flying = self._control(OUTER_DT)
            if not flying and self._flying:
                self.world.set_rotor_commands([0.0] * len(ROTOR_XY))
                self.attitude.reset()
            self._flying = flying
        if self._flying:
            self._inner_loop(tick % ATTITUDE_DIV == 0)

    def _inner_loop(self, attitude: bool) -> None:
        """[`attitude`: the attitude loop, then] body rates -> torques -> mixer, once per physics step (PX4's
        rate loop runs at the IMU rate). The collective is the thrust vector projected on the body's current z
        axis, as PX4's."""
        w = self.world
        q0 = w._q0
        qw, qx, qy, qz = q = tuple(self._qpos[q0 + 3:q0 + 7].tolist())
        fx, fy, fz = self._force
        bzx, bzy = 2 * (qx * qz + qw * qy), 2 * (qy * qz - qw * qx)
        thrust = fx * bzx + fy * bzy + fz * (1 - 2 * (qx * qx + qy * qy))
        # While the tilt lags a setpoint that is coming back up, the collective would push sideways harder than
        # the acceleration limit allows: cap the horizontal part (only ever active at that limit).
        # The motors lag their commands, so an overshoot of the rotors' actual thrust is taken off the command too.
        h = math.sqrt(bzx * bzx + bzy * bzy)
        cap = self._h_force_max
        if thrust * h > 0.9 * cap:
            excess = sum(w.rotor_thrusts()) * h - cap
            thrust = min(thrust, (cap - max(excess, 0.0)) / h)
        att = self.attitude
        if attitude:
            att.attitude(q, self._z_sp, self._yaw_rate_sp)  # type: ignore[arg-type]
        v0 = w._v0
        tx, ty, tz = att.rates(tuple(self._qvel[v0 + 3:v0 + 6].tolist()),  # type: ignore[arg-type]
                               TIMESTEP, self.mixer.saturated, self._yaw_accel_ff * self.params.inner.yaw_accel_ff)
        w.set_rotor_commands(self.mixer.mix(max(thrust, 0.0), tx, ty, tz))

    def _setpoints(self) -> tuple[np.ndarray | None, np.ndarray | None, float | None, float | None, float, float]:
        """What the flight mode asks for on the estimated state: a position target or a velocity command
        (exactly one), a yaw target or a yaw rate command, and the vertical speed limits."""
        p = self.params
        yaw_target: float | None
        target, yaw_target, vmax_up, vmax_down = self.hold_pos, self.hold_yaw, p.max_speed_up, p.max_speed_down
        vel_cmd: np.ndarray | None = None
        yaw_rate_cmd: float | None = None
        if self.main_mode == MAIN_OFFBOARD:
            if self.sp_pos is not None:
                target = self.sp_pos + enu_to_ned(self._hover_error())
            elif self.sp_vel is not None:
                vel_cmd = self.sp_vel
            yaw_target = self.sp_yaw
            if self.sp_yaw is None and self.sp_yaw_rate is not None:
                yaw_rate_cmd = min(max(self.sp_yaw_rate, -p.yaw_rate), p.yaw_rate)
        elif self.main_mode == MAIN_AUTO and self.sub_mode == SUB_TAKEOFF:
            target, yaw_target = self.takeoff_target, self.hold_yaw
            if abs(self.p[2] - self.takeoff_target[2]) < 0.05:
                self._set_mode(MAIN_AUTO, SUB_LOITER)
                self._event(mav.MAV_SEVERITY_INFO, "Takeoff complete, holding")
        elif self.main_mode == MAIN_AUTO and self.sub_mode == SUB_LAND:
            target = np.array([self.hold_pos[0], self.hold_pos[1], self.p[2] + 1.0])  # keep descending
            vmax_down = p.land_speed
        elif self.main_mode == MAIN_AUTO and self.sub_mode == SUB_RTL:
            target = self._rtl_target()
        return (None if vel_cmd is not None else target), vel_cmd, yaw_target, yaw_rate_cmd, vmax_up, vmax_down

    def _idle_on_ground(self, target: np.ndarray | None) -> bool:
        """A target at or below the ground keeps a landed vehicle on the ground (motors at idle)."""
        return self.on_ground and target is not None and target[2] > self.p[2] - 0.05

    def _control(self, dt: float) -> bool:
        """PX4-like outer cascade of the multirotor on the estimated state: position -> velocity setpoint (speed
        and acceleration limits, sqrt braking profile) -> acceleration (P + I on velocity, gravity feed-forward)
        -> thrust vector and attitude setpoint for the inner loop. False when the vehicle idles on the ground."""
        p = self.params
        target, vel_cmd, yaw_target, yaw_rate_cmd, vmax_up, vmax_down = self._setpoints()
        if self._idle_on_ground(target):
            self.v_int[:] = 0.0
            self._a_sp[:] = 0.0
            self._yaw_rate_sp = self._yaw_accel_ff = 0.0
            self._z_sp = (0.0, 0.0, 1.0)
            return False

        if vel_cmd is None:
            assert target is not None
            vel_cmd = self._position_control(target, vmax_up, vmax_down)
        self._velocity_control(np.array(vel_cmd, dtype=float), vmax_up, vmax_down, dt)
        # Yaw: rate-limited towards the target; the rate loop tracks it (ENU rate = - NED rate).
        if yaw_rate_cmd is None:
            yaw_rate_cmd = self._yaw_rate_toward(yaw_target)
        # The yaw rate ramps (PX4's yaw setpoint is acceleration-limited too): a step would saturate the
        # rotors' small yaw torque and overshoot. Near the commanded rate the ramp eases in exponentially
        # (0.1 s): an abrupt end, with the motors' lag behind it, would overshoot the rate limit.
        step = p.yaw_accel * dt
        ease = (-yaw_rate_cmd - self._yaw_rate_sp) * min(1.0, dt / 0.1)
        ramped = self._yaw_rate_sp + min(max(ease, -step), step)
        self._yaw_accel_ff = (ramped - self._yaw_rate_sp) / dt
        self._yaw_rate_sp = ramped
        return True

    def _velocity_control(self, vel_cmd: np.ndarray, vmax_up: float, vmax_down: float, dt: float) -> None:
        """Velocity setpoint (NED) -> acceleration (P + I, PX4's limits) -> thrust vector and tilt setpoint."""
        p = self.params
        h = np.linalg.norm(vel_cmd[:2])
        if h > p.max_speed_h:
            vel_cmd[:2] *= p.max_speed_h / h
        vel_cmd[2] = min(max(vel_cmd[2], -vmax_up), vmax_down)
        # Acceleration limits on the velocity setpoint's change relative to the current velocity.
        dv = vel_cmd - self.v
        a = dv / np.array([p.vel_tau, p.vel_tau, p.vel_tau_z])
        ah = float(np.linalg.norm(a[:2]))
        if ah > p.accel_h:
            a[:2] *= p.accel_h / ah
        clipped_z = abs(a[2]) > p.accel_v
        a[2] = min(max(a[2], -p.accel_v), p.accel_v)
        # Jerk limit on the horizontal acceleration (MPC_JERK_MAX): the tilt follows a ramp without overshooting
        # the acceleration limit.
        jump = p.jerk_max * dt
        a[:2] = np.clip(a[:2], self._a_sp[:2] - jump, self._a_sp[:2] + jump)
        self._a_sp = a.copy()
        # The integral carries a payload's weight and leans into a steady draft. Horizontally it integrates only
        # near the setpoint (conditional integration): a manoeuvre's large errors would wind it up and break
        # the acceleration limit.
        # Vertically it integrates unless the acceleration is clipped at its limit (anti-windup: a climb's first
        # jump does not wind it up), and always while a climb or descent is stalled (asked to move, not moving:
        # a load the gravity feed-forward does not know holds it, e.g. a payload heavier than the acceleration
        # limit's share of the thrust) or while it unwinds. So any steady error, however small, is taken up:
        # a condition tied to fixed speed bands (integrate near a hover or when a 0.3 m/s climb stalls) left a
        # dead band where a 0.25 m/s lift hung 13-20 cm short for good, and the vehicle hung 20 cm above its
        # retreat height after letting go of a bottle.
        stalled = abs(dv[2]) >= 0.1 and abs(self.v[2]) < 0.1
        if not clipped_z or stalled or dv[2] * self.v_int[2] < 0:
            self.v_int[2] = min(max(self.v_int[2] + dv[2] * dt * p.vel_ki_z, -3.0), 3.0)
        if float(np.linalg.norm(dv[:2])) < 0.15:
            self.v_int[:2] = np.clip(self.v_int[:2] + dv[:2] * dt * p.vel_ki, -1.0, 1.0)
        a_ned = a + self.v_int
        m = self.world.vehicle_mass
        force_enu = ned_to_enu(a_ned) * m
        force_enu[2] += m * GRAVITY
        fh = float(np.linalg.norm(force_enu[:2]))
        if fh > m * p.max_tilt_accel:
            force_enu[:2] *= m * p.max_tilt_accel / fh
        force_enu[2] = max(force_enu[2], 0.1 * m * GRAVITY)
        self._thrust_z = float(force_enu[2])
        self._h_force_max = m * min(p.accel_h + float(np.linalg.norm(self.v_int[:2])), p.max_tilt_accel)
        self._z_sp = attitude_setpoint((float(force_enu[0]), float(force_enu[1]), float(force_enu[2])),
                                       p.inner.max_tilt)
        self._force = (float(force_enu[0]), float(force_enu[1]), float(force_enu[2]))

    def _drift(self, dt: float) -> None:
        """The kinematic body's estimator: a bounded random walk of the horizontal and yaw biases."""
        p = self.params
        if p.pose_drift > 0:
            self.drift_bias[:2] += self.rng.normal(0.0, p.pose_drift * math.sqrt(dt), 2)
            n = float(np.linalg.norm(self.drift_bias[:2]))
            if n > p.pose_drift_max:
                self.drift_bias[:2] *= p.pose_drift_max / n
        if p.yaw_drift > 0:
            self.yaw_drift_bias = min(max(self.yaw_drift_bias + float(self.rng.normal(0.0, p.yaw_drift
                                                                                      * math.sqrt(dt))),
                                          -p.yaw_drift_max), p.yaw_drift_max)

    def _kinematic_control(self, dt: float) -> tuple[np.ndarray, float]:
        """The kinematic body's controller on the estimated state: position -> velocity setpoint (speed and
        acceleration limits, sqrt braking profile) -> a world-frame force (PI on velocity, gravity feed-forward,
        thrust limits) and a yaw torque; the body never tilts."""
        p = self.params
        target, vel_cmd, yaw_target, yaw_rate_cmd, vmax_up, vmax_down = self._setpoints()
        if self._idle_on_ground(target):
            self.v_int[:] = 0.0
            return np.zeros(3), 0.0
        if vel_cmd is None:
            assert target is not None
            vel_cmd = self._position_control(target, vmax_up, vmax_down)
        vel_cmd = np.array(vel_cmd, dtype=float)
        h = np.linalg.norm(vel_cmd[:2])
        if h > p.max_speed_h:
            vel_cmd[:2] *= p.max_speed_h / h
        vel_cmd[2] = min(max(vel_cmd[2], -vmax_up), vmax_down)
        # Acceleration limits on the velocity setpoint's change relative to the current velocity.
        dv = vel_cmd - self.v
        a = dv / p.kinematic_vel_tau
        ah = float(np.linalg.norm(a[:2]))
        if ah > p.accel_h:
            a[:2] *= p.accel_h / ah
        a[2] = min(max(a[2], -p.accel_v), p.accel_v)
        # Integral on the vertical axis only: it carries a payload's weight (the horizontal axes have no
        # steady disturbance here, and an integral there would break the acceleration limit).
        self.v_int[2] = min(max(self.v_int[2] + dv[2] * dt * p.kinematic_vel_ki, -3.0), 3.0)
        a_ned = a + self.v_int
        m = self.world.vehicle_mass
        force_enu = ned_to_enu(a_ned) * m
        force_enu[2] += m * GRAVITY
        fh = float(np.linalg.norm(force_enu[:2]))
        if fh > m * p.max_tilt_accel:
            force_enu[:2] *= m * p.max_tilt_accel / fh
        force_enu[2] = min(max(force_enu[2], 0.0), m * p.max_thrust_accel)
        # Yaw: rate-limited towards the target, then a torque tracking that rate.
        if yaw_rate_cmd is None:
            yaw_rate_cmd = self._yaw_rate_toward(yaw_target, KINEMATIC_YAW_ACCEL)
        torque = VEHICLE_YAW_INERTIA_TOTAL * (-yaw_rate_cmd - self.world.vehicle_yaw_rate()) / 0.05
        return force_enu, torque

    def _hover_error(self) -> np.ndarray:
        """ENU offset of where the vehicle settles from its position setpoint (hover_offset, hover_wander)."""
        p = self.params
        ox, oy = p.hover_offset
        if p.hover_wander > 0:
            phase = 2 * math.pi * self.sim_time / max(p.hover_wander_period, 0.1)
            ox, oy = ox + p.hover_wander * math.cos(phase), oy + p.hover_wander * math.sin(phase)
        return np.array([ox, oy, 0.0])

    def _yaw_rate_toward(self, yaw_target: float | None, yaw_accel: float | None = None) -> float:
        """Yaw rate command towards `yaw_target` (P gain, rate limit, sqrt braking); 0 without a target."""
        if yaw_target is None or not math.isfinite(yaw_target):
            return 0.0
        p = self.params
        err = wrap(yaw_target - self.yaw)
        yaw_rate_cmd = min(max(3.0 * err, -p.yaw_rate), p.yaw_rate)
        if abs(err) > 1e-4:
            accel = p.yaw_accel if yaw_accel is None else yaw_accel
            yaw_rate_cmd = math.copysign(min(abs(yaw_rate_cmd), math.sqrt(2 * accel * abs(err))), err)
        return yaw_rate_cmd

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

    def _climbing(self) -> bool:
        if self.main_mode == MAIN_AUTO and self.sub_mode == SUB_TAKEOFF:
            return True
        return self.main_mode == MAIN_OFFBOARD and (
            (self.sp_pos is not None and self.sp_pos[2] < self.p[2] - 0.05)
            or (self.sp_vel is not None and self.sp_vel[2] < 0))

