"""The inner loops of a PX4-style multirotor controller: thrust vector -> attitude setpoint, attitude (tilt) ->
body rates, body rates -> torques, and the mixer that turns collective thrust and torques into rotor thrusts
within the motors' limits. Plain floats, no numpy: the rate loop and the mixer run every 2 ms MuJoCo step and the
attitude loop every second one, where numpy's per-call overhead on 3-vectors costs more than the arithmetic."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class InnerGains:
    """Attitude and rate loop gains in physical units (PX4 normalises its MC_*RATE_P by the airframe's torque
    authority; here the rate loop's output is multiplied by the inertia instead, so the gains are bandwidths)."""

    att_p: float = 7.0  # 1/s, tilt error -> roll/pitch rate setpoint (PX4 MC_ROLL_P/MC_PITCH_P 6.5)
    rate_p: float = 28.0  # 1/s, roll/pitch rate error -> angular acceleration (crossover ~28 rad/s with 20 ms motors)
    rate_i: float = 20.0  # 1/s^2, its integral (a held object's offset centre of mass)
    rate_i_max: float = 6.0  # rad/s^2, integral limit
    yaw_rate_p: float = 15.0  # 1/s, yaw rate error -> yaw angular acceleration
    yaw_rate_i: float = 2.0
    yaw_accel_ff: float = 0.5  # share of the yaw rate setpoint's ramp fed forward (all of it overshoots: motor lag)
    rate_max: float = math.radians(220.0)  # rad/s (MC_ROLLRATE_MAX / MC_PITCHRATE_MAX)
    max_tilt: float = math.radians(35.0)  # rad (MPC_TILTMAX_AIR)


class Mixer:
    """Collective thrust and body torques (FLU) -> rotor thrusts, saturating as PX4's mixer does: roll and pitch
    first (scaled down only if their spread alone exceeds the motors' range), the collective shifted to keep
    them, yaw last with whatever headroom is left."""

    def __init__(self, rotor_xy: tuple[tuple[float, float], ...], spin: tuple[float, ...], yaw_moment: float,
                 max_thrust: float) -> None:
        # Rows: thrust, torque x, torque y, torque z produced by each rotor's unit thrust.
        effect = np.array([[1.0] * len(rotor_xy), [y for _, y in rotor_xy], [-x for x, _ in rotor_xy],
                           [-s * yaw_moment for s in spin]])
        inv = np.linalg.pinv(effect)  # rotors x (thrust, tx, ty, tz)
        self.n = len(rotor_xy)
        self.col = [float(inv[i, 0]) for i in range(self.n)]
        self.rx = [float(inv[i, 1]) for i in range(self.n)]
        self.ry = [float(inv[i, 2]) for i in range(self.n)]
        self.rz = [float(inv[i, 3]) for i in range(self.n)]
        self._rxy = list(zip(self.rx, self.ry, strict=True))
        self.effect = effect
        self.max_thrust = max_thrust
        self.saturated = False  # the last mix could not give the torques asked for (the rate integrals hold)

    def mix(self, thrust: float, tx: float, ty: float, tz: float) -> list[float]:
        if self.n == 4:
            return self._mix4(thrust, tx, ty, tz)
        fmax = self.max_thrust
        rp = [a * tx + b * ty for a, b in self._rxy]
        spread = max(rp) - min(rp)
        saturated = spread > fmax
        if saturated:  # even zero collective cannot give this roll/pitch torque: keep its direction
            k = fmax / spread
            rp = [r * k for r in rp]
        f = [c * thrust + r for c, r in zip(self.col, rp, strict=True)]
        lo, hi = min(f), max(f)
        if lo < 0.0:
            f = [x - lo for x in f]  # raise the collective: attitude before altitude
        elif hi > fmax:
            shift = hi - fmax
            f = [x - shift for x in f]
        return self._add_yaw(f, [c * tz for c in self.rz], saturated)

    def _add_yaw(self, f: list[float], yaw: list[float], saturated: bool) -> list[float]:
        """Yaw last, scaled down to the headroom the rotors have left."""
        fmax = self.max_thrust
        scale = 1.0
        for x, y in zip(f, yaw, strict=True):
            if y > 0 and x + y > fmax:
                scale = min(scale, max(0.0, (fmax - x) / y))
            elif y < 0 and x + y < 0.0:
                scale = min(scale, max(0.0, -x / y))
        self.saturated = saturated or scale < 1.0
        out = []
        for x, y in zip(f, yaw, strict=True):
            t = x + scale * y
            out.append(0.0 if t < 0.0 else (fmax if t > fmax else t))
        return out

    def _mix4(self, thrust: float, tx: float, ty: float, tz: float) -> list[float]:
        """`mix` unrolled for four rotors (it runs every physics step): the same steps, no list building
        until the yaw stage, which rarely saturates."""
        fmax = self.max_thrust
        (a0, b0), (a1, b1), (a2, b2), (a3, b3) = self._rxy
        r0, r1, r2, r3 = a0 * tx + b0 * ty, a1 * tx + b1 * ty, a2 * tx + b2 * ty, a3 * tx + b3 * ty
        spread = max(r0, r1, r2, r3) - min(r0, r1, r2, r3)
        saturated = spread > fmax
        if saturated:
            k = fmax / spread
            r0, r1, r2, r3 = r0 * k, r1 * k, r2 * k, r3 * k
        c0, c1, c2, c3 = self.col
        f0, f1, f2, f3 = c0 * thrust + r0, c1 * thrust + r1, c2 * thrust + r2, c3 * thrust + r3
        lo, hi = min(f0, f1, f2, f3), max(f0, f1, f2, f3)
        if lo < 0.0:
            f0, f1, f2, f3 = f0 - lo, f1 - lo, f2 - lo, f3 - lo
        elif hi > fmax:
            sh = hi - fmax
            f0, f1, f2, f3 = f0 - sh, f1 - sh, f2 - sh, f3 - sh
        z0, z1, z2, z3 = self.rz
        y0, y1, y2, y3 = z0 * tz, z1 * tz, z2 * tz, z3 * tz
        g0, g1, g2, g3 = f0 + y0, f1 + y1, f2 + y2, f3 + y3
        if min(g0, g1, g2, g3) >= 0.0 and max(g0, g1, g2, g3) <= fmax:  # the usual case: yaw fits
            self.saturated = saturated
            return [g0, g1, g2, g3]
        return self._add_yaw([f0, f1, f2, f3], [y0, y1, y2, y3], saturated)

    def wrench(self, thrusts: list[float]) -> tuple[float, float, float, float]:
        """Collective thrust and torques the rotor thrusts produce (the mixer's inverse)."""
        out = self.effect @ np.asarray(thrusts, dtype=float)
        return float(out[0]), float(out[1]), float(out[2]), float(out[3])


def attitude_setpoint(force: tuple[float, float, float], max_tilt: float) -> tuple[float, float, float]:
    """Body z axis (world ENU) the thrust vector asks for, its tilt limited to `max_tilt` from vertical."""
    fx, fy, fz = force
    fz = max(fz, 1e-6)
    h = math.hypot(fx, fy)
    limit = math.tan(max_tilt) * fz
    if h > limit:
        fx, fy = fx * limit / h, fy * limit / h
    n = math.sqrt(fx * fx + fy * fy + fz * fz)
    return fx / n, fy / n, fz / n


class AttitudeRateController:
    """Tilt -> body rates -> torques, once per physics step. Yaw is rate-controlled: the position loop turns
    the heading error into a yaw rate (as PX4's yaw setpoint follows a rate-limited trajectory)."""

    def __init__(self, inertia: tuple[float, float, float], gains: InnerGains | None = None) -> None:
        self.inertia = inertia
        self.g = gains or InnerGains()
        self.reset()

    def reset(self) -> None:
        self.ix = self.iy = self.iz = 0.0
        self.p_sp = self.q_sp = 0.0
        self._r21, self._bzz_inv, self._r_sp0 = 0.0, 1.0, 0.0

    def attitude(self, q: tuple[float, float, float, float], z_sp: tuple[float, float, float],
                 yaw_rate_sp: float) -> None:
        """The attitude loop (PX4's mc_att_control, at ATTITUDE_DIV physics steps): tilt error -> roll and
        pitch rate setpoints, and what turns the heading's rate setpoint into a body rate (kept for `rates`).
        `q` (w, x, y, z) the attitude, `z_sp` the body z axis wanted (world)."""
        g = self.g
        w, x, y, z = q
        # Body z axis in the world, then the tilt error z_b x z_sp expressed in the body frame.
        bzx, bzy, bzz = 2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)
        ex = bzy * z_sp[2] - bzz * z_sp[1]
        ey = bzz * z_sp[0] - bzx * z_sp[2]
        ez = bzx * z_sp[1] - bzy * z_sp[0]
        # World -> body: the transpose of the body's rotation matrix (its columns' components).
        r00, r10, r20 = 1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)
        r01, r11, r21 = 2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)
        rmax = g.rate_max
        self.p_sp = min(max(g.att_p * (r00 * ex + r10 * ey + r20 * ez), -rmax), rmax)
        self.q_sp = min(max(g.att_p * (r01 * ex + r11 * ey + r21 * ez), -rmax), rmax)
        # The heading's rate (z-y-x Euler yaw) is (q sin(roll) + r cos(roll)) / cos(pitch): the body rate r that
        # turns the heading at yaw_rate_sp when tilted (R20..R22 = -sin pitch, sin roll cos pitch, cos roll cos pitch).
        self._r21, self._bzz_inv = r21, 1.0 / max(bzz, 0.2)
        self._r_sp0 = yaw_rate_sp * (r21 * r21 + bzz * bzz)

    def rates(self, rates: tuple[float, float, float], dt: float, saturated: bool = False,
              yaw_accel_ff: float = 0.0) -> tuple[float, float, float]:
        """The rate loop (PX4's mc_rate_control, every physics step): body `rates` (FLU) against the last
        attitude step's setpoints -> torques (FLU, N m). `saturated`: the mixer could not deliver the last
        torques, so the integrals hold (anti-windup); `yaw_accel_ff`: the yaw rate setpoint's own rate of
        change, fed forward."""
        g = self.g
        p, qr, r = rates
        ep, eq = self.p_sp - p, self.q_sp - qr
        er = (self._r_sp0 - qr * self._r21) * self._bzz_inv - r
        if not saturated:
            imax = g.rate_i_max
            self.ix = min(max(self.ix + g.rate_i * ep * dt, -imax), imax)
            self.iy = min(max(self.iy + g.rate_i * eq * dt, -imax), imax)
            self.iz = min(max(self.iz + g.yaw_rate_i * er * dt, -imax), imax)
        jx, jy, jz = self.inertia
        # Gyroscopic term omega x J omega: small at these rates, but it is what a rate controller feeds forward.
        return (jx * (g.rate_p * ep + self.ix) + (jz - jy) * qr * r, jy * (g.rate_p * eq + self.iy) + (jx - jz) * r * p,
                jz * (g.yaw_rate_p * er + self.iz + yaw_accel_ff))

    def torques(self, q: tuple[float, float, float, float], rates: tuple[float, float, float],
                z_sp: tuple[float, float, float], yaw_rate_sp: float, dt: float,
                saturated: bool = False, yaw_accel_ff: float = 0.0) -> tuple[float, float, float]:
        """Both loops at once: `attitude`, then `rates`."""
        self.attitude(q, z_sp, yaw_rate_sp)
        return self.rates(rates, dt, saturated, yaw_accel_ff)
