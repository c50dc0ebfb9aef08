"""The student check and the audio probe: they run end to end and measure what they claim."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.studies import audio_probe, student_check

SPLIT = {"train": ["sim11-0000-avata"], "val": ["sim11-0001-m300"], "test": ["sim11-0002-mavic2"]}


def test_band_levels_measure_level_differences_between_microphones():
    fs = 48000.0
    t = np.arange(int(0.5 * fs)) / fs
    tone = np.sin(2 * np.pi * 1000.0 * t)
    levels = audio_probe.band_levels(np.stack([2.0 * tone, tone]), fs)
    band = int(np.searchsorted(audio_probe.BAND_EDGES_HZ, 1000.0)) - 1
    assert levels.shape == (2, 2, audio_probe.BAND_EDGES_HZ.size - 1)
    assert levels[0, 0, band] - levels[0, 1, band] == pytest.approx(20 * np.log10(2.0), abs=1e-6)
    assert levels[1, 0, band] == pytest.approx(-levels[1, 1, band], abs=1e-6)  # relative to the array mean


def test_probe_finds_position_information_when_levels_carry_it():
    rng = np.random.default_rng(0)
    positions = rng.uniform([-2, -5, 1], [8, 25, 20], size=(600, 3))
    mics = np.array([[0, 0, 0.2], [3, 0, 0.7], [3, 3, 1.2], [0, 3, 1.7]])
    distance = np.linalg.norm(positions[:, None] - mics[None], axis=-1)  # N x 4
    levels = -20 * np.log10(distance)[:, None, :, None] + rng.normal(0, 0.5, (600, 2, 4, 3))
    train, test = (levels[:450], positions[:450]), (levels[450:], positions[450:])
    constant = np.linalg.norm(test[1] - train[1].mean(axis=0), axis=1).mean()
    assert audio_probe.fit_and_score(train, test, np.ones(3, dtype=bool)) < 0.5 * constant
    shuffled = (train[0], train[1][rng.permutation(450)])  # levels unrelated to the targets
    assert audio_probe.fit_and_score(shuffled, test, np.ones(3, dtype=bool)) > 0.9 * constant


def test_probe_runs_on_recordings(labelled_dir):
    result = audio_probe.run([labelled_dir], stride=4, split=SPLIT)
    assert result["train_windows"] > 0 and result["test_windows"] > 0
    assert all(np.isfinite(result[k]) and result[k] > 0 for k in ("constant_E", "probe_E_low", "probe_E_all"))


def test_student_check_tests_the_best_validation_checkpoint(labelled_dir, feature_cache, tmp_path):
    result = student_check.run([labelled_dir], alpha=1.0, epochs=2, seed=0, cache=feature_cache, out=tmp_path,
                               split=SPLIT)
    assert result["best_epoch"] in (0.0, 1.0)
    assert (tmp_path / "alpha1").is_dir()
    assert result["train_sequences"] == 1 and result["test_sequences"] == 1
    assert np.isfinite(result["test_E_ideal"]) and result["constant_E"] > 0
