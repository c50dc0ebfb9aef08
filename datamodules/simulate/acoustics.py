"""Render what each microphone records: the moving drone through air and ground, plus noise.

For every microphone the received pressure is the sum of the direct path and the ground image
path (``docs/simulation_sources.md`` sections 2.3-2.4):

    p_m(t) = D(psi) s(t_e) / r(t_e)  [* absorption(r)]  +  the same for the image source [* R(f, theta)]

where t_e solves the retarded-time equation t = t_e + |x(t_e) - p_m| / c by fixed-point
iteration (delay and Doppler follow from it), s is the drone's emitted pressure at 1 m
(:mod:`drone_sound`), D its vertical directivity, absorption the ISO 9613-1 attenuation over the
path and R the ground's plane-wave reflection coefficient. The frequency-dependent factors are
applied frame by frame in a short-time Fourier domain (21 ms frames), updated as r changes.
Noise (:mod:`ambient`) is added, then a 16-bit ADC with a 120 dB SPL full scale (MEMS acoustic
overload point) quantises the result [M]; the output is float32 in full-scale units.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.signal import butter, istft, sosfilt, stft

from datamodules.simulate.ambient import AmbientConfig, AmbientRealisation, render_ambient
from datamodules.simulate.clocks import resample_at_clock
from datamodules.simulate.drone_sound import DroneSource, SourceConfig, directivity_gain, lerp, uniform_lookup
from datamodules.simulate.drones import DroneSpec
from datamodules.simulate.microphones import mic_geometry
from datamodules.simulate.propagation import GROUNDS, absorption_db_per_m, level_to_pressure, speed_of_sound
from datamodules.simulate.trajectory import Trajectory
from datamodules.snr import FRAME_SECONDS, SnrSpectrum, snr_spectrum


@dataclass
class AudioConfig:
    """Audio simulation parameters; defaults from ``simulation_sources.md`` sections 2-3 and 7."""

    sample_rate: float = 48000.0  #: 48 kHz default; MMAUD-derived AAUTE code uses 46080 [V S3, S4]
    microphones: str | list = "distributed4"
    temperature_c: float = 30.0  #: Singapore daytime (MMAUD V1 GT dates) [V S2]
    humidity_pct: float = 75.0
    pressure_kpa: float = 101.325
    ground: str = "concrete"  #: 'concrete' (rooftop), 'asphalt', 'grass' or 'none'
    full_scale_spl_db: float = 120.0  #: SPL of a 0 dBFS sine (MEMS acoustic overload point) [M]
    bits: int = 16  #: ADC resolution; audio_common's default capture format is S16LE [M]
    #: per-channel clock offsets (s; None: shared clock): sample k is taken at true time k / fs * (1 + drift) + offset
    clock_offset_s: list[float] | None = None
    clock_drift_ppm: list[float] | None = None  #: per-channel clock drifts (ppm); see ``clocks.py``
    block_seconds: float = 4.0
    control_rate: float = 1000.0
    snr_band_hz: float = 100.0  #: SNR is reported for 100 Hz - fs/2 (``simulation_sources.md`` 2.5)
    source: SourceConfig = field(default_factory=SourceConfig)
    ambient: AmbientConfig = field(default_factory=AmbientConfig)


@dataclass
class AudioResult:
    """Rendered audio (float32, channels x samples, full-scale units) and what describes it."""

    samples: np.ndarray
    sample_rate: float
    mic_positions: np.ndarray
    snr_db: np.ndarray  #: per channel, drone vs everything else, 100 Hz - fs/2
    #: per channel, second and 25 Hz bin, drone vs everything else (ADC included); None under one second of audio
    snr_spectrum: SnrSpectrum | None
    ambient: AmbientRealisation
    flight_level_db: float
    clipped_samples: int
    full_scale_pa: float


@dataclass
class _Path:
    """A propagation path to one microphone on the control grid (receiver time)."""

    emission_time: np.ndarray
    distance: np.ndarray
    gain: np.ndarray
    incidence_cos: np.ndarray | None  #: None for the direct path


def _solve_path(
    trajectory: Trajectory, mic: np.ndarray, receive_times: np.ndarray, c: float, image: bool
) -> _Path:
    """Retarded times, distances and directivity gains for one mic (and its ground image)."""
    target = mic * np.array([1.0, 1.0, -1.0]) if image else mic
    emission = receive_times.copy()
    for _ in range(5):  # |v|/c < 0.02: converges to ~1e-10 s in a few steps
        source = trajectory.position(emission)
        distance = np.linalg.norm(source - target, axis=1)
        emission = receive_times - distance / c
    source = trajectory.position(emission)
    distance = np.linalg.norm(source - target, axis=1)
    elevation = np.arcsin(np.clip((target[2] - source[:, 2]) / distance, -1.0, 1.0))
    incidence = (source[:, 2] + mic[2]) / distance if image else None
    return _Path(emission, distance, directivity_gain(elevation) / distance, incidence)


def render_audio(
    spec: DroneSpec,
    trajectory: Trajectory,
    duration: float,
    rng: np.random.Generator,
    config: AudioConfig | None = None,
    wind_speed: float | None = None,
) -> AudioResult:
    """Simulate ``duration`` seconds of audio; sample n is at trajectory time ``n / fs``.

    The trajectory must start a little before 0 (the sound recorded at 0 left the drone r/c
    earlier).
    """
    config = config or AudioConfig()
    fs = config.sample_rate
    mics = mic_geometry(config.microphones)
    channels = mics.shape[0]
    num_samples = int(round(duration * fs))
    c = speed_of_sound(config.temperature_c)
    ground = None if config.ground == "none" else GROUNDS.get(config.ground)
    if config.ground != "none" and ground is None:
        raise ValueError(f"unknown ground {config.ground!r}; known: {sorted(GROUNDS)} or 'none'")

    noise, ambient = render_ambient(mics, num_samples, fs, c, rng, config.ambient, wind_speed)
    source = DroneSource(spec, trajectory, fs, rng, ambient.wind_speed, config.source)

    offsets = np.zeros(channels) if config.clock_offset_s is None else np.asarray(config.clock_offset_s, float)
    drifts = np.zeros(channels) if config.clock_drift_ppm is None else np.asarray(config.clock_drift_ppm, float)
    if offsets.shape != (channels,) or drifts.shape != (channels,):
        raise ValueError(f"clock offsets/drifts need one value per channel ({channels})")
    if offsets.any() or drifts.any():  # the microphone hears the noise at its own clock's times too
        noise = resample_at_clock(noise, fs, offsets, drifts)

    dt = 1.0 / config.control_rate
    grid = np.arange(-0.1, duration + 0.1 + dt, dt)  # receiver clock, with margins
    paths: list[list[_Path]] = []
    for m in range(channels):
        true_times = grid * (1.0 + drifts[m] * 1e-6) + offsets[m]
        mic_paths = [_solve_path(trajectory, mics[m], true_times, c, image=False)]
        if ground is not None:
            mic_paths.append(_solve_path(trajectory, mics[m], true_times, c, image=True))
        paths.append(mic_paths)

    frame, overlap = 1024, 768  # 21 ms Hann frames, 75 % overlap (perfect reconstruction)
    freqs = np.fft.rfftfreq(frame, 1.0 / fs)
    alpha = absorption_db_per_m(freqs, config.temperature_c, config.humidity_pct, config.pressure_kpa)
    block = int(config.block_seconds * fs)
    margin = 2048
    drone = np.empty((channels, num_samples), dtype=np.float32)
    for start in range(0, num_samples, block):
        stop = min(start + block, num_samples)
        lo, hi = start - margin, stop + margin
        t_rx = np.arange(lo, hi) / fs
        index, weight = uniform_lookup(t_rx, grid[0], config.control_rate, grid.size)
        for m in range(channels):
            total = np.zeros(hi - lo)
            for path in paths[m]:
                emission = lerp(path.emission_time, index, weight)
                signal = lerp(path.gain, index, weight) * source.emitted(emission)
                _, frame_offsets, spectra = stft(signal, fs, "hann", frame, overlap, boundary="even")
                frame_times = t_rx[0] + frame_offsets
                r = np.interp(frame_times, grid, path.distance)
                response = 10.0 ** (-alpha[:, None] * r[None, :] / 20.0)
                if path.incidence_cos is not None:
                    cos = np.interp(frame_times, grid, path.incidence_cos)
                    response = response * ground.reflection_coefficient(freqs[:, None], cos[None, :])
                total += istft(spectra * response, fs, "hann", frame, overlap)[1][: hi - lo]
            drone[m, start:stop] = total[margin:margin + stop - start]

    snr = _band_snr_db(drone, noise, fs, config.snr_band_hz)
    full_scale = np.sqrt(2.0) * level_to_pressure(config.full_scale_spl_db)
    digital, clipped = _quantise((drone + noise) / full_scale, config.bits)
    drone_share = drone / full_scale
    spectrum = None  # noise = all but the drone, ADC error too; recorded per whole frame (one second)
    if digital.shape[-1] >= round(FRAME_SECONDS * fs):
        spectrum = snr_spectrum(drone_share, digital - drone_share, fs)
    return AudioResult(digital, fs, mics, snr, spectrum, ambient, source.flight_level_db, clipped, full_scale)


def _band_snr_db(signal: np.ndarray, noise: np.ndarray, fs: float, low_hz: float) -> np.ndarray:
    """Per-channel power ratio (dB) of signal to noise above ``low_hz``."""
    sos = butter(4, low_hz, btype="highpass", fs=fs, output="sos")
    p_signal = np.mean(sosfilt(sos, signal, axis=1) ** 2, axis=1)
    p_noise = np.mean(sosfilt(sos, noise, axis=1) ** 2, axis=1)
    return 10.0 * np.log10(np.maximum(p_signal, 1e-30) / np.maximum(p_noise, 1e-30))


def _quantise(x: np.ndarray, bits: int) -> tuple[np.ndarray, int]:
    """Round to a ``bits``-bit ADC grid in [-1, 1), counting clipped samples."""
    levels = 2.0 ** (bits - 1)
    codes = np.rint(x * levels)
    clipped = int(np.count_nonzero((codes < -levels) | (codes > levels - 1)))
    np.clip(codes, -levels, levels - 1, out=codes)
    return (codes / levels).astype(np.float32), clipped
