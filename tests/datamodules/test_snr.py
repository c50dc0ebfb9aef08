"""SNR spectra: exact from the simulator's parts, estimated from the audio alone, carried in the metadata."""

from __future__ import annotations

import numpy as np
import pytest

from datamodules.formats.mcap_file import read_mcap, write_mcap
from datamodules.recording import ArrayAudio
from datamodules.simulate.simulator import SimulationConfig, simulate_recording
from datamodules.snr import SnrSpectrum, estimate_snr_spectrum, recording_snr, snr_spectrum

FS = 8000.0


def test_exact_spectrum_of_a_tone_over_white_noise():
    rng = np.random.default_rng(0)
    t = np.arange(int(3 * FS)) / FS
    noise = rng.standard_normal((2, t.size))
    tone = np.stack([np.sin(2 * np.pi * 1000.0 * t), np.zeros_like(t)])
    spectrum = snr_spectrum(tone, noise, FS)
    assert spectrum.db.shape == (2, 3, int(FS / 2 / 25) + 1)
    tone_bin = int(1000.0 / spectrum.bin_hz)
    # a unit sine holds 1/2 of power in its bin's main lobe; white noise of unit variance has PSD 2 / fs per Hz
    assert spectrum.db[0, :, tone_bin].mean() > 10 * np.log10(0.5 / (2 / FS * 25 * 1.5)) - 2
    assert np.all(spectrum.db[0, :, tone_bin + 10] < -40) and np.all(spectrum.db[1] == -60.0)
    assert spectrum.source == "simulator"


def test_estimate_from_audio_alone_finds_the_drone_above_the_noise_floor():
    rng = np.random.default_rng(1)
    seconds, loud = 20, slice(5, 9)
    noise = rng.standard_normal((3, int(seconds * FS)))
    drone = np.zeros_like(noise)
    drone[:, int(loud.start * FS): int(loud.stop * FS)] = np.sqrt(10.0) * rng.standard_normal((3, int(4 * FS)))
    spectrum = estimate_snr_spectrum(ArrayAudio((noise + drone).astype(np.float32), FS, 0.0, np.zeros((3, 3))))
    assert spectrum.source == "estimated"
    band = slice(4, 150)  # 100 Hz - 3.7 kHz
    assert np.median(spectrum.db[:, loud, band]) == pytest.approx(10.0, abs=0.5)
    assert np.median(spectrum.db[:, 12:, band]) < -5


def test_window_snr_weights_frames_by_overlap():
    spectrum = SnrSpectrum(np.array([[[0.0], [10.0], [20.0]]]))
    assert spectrum.window_snr(0.5, 2.0)[0, 0] == pytest.approx((1 * 0.5 + 10 * 1.0) / 1.5)
    assert spectrum.window_snr(5.0, 6.0)[0, 0] == pytest.approx(100.0)  # beyond the frames: the nearest one


def test_simulator_records_the_spectrum_in_the_metadata(tmp_path):
    config = SimulationConfig(duration=3.0, lidar_sensors=(), camera=False)
    recording = simulate_recording(config, seed=3)
    path = tmp_path / "one.mcap"
    write_mcap(recording, path)
    spectrum = recording_snr(read_mcap(path))
    assert spectrum.source == "simulator" and spectrum.db.shape == (4, 3, 961)
    # the drone's low harmonics stand above the ambient noise, the top of the band holds next to nothing of it
    assert np.median(spectrum.db[:, :, 4:40]) > np.median(spectrum.db[:, :, 800:]) + 10
    # the audio itself carries the same drone: estimating from it sees it in the same bins
    del recording.meta["audio"]["snr_spectrum"]
    estimated = recording_snr(recording)
    assert estimated.source == "estimated" and estimated.db.shape == spectrum.db.shape
