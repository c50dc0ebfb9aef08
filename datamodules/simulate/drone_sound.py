"""The sound a drone emits: rotor harmonics, broadband noise and motor whine, driven by its flight.

Model (``docs/simulation_sources.md`` sections 1.1-1.3 and 7):
- each rotor turns at n_i(t) = n_thrust(t) (1 + d_i(t) + e_i(t)): the thrust law n ~ sqrt(T)
  from the trajectory's acceleration and drag; d_i a slow per-rotor offset of +-2 % for attitude
  and yaw control [M]; e_i the turbulence-driven fluctuation with sigma_N/N = 0.005 + 0.0052
  v_wind (Heutschi et al. 2020, hover at 10 m, via S12) [V];
- tonal lines at multiples h of each rotor's shaft rate: blade-passing harmonics (h = k B) with
  amplitude ~ k^-p, p ~ U(1, 1.5) per flight and +-2 dB jitter, up to k = 40; shaft-rate lines
  between them at -10 to -20 dB [E]; rendered from a per-rotor one-revolution wavetable read at
  the shaft phase, so the signal at any retarded time is exact up to table interpolation;
- broadband noise with PSD ~ f^-p, p ~ U(1, 2), at -10 dB re the tonal energy, and a motor whine
  band of 8-12 kHz at -20 dB [E], generated at twice the output rate and read at the retarded
  time by cubic Lagrange interpolation (``simulation_sources.md`` 2.3, option 1);
- level: A-weighted sound power LWA of the drone type +-3 dB per flight [V Mavic 3 / E others],
  plus 50 log10(n / n_hover) dB with rpm (between the 40-60 log10 of loading-noise theory and the
  Mavic 2's measured +3.5 dB per 1000 rpm) [M/V], plus a slow per-rotor amplitude fluctuation of
  1 dB rms (statistical AM, Dreier & Vorlaender 2024) [E];
- vertical directivity: +2.5 dB at 30-60 deg below the rotor plane, 0 dB in-plane, -4.5 dB on
  the rotor axis (Kloet et al.; Heutschi et al.) [V/E], normalised to unit mean power.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datamodules.simulate.drones import DroneSpec, rpm_for_thrust
from datamodules.simulate.noise import coloured_noise, ou_process
from datamodules.simulate.propagation import AIR_DENSITY, a_weighting_db, level_to_pressure
from datamodules.simulate.trajectory import Trajectory

#: Directivity table: elevation of the observer relative to the rotor plane (deg, negative =
#: below the drone) -> gain (dB) before normalisation (``simulation_sources.md`` 1.3 [V/E]).
DIRECTIVITY_ELEVATION_DEG = np.array([-90.0, -75.0, -60.0, -45.0, -30.0, -15.0, 0.0, 30.0, 60.0, 90.0])
DIRECTIVITY_GAIN_DB = np.array([-4.5, -1.0, 2.0, 2.5, 2.0, 1.0, 0.0, 0.0, -1.5, -4.5])


@dataclass
class SourceConfig:
    """Parameters of the drone source model (sources in the module docstring)."""

    bpf_harmonics: int = 40
    harmonic_slope: tuple[float, float] = (1.0, 1.5)
    harmonic_jitter_db: float = 2.0
    shaft_line_db: tuple[float, float] = (-20.0, -10.0)
    broadband_db: float = -10.0
    broadband_slope: tuple[float, float] = (1.0, 2.0)
    whine_db: float = -20.0
    whine_band_hz: tuple[float, float] = (8000.0, 12000.0)
    level_spread_db: float = 3.0
    rpm_level_exponent: float = 50.0
    rotor_offset_sigma: float = 0.02
    rotor_offset_time_constant: float = 2.0
    rpm_jitter_base: float = 0.005
    rpm_jitter_per_wind: float = 0.0052
    rpm_jitter_time_constant: float = 0.1  #: s [E]; S12 holds its micro-modulations for 20-50 ms
    rotor_am_sigma_db: float = 1.0
    rotor_am_time_constant: float = 0.5
    drag_coefficient: float = 1.0  #: bluff-body C_d on the side area [E]
    wavetable_size: int = 16384
    control_rate: float = 1000.0  #: Hz, rate of the rpm/phase/gain control signals
    max_frequency_ratio: float = 0.45  #: highest tonal line as a fraction of the output rate


def directivity_db(elevation_rad: np.ndarray) -> np.ndarray:
    """Unnormalised vertical directivity gain (dB) for observer elevations rel. to the rotor plane."""
    return np.interp(np.degrees(elevation_rad), DIRECTIVITY_ELEVATION_DEG, DIRECTIVITY_GAIN_DB)


def _directivity_mean_power() -> float:
    """Mean of 10^(D/10) over the sphere (weights cos(elevation)), used to normalise D."""
    elevation = np.linspace(-np.pi / 2, np.pi / 2, 4001)
    weights = np.cos(elevation)
    return float(np.sum(10.0 ** (directivity_db(elevation) / 10.0) * weights) / np.sum(weights))


def directivity_gain(elevation_rad: np.ndarray) -> np.ndarray:
    """Linear pressure gain of the vertical directivity, with unit mean power over the sphere."""
    return 10.0 ** (directivity_db(elevation_rad) / 20.0) / np.sqrt(_DIRECTIVITY_POWER)


_DIRECTIVITY_POWER = _directivity_mean_power()


def uniform_lookup(t: np.ndarray, t0: float, rate: float, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Left index and weight of times ``t`` on the uniform grid t0 + k / rate (clamped to it)."""
    pos = np.clip((np.asarray(t, dtype=np.float64) - t0) * rate, 0.0, size - 1.000001)
    index = pos.astype(np.int64)
    return index, pos - index


def lerp(values: np.ndarray, index: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Linear interpolation of ``values`` (... x grid) at a :func:`uniform_lookup` result."""
    return values[..., index] * (1.0 - weight) + values[..., index + 1] * weight


class DroneSource:
    """Emitted pressure at 1 m (Pa, free field, unit directivity) of one drone along one flight.

    Build it once per flight; then :meth:`emitted` evaluates the signal at any emission times
    (seconds on the trajectory's clock), which the renderer calls with each microphone's retarded
    times.
    """

    def __init__(
        self,
        spec: DroneSpec,
        trajectory: Trajectory,
        sample_rate: float,
        rng: np.random.Generator,
        wind_speed: float = 0.0,
        config: SourceConfig | None = None,
    ):
        self.spec = spec
        self.config = config = config or SourceConfig()
        self.sample_rate = float(sample_rate)
        t_start, t_end = float(trajectory.times[0]), float(trajectory.times[-1])
        dt = 1.0 / config.control_rate
        self.control_times = np.arange(t_start, t_end + dt, dt)
        n = self.control_times.size

        # rotor speeds from the flight, per rotor offsets and turbulence fluctuations
        velocity = trajectory.velocity(self.control_times)
        drag = (0.5 * AIR_DENSITY * config.drag_coefficient * spec.side_area_m2 / spec.mass_kg) * (
            velocity * np.linalg.norm(velocity, axis=1, keepdims=True)
        )
        mean_rpm = rpm_for_thrust(spec, trajectory.acceleration(self.control_times) + drag)
        rotors = spec.rotors
        offsets = ou_process(n, dt, config.rotor_offset_sigma, config.rotor_offset_time_constant, rng, (rotors,))
        jitter_sigma = config.rpm_jitter_base + config.rpm_jitter_per_wind * wind_speed
        jitter = ou_process(n, dt, jitter_sigma, config.rpm_jitter_time_constant, rng, (rotors,))
        self.rpm = mean_rpm[None, :] * (1.0 + offsets + jitter)  # rotors x n
        shaft_hz = self.rpm / 60.0
        self.shaft_phase = 2.0 * np.pi * np.concatenate(
            [rng.uniform(0, 1, (rotors, 1)), np.cumsum(0.5 * (shaft_hz[:, 1:] + shaft_hz[:, :-1]) * dt, axis=1)],
            axis=1,
        )
        self.shaft_phase[:, 1:] += self.shaft_phase[:, :1]

        # per-rotor amplitude: rpm law and slow fluctuation (dB)
        am_db = ou_process(n, dt, config.rotor_am_sigma_db, config.rotor_am_time_constant, rng, (rotors,))
        self.flight_level_db = rng.uniform(-config.level_spread_db, config.level_spread_db)
        level_db = config.rpm_level_exponent * np.log10(self.rpm / spec.hover_rpm) + am_db
        self.rotor_gain = 10.0 ** (level_db / 20.0)

        self._build_tonal(rng)
        self._build_broadband(trajectory, rng)
        self._calibrate()

    # ------------------------------------------------------------------------------ components

    def _build_tonal(self, rng: np.random.Generator) -> None:
        """One wavetable per rotor: the waveform of one shaft revolution (unit scale)."""
        cfg, spec = self.config, self.spec
        max_shaft_hz = float(self.rpm.max()) / 60.0
        top = min(cfg.bpf_harmonics * spec.blades, int(cfg.max_frequency_ratio * self.sample_rate / max_shaft_hz))
        self.harmonic_orders = h = np.arange(1, max(top, 1) + 1)
        slope = rng.uniform(*cfg.harmonic_slope)
        k = np.ceil(h / spec.blades)  # the BPF harmonic a shaft line sits under
        level_db = -20.0 * slope * np.log10(k) + rng.uniform(-cfg.harmonic_jitter_db, cfg.harmonic_jitter_db, h.size)
        is_bpf = h % spec.blades == 0
        level_db[~is_bpf] += rng.uniform(*cfg.shaft_line_db, size=int((~is_bpf).sum()))
        self.harmonic_amplitude = 10.0 ** (level_db / 20.0)
        phase = rng.uniform(0, 2 * np.pi, (spec.rotors, h.size))
        theta = 2 * np.pi * np.arange(cfg.wavetable_size) / cfg.wavetable_size
        self.wavetables = np.einsum("h,rht->rt", self.harmonic_amplitude,
                                    np.cos(h[None, :, None] * theta[None, None, :] + phase[:, :, None]))

    def _build_broadband(self, trajectory: Trajectory, rng: np.random.Generator) -> None:
        """Broadband + whine noise, unit variance before calibration, at twice the output rate."""
        cfg = self.config
        self.noise_rate = 2.0 * self.sample_rate
        self.noise_t0 = float(trajectory.times[0])
        length = int(np.ceil((trajectory.times[-1] - trajectory.times[0]) * self.noise_rate)) + 4
        slope = rng.uniform(*cfg.broadband_slope)
        corner = self.spec.hover_bpf_hz
        top = cfg.max_frequency_ratio * self.sample_rate
        lo, hi = cfg.whine_band_hz
        hi = min(hi, top)
        whine_width = max(hi - lo, 1.0)

        def broadband_psd(f: np.ndarray) -> np.ndarray:
            shape = np.where(f < corner, 1.0, (np.maximum(f, 1e-9) / corner) ** -slope) * (f <= top)
            return shape

        f_grid = np.linspace(0, self.noise_rate / 2, 65537)
        bb_norm = np.trapezoid(broadband_psd(f_grid), f_grid)
        whine_rel = 10.0 ** ((cfg.whine_db - cfg.broadband_db) / 10.0)

        def psd(f: np.ndarray) -> np.ndarray:
            whine = ((f >= lo) & (f <= hi)) * (whine_rel / whine_width) if lo < hi else 0.0
            return broadband_psd(f) / bb_norm + whine

        self._noise_psd = psd
        self._noise_power = 1.0 + (whine_rel if lo < hi else 0.0)
        self.noise = coloured_noise(length, self.noise_rate, psd, rng, frame_length=8192, dtype=np.float32)[0]

    def _calibrate(self) -> None:
        """Scale tonal and broadband parts so that the hover A-weighted power matches LWA (+ spread)."""
        spec, cfg = self.spec, self.config
        freqs = self.harmonic_orders * spec.hover_rpm / 60.0
        tonal_power = spec.rotors * 0.5 * self.harmonic_amplitude**2  # rotors add incoherently
        tonal_total = float(tonal_power.sum())
        weights = 10.0 ** (a_weighting_db(freqs) / 10.0)
        tonal_a = float(np.sum(tonal_power * weights))
        self.broadband_scale = np.sqrt(tonal_total * 10.0 ** (cfg.broadband_db / 10.0))
        f_grid = np.linspace(1.0, self.noise_rate / 2, 65537)
        noise_a = float(np.trapezoid(self._noise_psd(f_grid) * 10.0 ** (a_weighting_db(f_grid) / 10.0), f_grid))
        total_a = tonal_a + self.broadband_scale**2 * noise_a
        # free field: Lp(1 m) = LW - 10 log10(4 pi)
        target = level_to_pressure(spec.lwa_db + self.flight_level_db - 10.0 * np.log10(4.0 * np.pi))
        self.scale = target / np.sqrt(total_a)

    # ------------------------------------------------------------------------------ evaluation

    def emitted(self, t: np.ndarray) -> np.ndarray:
        """Emitted pressure at 1 m (Pa) at emission times ``t`` (s, trajectory clock)."""
        t = np.asarray(t, dtype=np.float64)
        index, weight = uniform_lookup(t, self.control_times[0], self.config.control_rate, self.control_times.size)
        phase = lerp(self.shaft_phase, index, weight)  # rotors x N
        gain = lerp(self.rotor_gain, index, weight)
        size = self.config.wavetable_size
        pos = np.mod(phase, 2.0 * np.pi) * (size / (2.0 * np.pi))
        i0 = pos.astype(np.int64)
        frac = pos - i0
        i0 %= size
        rows = (np.arange(self.spec.rotors) * size)[:, None]
        table = self.wavetables.ravel()
        wave = table[rows + i0] * (1.0 - frac) + table[rows + (i0 + 1) % size] * frac
        out = np.einsum("rn,rn->n", gain, wave)
        out += self.broadband_scale * gain.mean(axis=0) * self._read_noise(t)
        return self.scale * out

    def _read_noise(self, t: np.ndarray) -> np.ndarray:
        """Cubic Lagrange interpolation of the oversampled noise at arbitrary times."""
        pos = (t - self.noise_t0) * self.noise_rate
        i = np.clip(np.floor(pos).astype(np.int64), 1, self.noise.size - 3)
        d = pos - i
        x = self.noise
        xm1, x0, x1, x2 = x[i - 1], x[i], x[i + 1], x[i + 2]
        return (
            -d * (d - 1) * (d - 2) / 6 * xm1
            + (d + 1) * (d - 1) * (d - 2) / 2 * x0
            - (d + 1) * d * (d - 2) / 2 * x1
            + (d + 1) * d * (d - 1) / 6 * x2
        )

    def hover_spectrum(self) -> tuple[np.ndarray, np.ndarray]:
        """Tonal line frequencies (Hz) and their powers (Pa^2 at 1 m) at hover, for checks."""
        freqs = self.harmonic_orders * self.spec.hover_rpm / 60.0
        return freqs, self.spec.rotors * 0.5 * (self.scale * self.harmonic_amplitude) ** 2
