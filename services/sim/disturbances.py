"""Seeded disturbance models of the simulated multirotor: Gauss-Markov processes, indoor air (turbulence,
gusts, a draft), the pose estimator's error, ground effect and rotor downwash on objects (README: figures and
sources)."""

from __future__ import annotations

import math

import numpy as np


class GaussMarkov:
    """First-order Gauss-Markov (Ornstein-Uhlenbeck) process per axis: stationary standard deviation `sigma`,
    correlation time `tau`, discretised exactly (any dt keeps the statistics). Starts from its stationary
    distribution so a run has no warm-up."""

    def __init__(self, sigma: np.ndarray | float, tau: float, rng: np.random.Generator, n: int = 3) -> None:
        self.sigma = np.broadcast_to(np.asarray(sigma, dtype=float), (n,)).copy()
        self.tau = tau
        self.rng = rng
        self.x = self.sigma * rng.standard_normal(n) if tau > 0 else np.zeros(n)

    def step(self, dt: float) -> np.ndarray:
        if self.tau <= 0 or not self.sigma.any():
            return self.x
        a = math.exp(-dt / self.tau)
        self.x = a * self.x + self.sigma * math.sqrt(1.0 - a * a) * self.rng.standard_normal(len(self.x))
        return self.x


class Wind:
    """Air velocity at the vehicle (world ENU, m/s): a steady draft (an air vent, a door), turbulence as
    Dryden-like first-order filtered noise, and discrete "1 - cosine" gusts (MIL-F-8785C's shape) arriving as a
    Poisson process with random direction, amplitude and length."""

    def __init__(self, rng: np.random.Generator, mean: float, sigma_h: float, sigma_v: float, tau: float,
                 gust_rate: float, gust_amp: tuple[float, float], gust_s: tuple[float, float]) -> None:
        self.rng = rng
        a = float(rng.uniform(-math.pi, math.pi))
        self.mean = np.array([mean * math.cos(a), mean * math.sin(a), 0.0])
        self.turb = GaussMarkov(np.array([sigma_h, sigma_h, sigma_v]), tau, rng)
        self.gust_rate, self.gust_amp, self.gust_s = gust_rate, gust_amp, gust_s
        self.gust_dir = np.zeros(3)
        self.gust_t = self.gust_len = 0.0
        self.gust_peak = 0.0

    def step(self, dt: float) -> np.ndarray:
        w = self.mean + self.turb.step(dt)
        if self.gust_len > 0.0:
            self.gust_t += dt
            if self.gust_t >= self.gust_len:
                self.gust_len = 0.0
            else:
                w = w + self.gust_dir * (self.gust_peak * 0.5 * (1.0 - math.cos(2 * math.pi * self.gust_t
                                                                                  / self.gust_len)))
        elif self.gust_rate > 0 and self.rng.random() < self.gust_rate * dt:
            a = float(self.rng.uniform(-math.pi, math.pi))
            self.gust_dir = np.array([math.cos(a), math.sin(a), 0.0])
            self.gust_peak = float(self.rng.uniform(*self.gust_amp))
            self.gust_len = float(self.rng.uniform(*self.gust_s))
            self.gust_t = 0.0
        return w


class PoseEstimator:
    """Error of an indoor visual-inertial estimate (estimate - truth): a slowly wandering position bias per
    axis (Gauss-Markov: VIO drift bounded by re-observed features), white position and velocity noise, and a
    wandering yaw bias. Attitude (roll, pitch) is the IMU's and taken as exact."""

    def __init__(self, rng: np.random.Generator, bias_xy: float, bias_z: float, bias_tau: float,
                 noise: float, vel_noise: float, yaw_bias: float, yaw_tau: float) -> None:
        self.rng = rng
        self.bias = GaussMarkov(np.array([bias_xy, bias_xy, bias_z]), bias_tau, rng)
        self.yaw = GaussMarkov(yaw_bias, yaw_tau, rng, n=1)
        self.noise, self.vel_noise = noise, vel_noise

    def step(self, dt: float) -> None:
        self.bias.step(dt)
        self.yaw.step(dt)

    def position_error(self) -> np.ndarray:
        if self.noise > 0:
            return self.bias.x + self.noise * self.rng.standard_normal(3)
        return self.bias.x.copy()

    def velocity_error(self) -> np.ndarray:
        return self.vel_noise * self.rng.standard_normal(3) if self.vel_noise > 0 else np.zeros(3)

    @property
    def yaw_error(self) -> float:
        return float(self.yaw.x[0])


def ground_effect(height: float, rotor_radius: float, rotor_spacing: float = 0.0, arm: float = 0.0,
                  body_factor: float = 2.0) -> float:
    """Thrust in ground effect over thrust out of it for a rotor `height` above a surface. One rotor:
    Cheeseman & Bennett (1955), 1 / (1 - (R / 4z)^2). Given the spacing of adjacent rotors and the arm length,
    the multirotor model of Sanchez-Cuevas, Heredia & Ollero (2017), whose neighbouring rotors' and the body's
    reflected wakes make the gain several times larger (~10 % 0.18 m above a surface). Bounded where
    the models' singularity lies (z < R / 2)."""
    z = max(height, rotor_radius / 2)
    r2 = rotor_radius * rotor_radius
    loss = (rotor_radius / (4.0 * z)) ** 2
    if rotor_spacing > 0:
        d2, b2, z2 = rotor_spacing ** 2, arm ** 2, 4 * z * z
        loss += r2 * z / math.sqrt((d2 + z2) ** 3) + r2 / 2 * z / math.sqrt((2 * d2 + z2) ** 3) \
            + 2 * r2 * z / math.sqrt((b2 + z2) ** 3) * body_factor
    return 1.0 / (1.0 - min(loss, 0.5))


def downwash_force(thrust: float, rotor_radius: float, depth: float, offset: float, obj_radius: float,
                   obj_area: float, drag_coefficient: float = 1.0) -> float:
    """Downward force (N) of one rotor's slipstream on an object `depth` below the rotor disc whose centre is
    `offset` from the rotor axis. Momentum theory gives the fully developed wake a dynamic pressure of T / A;
    the jet spreads and slows with depth (pressure ~ 1 / (1 + (depth / 2R)^2)); the object catches the part of
    its top area that overlaps the disc."""
    if thrust <= 0 or depth <= 0:
        return 0.0
    overlap = (rotor_radius + obj_radius - offset) / (2 * min(rotor_radius, obj_radius))
    if overlap <= 0:
        return 0.0
    disc = math.pi * rotor_radius * rotor_radius
    pressure = thrust / disc / (1.0 + (depth / (2 * rotor_radius)) ** 2)
    return drag_coefficient * pressure * min(obj_area, disc) * min(overlap, 1.0)
