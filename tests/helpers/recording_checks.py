"""Assertions shared by tests that compare recordings."""

from __future__ import annotations

import numpy as np

from datamodules.recording import Recording


def assert_same_recording(a: Recording, b: Recording) -> None:
    assert (a.sequence_id, a.drone, a.meta) == (b.sequence_id, b.drone, b.meta)
    assert a.audio.sample_rate == b.audio.sample_rate and a.audio.t0 == b.audio.t0
    assert np.array_equal(a.audio.mic_positions, b.audio.mic_positions)
    assert np.array_equal(a.audio.read(0, a.audio.num_samples), b.audio.read(0, b.audio.num_samples))
    assert set(a.lidar) == set(b.lidar)
    for sensor in a.lidar:
        assert np.array_equal(a.lidar[sensor].timestamps, b.lidar[sensor].timestamps)
        for i in range(len(a.lidar[sensor])):
            ca, cb = a.lidar[sensor][i], b.lidar[sensor][i]
            assert np.array_equal(ca.points, cb.points) and np.array_equal(ca.intensity, cb.intensity)
            assert np.array_equal(ca.origin, cb.origin)
    assert np.array_equal(a.frames.timestamps, b.frames.timestamps)
    assert all(a.frames[i] == b.frames[i] for i in range(len(a.frames)))
    for ta, tb in ((a.ground_truth, b.ground_truth), (a.pseudo_labels, b.pseudo_labels)):
        assert (ta is None) == (tb is None)
        if ta is None:
            continue
        assert np.array_equal(ta.timestamps, tb.timestamps) and np.array_equal(ta.valid, tb.valid)
        assert np.array_equal(ta.xyz[ta.valid], tb.xyz[tb.valid])
        assert ta.quality.keys() == tb.quality.keys()
        assert all(np.array_equal(ta.quality[k], tb.quality[k]) for k in ta.quality)
