"""The clock calibration study: the truth it reads, the errors it measures, its tables (failures included)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from benchmarks.studies.clock_calibration import (
    e_table,
    error_table,
    flight_e_table,
    flight_table,
    offset_errors,
    true_clocks,
)
from datamodules.features.clock_calibration import ClockCalibration


def test_truth_is_relative_to_node_0_and_errors_cover_the_drift():
    meta = {"clocks_truth": {"effective_offsets_s": [1e-3, 2e-3, 0.0], "drifts_ppm": [10.0, 10.0, -10.0]}}
    offsets, drifts = true_clocks(meta)
    assert np.allclose(offsets, [0.0, 1e-3, -1e-3]) and np.allclose(drifts, [0.0, 0.0, -20.0])
    estimate = ClockCalibration(np.array([0.0, 1.01e-3, -1e-3]), np.zeros(3), np.zeros(3), np.zeros(3), frames=5,
                                residual_rms_s=0.0)  # node 2's drift missed: 20 ppm x 60 s = 1.2 ms at the end
    first, worst = offset_errors(estimate, offsets, drifts, 60.0)
    assert first == pytest.approx([0.0, 1e-5, 0.0], abs=1e-12)
    assert worst == pytest.approx([0.0, 1e-5, 1.2e-3], abs=1e-12)
    with pytest.raises(ValueError, match="no clocks_truth"):
        true_clocks({})


def test_tables_count_failed_flights():
    ok = {"condition": "quiet", "recording": "a", "drone": "m300", "status": "ok", "seconds": 3.0, "std_ms": 0.02,
          "frames": 100}
    rows = [{**ok, "node": n, "error0_ms": e, "max_error_ms": abs(e) + 0.01} for n, e in ((1, 0.01), (2, -0.03))]
    rows += [{"condition": "quiet", "recording": "b", "drone": "avata", "node": n, "status": "failed: too quiet",
              "seconds": 1.0} for n in (1, 2)]
    frame = pd.DataFrame(rows)
    line = error_table(frame).splitlines()[2]
    assert line.startswith("| quiet | 4 | 2 | 0.020 / ") and "| 2 of 4 |" in line  # 0.02, 0.04 within 0.05 ms
    flights = flight_table(frame).splitlines()
    assert "+0.010 +- 0.020 / -0.030 +- 0.020" in flights[2] and "failed: too quiet" in flights[3]
    errors = pd.DataFrame([{"condition": "quiet", "shared": 2.0, "uncalibrated": 9.0, "calibrated": 2.2,
                            "corrected": 4, "recordings": 5, "shared_corrected": 1.5,
                            "calibrated_corrected": 1.2}]).set_index("condition")
    assert e_table(errors).splitlines()[2].endswith("| 2.20 m | +10% | 4 of 5 | 1.50 / 1.20 m (-20%) |")
    flights = pd.DataFrame([{"condition": "quiet", "recording": "b", "drone": "avata", "shared": 1.0,
                             "uncalibrated": 7.0, "calibrated": 6.5, "corrected": False}])
    assert flight_e_table(flights).splitlines()[2] == "| quiet | b | avata | 1.00 m | 7.00 m | 6.50 m | no |"
