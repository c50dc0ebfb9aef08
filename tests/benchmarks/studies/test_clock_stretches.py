"""The clock stretch study: the stretches it cuts, the truth it scores each estimate against, its refusals and table."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from benchmarks.studies import clock_stretches
from benchmarks.studies.clock_sensitivity import settings, with_clocks
from benchmarks.studies.clock_stretches import recording_rows, refusal_reason, stretch_errors, summary
from benchmarks.studies.common import true_clocks
from datamodules.features.clock_calibration import ClockCalibration, ClockCalibrationError
from datamodules.formats import discover_recordings
from datamodules.formats.mcap_file import read_mcap


def _estimate(offsets, drifts=(0.0, 0.0, 0.0), std=(0.0, 1e-5, 3e-5)) -> ClockCalibration:
    return ClockCalibration(np.array(offsets), np.array(std), np.array(drifts), np.zeros(3), 50, 1e-5)


def test_a_stretch_estimate_is_scored_at_its_centre_against_the_drifting_truth():
    offsets, drifts = np.array([0.0, 1e-3, -2e-3]), np.array([0.0, 20.0, -10.0])
    start, seconds = 30.0, 10.0
    at_start = offsets + drifts * 1e-6 * start  # a perfect estimate: the clocks at the stretch's first sample
    error, std = stretch_errors(_estimate(at_start, drifts), offsets, drifts, start, seconds)
    np.testing.assert_allclose(error, 0.0, atol=1e-15)
    error, _ = stretch_errors(_estimate(at_start + [0.0, 0.0, 5e-5]), offsets, drifts, start, seconds)
    np.testing.assert_allclose(error, [0.0, -drifts[1] * 1e-6 * 5.0, 5e-5 - drifts[2] * 1e-6 * 5.0], atol=1e-15)
    np.testing.assert_allclose(std, [0.0, np.hypot(1e-5, 2e-5), np.hypot(3e-5, 2e-5)])  # the estimator's floor


def test_refusals_are_counted_by_their_reason():
    assert refusal_reason(ClockCalibrationError("clock calibration found a coherent source in 3 blocks, needs 10")) \
        == "clock calibration found a coherent source in N blocks, needs N"
    assert refusal_reason(ClockCalibrationError("clock calibration is unreliable (residual RMS 40 us, limit 30)")) \
        == "clock calibration is unreliable"


def test_each_stretch_of_a_recording_is_estimated_from_its_own_samples(simulated_dir, tmp_path, monkeypatch):
    with_clocks(discover_recordings(simulated_dir)[0], tmp_path / "drift.mcap", dict(settings())["drift 50 ppm"])
    offsets, drifts = true_clocks(read_mcap(tmp_path / "drift.mcap").meta)
    seen = []

    def fake(samples: np.ndarray, rate: float, mics: np.ndarray):
        seen.append(samples.shape)
        if len(seen) == 2:
            return ClockCalibrationError("clock calibration found a coherent source in 2 blocks, needs 10"), 0.1, 0.1
        return _estimate(np.zeros(4), np.zeros(4), np.zeros(4)), 0.1, 0.2

    monkeypatch.setattr(clock_stretches, "estimate_stretch", fake)
    rows = pd.DataFrame(recording_rows(tmp_path / "drift.mcap", 1.5))  # 4 s: two whole stretches
    assert seen == [(4, 72000), (4, 72000)]
    first = rows[rows.stretch == 0]
    assert list(first.node) == [1, 2, 3] and (first.status == "ok").all()
    np.testing.assert_allclose(first.error_ms, -1e3 * (offsets + drifts * 1e-6 * 0.75)[1:])
    refused = rows[rows.stretch == 1]
    assert len(refused) == 1 and refused.status.iloc[0] == "refused"


def test_the_summary_counts_stretches_and_offsets():
    rows = pd.DataFrame(
        [{"recording": "a", "stretch": 0, "seconds": 10.0, "status": "ok", "node": n, "error_ms": e, "std_ms": 0.05,
          "cpu_s": 2.0} for n, e in ((1, 0.01), (2, -0.07), (3, 0.2))]
        + [{"recording": "a", "stretch": 1, "seconds": 10.0, "status": "refused", "reason": "too few", "cpu_s": 1.0}])
    line = summary(rows).splitlines()[2]
    assert line.startswith("| 10 s | 1 / 1 | too few: 1 | 66.7% / 33.3% | 0.070 ms | 33% / 67% | 2.0 / 1.0 s |"), line


def test_a_folder_without_recordings_is_one_line(tmp_path):
    with pytest.raises(SystemExit, match="no recordings found"):
        clock_stretches.main(["--data", str(tmp_path)])
