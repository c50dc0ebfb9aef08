"""The phase benchmark's scoring: errors by detection, range and drone, and the leave-one-flight-out constant."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.studies.phase_bench import constant_errors, smooth_flights, summarise
from zoo.smoothing import make_smoother, smooth_detected


def test_constant_is_the_mean_ground_truth_of_the_other_flights():
    gt = np.array([[0.0, 10.0, 0.0], [0.0, 12.0, 0.0], [0.0, 20.0, 0.0]])
    flight = np.array(["a", "a", "b"])
    np.testing.assert_allclose(constant_errors(gt, flight), [10.0, 8.0, 9.0])


def test_summary_splits_errors_by_detection_range_and_drone():
    gt = np.array([[0.0, 5.0, 0.0], [0.0, 15.0, 0.0], [0.0, 30.0, 0.0], [0.0, 15.0, 0.0]])
    position = gt + np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 4.0], [0, 0, 8.0]])
    detected = np.array([True, True, False, True])
    drone = np.array(["m300", "m300", "avata", "avata"])
    flight = np.array(["x", "x", "y", "y"])
    result = summarise(position, gt, detected, drone, flight)
    assert result["E"] == pytest.approx(15.0 / 4)
    assert result["detected"] == pytest.approx(0.75)
    assert result["E_detected"] == pytest.approx(11.0 / 3) and result["E_undetected"] == pytest.approx(4.0)
    assert result["E_0-10m"] == pytest.approx(1.0) and result["E_10-20m"] == pytest.approx(5.0)
    assert result["E_20-40m"] == pytest.approx(4.0) and result["share_10-20m"] == pytest.approx(0.5)
    assert result["E_avata"] == pytest.approx(6.0) and result["detected_avata"] == pytest.approx(0.5)


def test_smooth_flights_smooths_each_flight_from_its_detections_in_time_order():
    rng = np.random.default_rng(3)
    times = np.tile(np.arange(60) / 10.0, 2)
    sequence = np.repeat([0, 1], 60)
    gt = np.stack([np.r_[np.linspace(0, 6, 60), np.linspace(5, -1, 60)], np.full(120, 15.0),
                   np.full(120, 12.0)], axis=1)
    position = gt + rng.normal(0, 0.5, gt.shape)
    detected = rng.random(120) > 0.3
    order = rng.permutation(120)
    arrays = {"time": times[order], "sequence": sequence[order], "position": position[order],
              "detected": detected[order]}
    smoothed = smooth_flights(arrays, {"preset": "tuned", "horizon": 2.0})
    smoother = make_smoother(preset="tuned", horizon=2.0)
    for flight in (0, 1):
        rows = np.flatnonzero(sequence == flight)
        alone = smooth_detected(smoother, times[rows], position[rows], detected[rows])
        back = np.argsort(order)[rows]  # where these rows went in the shuffled arrays
        np.testing.assert_allclose(smoothed[back], alone, atol=1e-9)
