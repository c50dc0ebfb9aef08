"""Everything the microphones hear that is not the drone: ambient field, HVAC, wind, self-noise.

Defaults (``docs/simulation_sources.md`` section 2.5 and 7):
- diffuse ambient of 45-62 dB(A) drawn per recording, pink-to-red spectrum (PSD ~ f^-p,
  p ~ U(1, 2)), spatially coherent between microphones as sinc(k d) [M]; its level wanders
  slowly by 2 dB rms (traffic, distant machinery) [E];
- rooftop HVAC: a static point source with 50 Hz mains harmonics (Singapore) and fan noise,
  at 0-10 dB below the ambient at the rig [E; "optional HVAC tones at 50/100 Hz harmonics"];
- wind noise at the capsule: incoherent between microphones, below ~300 Hz, intermittent with
  gusts, p_rms ~ rho I U^2 with turbulence intensity I = 0.1, minus 25 dB for a foam windscreen
  (20-30 dB, S30/S31) [E]; wind speed 0-4 m/s per recording [E];
- microphone self-noise 30 dB(A) (a MEMS capsule with 64 dB SNR re 94 dB SPL) [M].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datamodules.simulate.noise import coloured_noise, ou_process
from datamodules.simulate.propagation import AIR_DENSITY, a_weighting_db, level_to_pressure


@dataclass
class AmbientConfig:
    """Noise-field parameters (sources in the module docstring)."""

    level_dba: tuple[float, float] = (45.0, 62.0)
    spectral_slope: tuple[float, float] = (1.0, 2.0)
    low_corner_hz: float = 50.0
    level_wander_db: float = 2.0
    level_wander_time_constant: float = 5.0
    hvac: bool = True
    hvac_position: tuple[float, float, float] = (9.0, -6.0, 1.0)
    hvac_relative_db: tuple[float, float] = (-10.0, 0.0)
    mains_hz: float = 50.0
    wind_speed: tuple[float, float] = (0.0, 4.0)
    wind_turbulence_intensity: float = 0.1
    windscreen_db: float = 25.0
    wind_corner_hz: float = 40.0
    wind_cutoff_hz: float = 300.0
    gust_sigma: float = 0.3  #: relative std of the wind speed
    gust_time_constant: float = 2.0
    self_noise_dba: float = 30.0


def _a_weighted_variance(psd, sample_rate: float) -> float:
    f = np.linspace(1.0, sample_rate / 2, 200001)
    return float(np.trapezoid(psd(f) * 10.0 ** (a_weighting_db(f) / 10.0), f))


def _scaled_psd(shape, target_dba: float, sample_rate: float):
    """A PSD of the given shape whose A-weighted level is ``target_dba``."""
    scale = level_to_pressure(target_dba) ** 2 / _a_weighted_variance(shape, sample_rate)
    return lambda f: scale * shape(f)


def diffuse_coherence(mic_positions: np.ndarray, speed_of_sound: float):
    """Coherence of a spherically isotropic field: sinc(2 f d_ij / c) (numpy's normalised sinc)."""
    distance = np.linalg.norm(mic_positions[:, None, :] - mic_positions[None, :, :], axis=-1)

    def coherence(f: np.ndarray) -> np.ndarray:
        return np.sinc(2.0 * f[:, None, None] * distance[None] / speed_of_sound).astype(np.complex128)

    return coherence


def _fractional_delay(signal: np.ndarray, delay_samples: float) -> np.ndarray:
    """Delay by a (fractional) number of samples with an exact FFT phase shift (circular)."""
    n = signal.size
    spectrum = np.fft.rfft(signal)
    spectrum *= np.exp(-2j * np.pi * np.fft.rfftfreq(n) * delay_samples)
    return np.fft.irfft(spectrum, n)


@dataclass
class AmbientRealisation:
    """The drawn per-recording values, kept for the metadata."""

    level_dba: float
    slope: float
    wind_speed: float
    hvac_dba: float | None


def render_ambient(
    mic_positions: np.ndarray,
    num_samples: int,
    sample_rate: float,
    speed_of_sound: float,
    rng: np.random.Generator,
    config: AmbientConfig | None = None,
    wind_speed: float | None = None,
) -> tuple[np.ndarray, AmbientRealisation]:
    """All noise at the microphones (Pa, channels x samples, float32) and what was drawn."""
    config = config or AmbientConfig()
    channels = mic_positions.shape[0]
    level = float(rng.uniform(*config.level_dba))
    slope = float(rng.uniform(*config.spectral_slope))
    wind = float(rng.uniform(*config.wind_speed)) if wind_speed is None else float(wind_speed)
    corner = config.low_corner_hz

    def ambient_shape(f: np.ndarray) -> np.ndarray:
        return 1.0 / (1.0 + (np.maximum(f, 1e-9) / corner) ** slope)

    out = coloured_noise(num_samples, sample_rate, _scaled_psd(ambient_shape, level, sample_rate), rng,
                         channels=channels, coherence=diffuse_coherence(mic_positions, speed_of_sound),
                         dtype=np.float32)
    dt = 1.0 / 100.0
    control = int(num_samples / sample_rate / dt) + 2
    wander = ou_process(control, dt, config.level_wander_db, config.level_wander_time_constant, rng)
    t_audio = np.arange(num_samples) / sample_rate
    out *= (10.0 ** (np.interp(t_audio, np.arange(control) * dt, wander) / 20.0)).astype(np.float32)

    hvac_dba = None
    if config.hvac:
        hvac_dba = level + float(rng.uniform(*config.hvac_relative_db))
        out += _render_hvac(mic_positions, num_samples, sample_rate, speed_of_sound, hvac_dba, rng, config)

    if wind > 0:
        out += _render_wind(channels, num_samples, sample_rate, wind, rng, config)

    def white(f: np.ndarray) -> np.ndarray:
        return np.ones_like(f)

    self_psd = _scaled_psd(white, config.self_noise_dba, sample_rate)
    out += (rng.standard_normal((channels, num_samples)) * np.sqrt(self_psd(np.array([1.0]))[0] * sample_rate / 2)
            ).astype(np.float32)
    return out, AmbientRealisation(level, slope, wind, hvac_dba)


def _render_hvac(mic_positions, num_samples, sample_rate, speed_of_sound, level_dba, rng, config) -> np.ndarray:
    """A static HVAC unit: mains hum harmonics plus fan noise, delayed and spread to each mic."""
    t = np.arange(num_samples) / sample_rate
    hum = np.zeros(num_samples)
    for k in range(1, 11):
        hum += np.cos(2 * np.pi * config.mains_hz * k * t + rng.uniform(0, 2 * np.pi)) / k

    def fan_shape(f: np.ndarray) -> np.ndarray:
        return 1.0 / (1.0 + (np.maximum(f, 1e-9) / 200.0) ** 2)

    fan = coloured_noise(num_samples, sample_rate, fan_shape, rng)[0]
    source = hum / np.sqrt(np.mean(hum**2)) * 0.5 + fan / np.std(fan)
    # calibrate the A-weighted level at the rig centre via the spectrum of the emitted signal
    spectrum = np.abs(np.fft.rfft(source)) ** 2
    weights = 10.0 ** (a_weighting_db(np.fft.rfftfreq(num_samples, 1 / sample_rate)) / 10.0)
    weighted_rms = np.sqrt(np.sum(spectrum * weights) / np.sum(spectrum)) * np.std(source)
    position = np.asarray(config.hvac_position)
    centre_distance = np.linalg.norm(position - mic_positions.mean(axis=0))
    source *= level_to_pressure(level_dba) * centre_distance / weighted_rms
    out = np.empty((mic_positions.shape[0], num_samples), dtype=np.float32)
    for m, mic in enumerate(mic_positions):
        r = float(np.linalg.norm(position - mic))
        out[m] = _fractional_delay(source, r / speed_of_sound * sample_rate) / r
    return out


def _render_wind(channels, num_samples, sample_rate, wind_speed, rng, config) -> np.ndarray:
    """Gusty wind noise, independent per capsule, below ``wind_cutoff_hz``."""
    rms = AIR_DENSITY * config.wind_turbulence_intensity * wind_speed**2 * 10.0 ** (-config.windscreen_db / 20.0)

    def wind_shape(f: np.ndarray) -> np.ndarray:
        return 1.0 / (1.0 + (f / config.wind_corner_hz) ** 2) * (f <= config.wind_cutoff_hz)

    f = np.linspace(0, sample_rate / 2, 100001)
    psd_scale = rms**2 / np.trapezoid(wind_shape(f), f)
    noise = coloured_noise(num_samples, sample_rate, lambda x: psd_scale * wind_shape(x), rng,
                           channels=channels, dtype=np.float32)
    dt = 1.0 / 100.0
    control = int(num_samples / sample_rate / dt) + 2
    t_audio = np.arange(num_samples) / sample_rate
    # gusts are larger than the array (U x 2 s ~ metres), so one envelope serves all capsules;
    # wind-noise pressure scales with U^2, normalised to keep the mean power
    gust = np.maximum(1.0 + ou_process(control, dt, config.gust_sigma, config.gust_time_constant, rng), 0.0)
    envelope = gust**2 / np.sqrt(np.mean(gust**4))
    noise *= np.interp(t_audio, np.arange(control) * dt, envelope).astype(np.float32)[None, :]
    return noise
