"""Random but physically plausible drone flights inside the MMAUD flight region.

A flight is a sequence of manoeuvres (hover, or transit to a random waypoint at a sampled
cruise speed) flown by a point mass under an acceleration- and speed-limited controller, with
an Ornstein-Uhlenbeck gust disturbance, integrated at 100 Hz and interpolated by a cubic spline
so that position, velocity and acceleration can be queried at audio rate.

Defaults (``docs/simulation_sources.md`` sections 0 and 7): region x in [-2, 8], y in [-5, 25],
z in [0.5, 25] m relative to the rig (AAUTE paper's 10 x 30 x 25 m region, AV-FDTI heat-map
bounds, TAME ground truth) [V]; speeds 0-5 m/s with a mode near 1 m/s (MMAUD speed histograms,
TAME ground truth) [V/E]; accelerations <= 3 m/s^2, climb <= 2 m/s, hovers of 2-10 s [E].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline


@dataclass
class TrajectoryConfig:
    """Flight envelope of the simulated drone (metres, seconds)."""

    region_min: tuple[float, float, float] = (-2.0, -5.0, 0.5)
    region_max: tuple[float, float, float] = (8.0, 25.0, 25.0)
    cruise_speed_median: float = 1.1  #: lognormal median (m/s); mode ~1 m/s with sigma 0.5
    cruise_speed_sigma: float = 0.5
    max_speed: float = 5.0
    max_climb_rate: float = 2.0
    max_acceleration: float = 2.5
    hover_probability: float = 0.5  #: chance that a manoeuvre is a hover
    hover_seconds: tuple[float, float] = (2.0, 10.0)
    gust_acceleration: float = 0.15  #: rms of the OU gust acceleration (m/s^2): hover wander ~0.1-0.3 m
    gust_time_constant: float = 1.5  #: s
    controller_gain: float = 0.8  #: 1/s, position-to-velocity gain near a waypoint
    velocity_time_constant: float = 0.6  #: s, how fast the drone follows its velocity command
    rate_hz: float = 100.0


class Trajectory:
    """A flight path, queried at any times in seconds since the start of the recording."""

    def __init__(self, times: np.ndarray, positions: np.ndarray):
        self.times = np.asarray(times, dtype=np.float64)
        self.positions = np.asarray(positions, dtype=np.float64)
        self._spline = CubicSpline(self.times, self.positions, axis=0)
        self._velocity = self._spline.derivative(1)
        self._acceleration = self._spline.derivative(2)

    def shifted(self, offset: float) -> Trajectory:
        """The same flight on a clock whose zero is ``offset`` seconds into it."""
        return Trajectory(self.times - offset, self.positions)

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0])

    def position(self, t: np.ndarray | float) -> np.ndarray:
        """Position(s) at time(s) ``t`` (... x 3, m)."""
        return self._spline(np.clip(t, self.times[0], self.times[-1]))

    def velocity(self, t: np.ndarray | float) -> np.ndarray:
        return self._velocity(np.clip(t, self.times[0], self.times[-1]))

    def acceleration(self, t: np.ndarray | float) -> np.ndarray:
        return self._acceleration(np.clip(t, self.times[0], self.times[-1]))


def _sample_point(config: TrajectoryConfig, rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(config.region_min, config.region_max)


def generate_trajectory(
    duration: float, rng: np.random.Generator, config: TrajectoryConfig | None = None
) -> Trajectory:
    """Fly a random sequence of hovers and transits for ``duration`` seconds (plus 1 s margin)."""
    config = config or TrajectoryConfig()
    dt = 1.0 / config.rate_hz
    steps = int(np.ceil((duration + 1.0) / dt)) + 1
    lo, hi = np.array(config.region_min), np.array(config.region_max)

    position = _sample_point(config, rng)
    velocity = np.zeros(3)
    gust = np.zeros(3)
    positions = np.empty((steps, 3))
    target, speed, hover_until = position.copy(), 0.0, 0.0
    gust_decay = np.exp(-dt / config.gust_time_constant)
    gust_kick = config.gust_acceleration * np.sqrt(1.0 - gust_decay**2)

    for i in range(steps):
        t = i * dt
        positions[i] = position
        arrived = np.linalg.norm(target - position) < 0.3
        if t >= hover_until and (arrived or speed == 0.0):
            if rng.random() < config.hover_probability:
                target, speed = position.copy(), 0.0
                hover_until = t + rng.uniform(*config.hover_seconds)
            else:
                target = _sample_point(config, rng)
                speed = min(rng.lognormal(np.log(config.cruise_speed_median), config.cruise_speed_sigma),
                            config.max_speed)
                hover_until = t
        # velocity command: towards the target at cruise speed, slowing near it
        offset = target - position
        distance = np.linalg.norm(offset)
        command_speed = min(max(speed, 0.3), config.controller_gain * distance) if distance > 1e-6 else 0.0
        command = offset / max(distance, 1e-9) * command_speed
        command[2] = np.clip(command[2], -config.max_climb_rate, config.max_climb_rate)
        accel = (command - velocity) / config.velocity_time_constant
        norm = np.linalg.norm(accel)
        if norm > config.max_acceleration:
            accel *= config.max_acceleration / norm
        gust = gust * gust_decay + gust_kick * rng.standard_normal(3)
        velocity = velocity + (accel + gust) * dt
        position = np.clip(position + velocity * dt, lo, hi)
    return Trajectory(np.arange(steps) * dt, positions)
