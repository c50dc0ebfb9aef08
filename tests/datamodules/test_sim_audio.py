"""Physical realism of the simulated audio: delays, levels, Doppler, ground interference, noise."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import welch

from datamodules.simulate.acoustics import AudioConfig, render_audio
from datamodules.simulate.ambient import AmbientConfig
from datamodules.simulate.drone_sound import DroneSource, SourceConfig
from datamodules.simulate.drones import DRONES
from datamodules.simulate.microphones import distributed4
from datamodules.simulate.propagation import a_weighting_db, speed_of_sound
from datamodules.simulate.trajectory import Trajectory

FS = 48000.0
C = speed_of_sound(30.0)
STEADY = SourceConfig(rotor_offset_sigma=0.0, rpm_jitter_base=0.0, rpm_jitter_per_wind=0.0, rotor_am_sigma_db=0.0)
QUIET = AmbientConfig(level_dba=(-30.0, -30.0), hvac=False, wind_speed=(0.0, 0.0), self_noise_dba=-30.0)


def straight(start: np.ndarray, velocity: np.ndarray, t0: float = -2.0, t1: float = 4.0) -> Trajectory:
    times = np.linspace(t0, t1, 61)
    return Trajectory(times, start[None, :] + velocity[None, :] * times[:, None])


def render(trajectory, seconds=1.0, ground="none", source=STEADY, ambient=QUIET, seed=0, drone="mavic2"):
    config = AudioConfig(ground=ground, source=source, ambient=ambient)
    return render_audio(DRONES[drone], trajectory, seconds, np.random.default_rng(seed), config)


def test_tdoa_between_microphones_matches_geometry():
    mics = distributed4()
    drone = np.array([3.0, 8.0, 6.0])
    result = render(straight(drone, np.zeros(3)))
    x = result.samples.astype(np.float64)
    n = 2 * x.shape[1]
    spectra = np.fft.rfft(x, n)
    distances = np.linalg.norm(mics - drone, axis=1)
    for j in range(1, 4):
        cross = spectra[j] * np.conj(spectra[0])
        gcc = np.fft.irfft(cross / np.maximum(np.abs(cross), 1e-20), n)
        max_lag = int(np.ceil(np.linalg.norm(mics[j] - mics[0]) / C * FS)) + 2
        lags = np.concatenate([np.arange(0, max_lag + 1), np.arange(-max_lag, 0)])
        values = np.concatenate([gcc[: max_lag + 1], gcc[-max_lag:]])
        measured = lags[int(np.argmax(values))]
        true = (distances[j] - distances[0]) / C * FS
        assert abs(measured - true) <= 1.0, (j, measured, true)


def _a_weighted_spl(signal_pa: np.ndarray) -> float:
    f, psd = welch(signal_pa, FS, nperseg=8192)
    power = np.trapezoid(psd * 10 ** (a_weighting_db(np.maximum(f, 1.0)) / 10), f)
    return 10 * np.log10(power / 20e-6**2)


def test_level_falls_6db_per_doubling_and_is_calibrated():
    mic = distributed4()[0]
    direction = np.array([0.3, 0.6, 0.74]) / np.linalg.norm([0.3, 0.6, 0.74])
    levels = {}
    for r in (5.0, 10.0, 20.0):
        result = render(straight(mic + direction * r, np.zeros(3)))
        levels[r] = _a_weighted_spl(result.samples[0] * result.full_scale_pa)
    assert levels[5.0] - levels[10.0] == pytest.approx(6.02, abs=0.5)
    assert levels[10.0] - levels[20.0] == pytest.approx(6.02, abs=0.5)
    # LWA 81 dB(A) -> 81 - 11 - 20 = 50 dB(A) at 10 m, +-3 dB flight spread and +-3 dB directivity
    assert 44.0 < levels[10.0] < 56.0


def test_doppler_shift_of_an_approaching_drone():
    mic = distributed4()[0]
    direction = np.array([0.0, 0.6, 0.8])
    speed = 5.0
    trajectory = straight(mic + direction * 20.0, -direction * speed)
    result = render(trajectory, seconds=2.0)
    source = DroneSource(DRONES["mavic2"], trajectory, FS, np.random.default_rng(1), 0.0, STEADY)
    emitted = 20 * source.rpm[0, 0] / 60.0  # 10th blade-passing harmonic (2 blades)
    expected = emitted / (1.0 - speed / C)
    x = result.samples[0].astype(np.float64)
    spectrum = np.abs(np.fft.rfft(x * np.hanning(x.size)))
    f = np.fft.rfftfreq(x.size, 1 / FS)
    band = (f > emitted - 15) & (f < expected + 15)
    peak = f[band][np.argmax(spectrum[band])]
    assert abs(peak - expected) < 1.0
    assert expected - emitted > 25.0  # the shift is resolvable, so the test can fail


def test_ground_reflection_makes_the_predicted_comb():
    mic = distributed4()[0]  # 0.2 m above the roof
    drone = mic + np.array([5.0, 5.0, 7.0])
    trajectory = straight(drone, np.zeros(3))
    broadband = SourceConfig(**{**STEADY.__dict__, "broadband_db": 10.0})  # a flat-ish source for the ratio
    on = render(trajectory, seconds=2.0, ground="concrete", source=broadband).samples[0]
    off = render(trajectory, seconds=2.0, ground="none", source=broadband).samples[0]
    f, p_on = welch(on, FS, nperseg=4096)
    _, p_off = welch(off, FS, nperseg=4096)
    r1 = np.linalg.norm(drone - mic)
    r2 = np.linalg.norm(drone - mic * np.array([1, 1, -1]))
    predicted = np.abs(1 + 0.95 * r1 / r2 * np.exp(-2j * np.pi * f * (r2 - r1) / C)) ** 2
    band = (f > 200) & (f < 4000)
    measured_db = 10 * np.log10(p_on[band] / p_off[band])
    predicted_db = 10 * np.log10(predicted[band])
    assert np.corrcoef(measured_db, predicted_db)[0, 1] > 0.9
    notch = C / (2 * (r2 - r1))
    near = np.abs(f[band] - notch) < 15
    assert measured_db[near].min() < -10.0


def test_adc_grid_snr_metadata_and_determinism():
    trajectory = straight(np.array([2.0, 10.0, 8.0]), np.array([0.5, 0.0, 0.0]))
    loud = AmbientConfig(level_dba=(62.0, 62.0), wind_speed=(0.0, 0.0))
    soft = AmbientConfig(level_dba=(45.0, 45.0), wind_speed=(0.0, 0.0))
    a = render(trajectory, ambient=soft, source=SourceConfig(), seed=3)
    b = render(trajectory, ambient=soft, source=SourceConfig(), seed=3)
    c = render(trajectory, ambient=loud, source=SourceConfig(), seed=3)
    assert np.array_equal(a.samples, b.samples)
    codes = a.samples.astype(np.float64) * 32768
    assert np.array_equal(codes, np.rint(codes))
    # ambient (and the HVAC tied to it) 17 dB louder: SNR 17 dB lower, the drone is unchanged
    assert np.allclose(a.snr_db - c.snr_db, 17.0, atol=1.0)
    assert a.clipped_samples == 0
