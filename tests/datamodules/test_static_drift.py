"""Node drifts from a static source: found where one is heard throughout, never made up from a moving one."""

from __future__ import annotations

import numpy as np
import pytest

from datamodules.features.clock_calibration import (
    ClockCalibration,
    ClockCalibrationConfig,
    estimate_clock_offsets,
    static_drifts,
)
from datamodules.features.phase import SPEED_OF_SOUND, mic_pairs
from datamodules.features.static_drift import StaticDrift, _node_drifts, static_source_drift
from datamodules.recording import ArrayAudio
from datamodules.simulate.ambient import AmbientConfig
from datamodules.simulate.simulator import simulate_recording
from tests.helpers.flights import flying_m300

FS = 48000
MICS = np.array([[0.0, 0.0, 0.0], [1.6, 0.0, 0.1], [0.0, 1.6, 0.2], [1.6, 1.6, 0.0]])
DRIFTS = np.array([0.0, 12.0, -18.0, 25.0])  #: ppm, node 0 the reference


def _static_source(seconds: float, drifts: np.ndarray, snr_db: float = 0.0, seed: int = 0) -> ArrayAudio:
    """Noise from a source 11 m away heard by every microphone on its node's drifting clock (sample ``k`` taken at
    ``k / fs (1 + drift)``: linear interpolation, whose loss at 8 kHz is under 1 dB), plus noise of the same power
    that differs per microphone (``snr_db`` below the source)."""
    rng = np.random.default_rng(seed)
    count = int(seconds * FS)
    source = rng.standard_normal(count + FS)  # on the true clock, from 1 s before the first sample
    position = np.array([9.0, -6.0, 1.0])
    k = np.arange(count)
    heard = np.empty((len(MICS), count))
    for m, mic in enumerate(MICS):
        taken = k * (1 + drifts[m] * 1e-6) - np.linalg.norm(position - mic) / SPEED_OF_SOUND * FS + FS
        heard[m] = np.interp(taken, np.arange(source.size), source)
    noise = rng.standard_normal(heard.shape) * 10 ** (-snr_db / 20)
    return ArrayAudio((heard + noise).astype(np.float32), FS, 0.0, MICS)


def test_the_drifts_of_the_nodes_are_read_off_a_static_source():
    found = static_source_drift(_static_source(30.0, DRIFTS))
    assert found is not None
    assert found.drifts_ppm[0] == 0.0
    assert np.abs(found.drifts_ppm - DRIFTS).max() < 0.2, found
    assert found.share > 0.9 and found.stretches >= 10
    assert np.all(found.drifts_std_ppm[1:] > 0) and np.all(found.drifts_std_ppm < 0.2)


def test_without_a_static_source_there_is_no_drift():
    rng = np.random.default_rng(1)
    incoherent = ArrayAudio(rng.standard_normal((4, 20 * FS)).astype(np.float32), FS, 0.0, MICS)
    assert static_source_drift(incoherent) is None
    assert static_source_drift(_static_source(12.0, DRIFTS)) is None  # 6 stretches of 2 s: too few to tell


def test_stretches_holding_nan_samples_are_left_out():
    audio = _static_source(30.0, DRIFTS)
    samples = audio.read(0, audio.num_samples)
    samples[:, 5 * FS:7 * FS] = np.nan
    found = static_source_drift(ArrayAudio(samples, FS, 0.0, MICS))
    assert found is not None and np.abs(found.drifts_ppm - DRIFTS).max() < 0.2
    samples[:] = np.nan
    assert static_source_drift(ArrayAudio(samples, FS, 0.0, MICS)) is None


@pytest.fixture(scope="module")
def flying_drone():
    """15 s of a loud drone flying in quiet air with no static source (no HVAC), all nodes on one clock."""
    return simulate_recording(flying_m300(15.0), seed=6)


def test_a_moving_drone_is_not_taken_for_a_static_source(flying_drone):
    assert static_source_drift(flying_drone.audio) is None


def test_a_pair_whose_line_is_another_sources_is_left_out():
    pairs = mic_pairs(4)
    slopes = np.array([DRIFTS[j] - DRIFTS[i] for i, j in pairs])
    stds, shares = np.full(len(pairs), 0.05), np.ones(len(pairs))
    assert np.allclose(_node_drifts(pairs, slopes, stds, shares, 0.5, 1.0, 100.0, 30).drifts_ppm, DRIFTS)
    wrong = slopes.copy()
    wrong[0] += 30.0  # pair (0, 1) followed a moving source
    found = _node_drifts(pairs, wrong, stds, shares, 0.5, 1.0, 100.0, 30)
    assert np.allclose(found.drifts_ppm, DRIFTS)
    # without a pair to spare nothing checks the rest: no drifts
    few = np.array([0.6, 0.6, 0.6, 0.0, 0.0, 0.0])
    assert _node_drifts(pairs, slopes, stds, few, 0.5, 1.0, 100.0, 30) is None
    # two pairs that disagree and nothing to tell which is right: none
    assert _node_drifts(pairs, wrong, stds, np.array([1, 1, 1, 1, 0, 0.0]), 0.5, 1.0, 100.0, 30) is None


def test_the_calibration_corrects_for_the_static_drifts_and_fits_the_offsets_alone(monkeypatch):
    import datamodules.features.clock_calibration as calibration

    frames = 20
    measured = calibration.FrameMeasurements(np.arange(frames, dtype=float), np.full((frames, 4), 1e-3),
                                             np.zeros((frames, 6)), np.full(frames, 10.0))
    static = StaticDrift(DRIFTS.copy(), np.full(4, 0.05), np.zeros(6), 0.9, 30)
    fitted = ClockCalibration(np.array([0.0, 1e-3, 0.0, 0.0]), np.full(4, 1e-5), np.zeros(4), np.zeros(4),
                              frames=frames, residual_rms_s=1e-5)
    seen = {}

    def measure(audio, config, drifts_ppm=None):
        seen["drifts"] = drifts_ppm
        return measured

    def fit(mics, m, used, positions, config):
        seen["fit_drift"] = config.fit_drift
        return fitted

    monkeypatch.setattr(calibration, "static_drifts", lambda audio, config: static)
    monkeypatch.setattr(calibration, "measure", measure)
    monkeypatch.setattr(calibration, "_initial_positions", lambda mics, m, used, config: np.zeros((used.size, 3)))
    monkeypatch.setattr(calibration, "_fit", fit)
    audio = ArrayAudio(np.zeros((4, 48000), dtype=np.float32), 48000.0, 0.0, MICS)
    found = estimate_clock_offsets(audio)
    assert np.array_equal(seen["drifts"], DRIFTS) and seen["fit_drift"] is False
    assert np.array_equal(found.drifts_ppm, DRIFTS) and found.static_drift
    assert "drifts (ppm, from a static source)" in found.summary() and found.meta()["static_drift"] is True
    assert ClockCalibration.from_array(found.to_array()).static_drift
    estimate_clock_offsets(audio, ClockCalibrationConfig(static_drift=False))
    assert seen["drifts"] is None and seen["fit_drift"] is True  # switched off: offsets and drifts fitted


@pytest.mark.slow
def test_the_calibration_takes_the_static_sources_drifts_and_fits_the_offsets_alone():
    """A drone flying over a rooftop HVAC unit, the nodes on drifting clocks with offsets."""
    offsets, drifts = [0.0, 0.4e-3, -0.7e-3, 1.1e-3], [0.0, 9.0, -14.0, 6.0]
    ambient = AmbientConfig(level_dba=(50.0, 50.0), wind_speed=(0.0, 0.0), hvac_relative_db=(0.0, 0.0))
    recording = simulate_recording(flying_m300(30.0, ambient, clock_offset_s=offsets, clock_drift_ppm=drifts), seed=3)
    config = ClockCalibrationConfig()
    static = static_drifts(recording.audio, config)
    assert static is not None and np.abs(static.drifts_ppm - drifts).max() < 0.5, static
    found = estimate_clock_offsets(recording.audio, config)
    assert np.array_equal(found.drifts_ppm, static.drifts_ppm) and found.static_drift
    times = np.linspace(0.0, recording.audio.duration, 20)
    truth = np.asarray(offsets) + np.asarray(drifts) * 1e-6 * times[:, None]
    assert np.abs(found.offsets_at(times) - truth).max() < 5e-5, found.summary()
