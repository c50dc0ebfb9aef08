"""The in-memory data model."""

from __future__ import annotations

import numpy as np
import pytest

from datamodules.recording import (
    ArrayAudio,
    Recording,
    RecordingError,
    Track,
    check_monotonic,
    ns_to_seconds,
    seconds_to_ns,
)


def test_ns_round_trip_is_exact_at_unix_epochs():
    rng = np.random.default_rng(0)
    t = 1.69e9 + rng.uniform(0, 1e6, 10000)
    assert np.array_equal(ns_to_seconds(seconds_to_ns(t)), t)
    # the naive t * 1e9 loses up to 256 ns at this epoch; ours keeps the nearest nanosecond
    assert np.all(np.abs(seconds_to_ns(t) - np.array([round(v * 1e9) for v in t])) <= 256)


def test_audio_window_is_causal_and_checked():
    fs = 1000.0
    samples = np.tile(np.arange(5000, dtype=np.float32), (2, 1))
    audio = ArrayAudio(samples, fs, t0=100.0, mic_positions=np.zeros((2, 3)))
    window = audio.window(t_end=102.0, seconds=0.5)
    assert window.shape == (2, 500)
    assert window[0, -1] == 1999.0  # the last sample is the one just before t_end
    with pytest.raises(RecordingError, match="outside the audio"):
        audio.window(t_end=100.2, seconds=0.5)
    with pytest.raises(RecordingError, match="one mic position per channel"):
        ArrayAudio(samples, fs, 0.0, np.zeros((3, 3)))


def test_track_checks_lengths_and_interpolates_valid_points():
    track = Track([0.0, 1.0, 2.0], [[0, 0, 0], [100, 100, 100], [2, 2, 2]], valid=[True, False, True])
    assert np.allclose(track.interpolate(np.array([1.0])), [[1.0, 1.0, 1.0]])
    with pytest.raises(RecordingError, match="timestamps but"):
        Track([0.0, 1.0], [[0, 0, 0]])


def test_monotonic_check_names_the_stream():
    with pytest.raises(RecordingError, match="/ground_truth: timestamps must increase"):
        check_monotonic(np.array([0.0, 0.1, 0.1, 0.3]), "/ground_truth")


def test_unknown_drone_is_rejected():
    with pytest.raises(RecordingError, match="unknown drone type"):
        Recording("s", "bebop")


def test_window_ends_on_the_sample_boundary_of_a_rounded_absolute_stamp():
    """Stamps t0 + k / 10 read back from nanoseconds near 1.7e9 s must end their window on sample k * 4800."""
    fs, t0 = 48000.0, 1692845357.0
    audio = ArrayAudio(np.zeros((1, 480000), np.float32), fs, t0=t0, mic_positions=np.zeros((1, 3)))
    stamps = ns_to_seconds(seconds_to_ns(t0 + np.arange(100) * 0.1))
    assert [audio.sample_index(t) for t in stamps] == [k * 4800 for k in range(100)]
    assert audio.sample_index(t0 + 0.5 / fs) == 0  # half a sample in: still the sample before
    assert audio.sample_index(t0 + 1.0 / fs - 3e-6) == 0  # 3 us short of sample 1 (0.14 samples) is not sample 1
