"""How well a smoother's std describes its errors: the k-sigma coverage of the truth and the factor that calibrates it.

The posterior std of a white-noise model is overconfident, because audio errors are correlated in time.
The robust presets carry a factor per lag that multiplies the std (``std_scale``, see
:data:`zoo.smoothing.ROBUST_PRESETS`); these two functions measure the coverage and choose the factor
(``python -m benchmarks.studies.smoothing_bench --accuracy`` and ``--fit-preset``). They use ground truth, so
they serve evaluation and calibration, never smoothing itself.
"""

from __future__ import annotations

import math

import numpy as np


def coverage(mean: np.ndarray, std: np.ndarray, truth: np.ndarray, k: float = 2.0) -> float:
    """Fraction of truth values inside the ``k``-sigma band, pooled over frames and axes (NaN rows skipped)."""
    mean, std, truth = (np.asarray(a, dtype=np.float64) for a in (mean, std, truth))
    if not (mean.shape == std.shape == truth.shape):
        raise ValueError(f"mean, std and truth must have one shape, got {mean.shape}, {std.shape}, {truth.shape}")
    valid = np.isfinite(mean) & np.isfinite(std) & np.isfinite(truth)
    if not valid.any():
        return math.nan
    return float(np.mean(np.abs(truth - mean)[valid] <= k * std[valid]))


def calibration_factor(mean: np.ndarray, std: np.ndarray, truth: np.ndarray, target: float = 0.95,
                       k: float = 2.0) -> float:
    """The factor c for which ``k * c * std`` covers the fraction ``target`` of |truth - mean| (pooled)."""
    z = np.abs(np.asarray(truth) - np.asarray(mean)) / np.asarray(std)
    z = z[np.isfinite(z)]
    if z.size == 0:
        raise ValueError("no finite (mean, std, truth) triple to calibrate on")
    return float(np.quantile(z, target) / k)
