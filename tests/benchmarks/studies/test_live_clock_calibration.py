"""The live clock calibration study: queueing behind a slow update, offset errors after the start, its summary."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from benchmarks.studies.live_clock_calibration import offset_rows, queued_latency, summary
from datamodules.features.clock_calibration import ClockCalibration


def test_a_slow_update_holds_up_the_rows_behind_it_until_the_stream_catches_up():
    compute = np.full(30, 0.02)
    compute[5] = 1.0  # the estimate, in the update of the block that completes its seconds
    latency = queued_latency(compute, hop=0.1)
    assert latency[:5] == pytest.approx(0.02)
    assert latency[5] == pytest.approx(1.0)
    # the next block arrived at 0.6 s and starts when the slow one ends (1.5 s): 0.9 s + its own 0.02 s
    assert latency[6] == pytest.approx(0.92)
    assert np.all(np.diff(latency[5:18]) < 0)  # each later block waits 0.08 s less
    assert latency[-1] == pytest.approx(0.02)  # caught up


def test_offset_errors_are_taken_from_where_the_correction_starts():
    offsets, drifts = np.array([0.0, 1e-3, -2e-3]), np.array([0.0, 10.0, 0.0])
    estimate = ClockCalibration(np.array([0.0, 1e-3, -2e-3 + 2e-5]), np.array([0.0, 1e-5, 1e-5]),
                                np.zeros(3), np.zeros(3), frames=50, residual_rms_s=1e-5)  # node 1's drift missed
    once = SimpleNamespace(calibration=estimate, history=[(30.0, estimate)], estimates=[estimate])
    rows = offset_rows(once, offsets, drifts, 30.0, 60.0)
    assert [r["node"] for r in rows] == [1, 2]
    assert rows[0]["error_ms"] == pytest.approx(-0.3)  # 10 ppm x 30 s
    assert rows[0]["max_error_ms"] == pytest.approx(0.6) and rows[0]["drift_error_ppm"] == pytest.approx(-10.0)
    assert rows[1]["error_ms"] == pytest.approx(0.02) and rows[1]["std_ms"] == pytest.approx(0.01)
    assert np.isnan(rows[0]["max_error_once_ms"])
    # a run that follows the clocks: from 45 s on its correction has node 1's drift; each correction counts
    # from the second it started, so the largest error is the first one's just before 45 s (44.5 s on the grid)
    found = ClockCalibration(np.array([0.0, 1e-3, -2e-3]), np.full(3, 1e-5), np.array([0.0, 10.0, 0.0]),
                             np.zeros(3), frames=100, residual_rms_s=1e-5)
    followed = SimpleNamespace(calibration=found, history=[(30.0, estimate), (45.0, found)],
                               estimates=[estimate, found])
    rows = offset_rows(followed, offsets, drifts, 30.0, 60.0, once)
    assert rows[0]["error_ms"] == pytest.approx(-0.3) and rows[0]["max_error_ms"] == pytest.approx(0.445)
    assert rows[0]["max_error_once_ms"] == pytest.approx(0.6) and rows[0]["estimates"] == 2
    assert rows[0]["drift_error_ppm"] == pytest.approx(0.0)


def test_summary_pools_the_calibrated_flights_and_counts_the_refused():
    base = {"condition": "default", "clock_seconds": 30.0, "estimate_cpu_s": 5.0, "worst_queued_s": 5.2}

    def stream(shared: float, uncalibrated: float, once: float, followed: float, rows: int) -> dict[str, float]:
        return {"E_stream_shared": shared, "E_stream_uncalibrated": uncalibrated, "E_stream_once": once,
                "E_stream_calibrated": followed, "stream_rows": rows}

    e = pd.DataFrame([
        {**base, "status": "ok", "once_calibrated": True, "rows": 100, "E_raw_shared": 2.0,
         "E_raw_uncalibrated": 10.0, "E_raw_once": 3.0, "E_raw_calibrated": 2.5,
         "E_smooth_shared": 1.5, "E_smooth_uncalibrated": 9.0, "E_smooth_once": 2.5, "E_smooth_calibrated": 2.0,
         "E_settled_shared": 1.0, "E_settled_uncalibrated": 8.0, "E_settled_once": 1.4, "E_settled_calibrated": 1.0,
         "detected_shared": 1.0, "detected_once": 0.6, "detected_calibrated": 0.8, **stream(2.0, 10.0, 3.0, 2.0, 300)},
        {**base, "status": "ok", "once_calibrated": False, "rows": 300, "E_raw_shared": 4.0,
         "E_raw_uncalibrated": 14.0, "E_raw_once": 14.0, "E_raw_calibrated": 4.5,
         "E_smooth_shared": 3.5, "E_smooth_uncalibrated": 13.0, "E_smooth_once": 13.0, "E_smooth_calibrated": 4.0,
         "E_settled_shared": 3.0, "E_settled_uncalibrated": 12.0, "E_settled_once": 12.0,
         "E_settled_calibrated": 3.4, "detected_shared": 0.8, "detected_once": 0.0, "detected_calibrated": 0.6,
         **stream(4.0, 14.0, 14.0, 5.0, 300)},
        {**base, "status": "refused", **stream(6.0, 12.0, 8.0, 8.0, 600)}])
    o = pd.DataFrame([{"condition": "default", "clock_seconds": 30.0, "error_ms": err, "std_ms": 0.01,
                       "max_error_ms": abs(err) + 0.01, "max_error_once_ms": abs(err) + 0.1}
                      for err in (0.005, -0.015, 0.03)])
    line = summary(e, o).splitlines()[2]
    assert line.startswith("| default | 30 | 1 / 2 of 3 | 3.50 / 13.00 / 11.25 / 4.00 | 3.00 / 12.00 / 10.38 / 3.50 | "
                           "2.50 / 11.00 / 9.35 / 2.80 | 85% / 15% / 65% | 0.015 / 0.030 |")
    # every flight from S, the refused one too (it falls back), pooled by rows
    assert "| 0.130 / 0.040 | 33% / 67% | 4.50 / 12.00 / 8.25 / 5.75 |" in line
