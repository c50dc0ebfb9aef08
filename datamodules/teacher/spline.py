"""B-spline trajectory through the per-frame evidence, with gaps and per-label quality.

The AAUTE paper's step 9 [B] ("B-spline fit -> smooth trajectory") with Deng et al.'s
parametrisation (``reference/mmaud_and_teacher.md`` section 3.2 [V]): per axis, a cubic smoothing
spline of position against time (SciPy FITPACK, automatic knots), evaluated at the label times.
Deng's smoothing factor s = 0.5 is for unweighted tracker output; here each evidence row is
weighted by 1 / sigma with sigma^2 = point_sigma^2 / n + floor_sigma^2 (n returns behind the
centroid), so FITPACK's recommended s = m (m rows, the expected chi-square) gives a fit within
the evidence's own noise; ``smoothing`` scales it.

The spline never bridges missing evidence: the evidence is split into segments wherever two
consecutive rows are more than ``max_gap_s`` apart, each segment is fitted on its own, and a
label time is valid only inside a segment or within ``max_extrapolation_s`` of its ends.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import make_splrep

from datamodules.recording import Track


def _merge_equal_times(times: np.ndarray, xyz: np.ndarray, counts: np.ndarray):
    """Rows at the same time become one (count-weighted mean); the spline needs increasing x."""
    unique, inverse = np.unique(times, return_inverse=True)
    if unique.size == times.size:
        return times, xyz, counts
    total = np.bincount(inverse, weights=counts)
    merged = np.stack([np.bincount(inverse, weights=xyz[:, k] * counts) for k in range(3)], axis=1) / total[:, None]
    return unique, merged, total


def segments(times: np.ndarray, max_gap_s: float) -> list[slice]:
    """Runs of sorted ``times`` whose consecutive steps are at most ``max_gap_s``."""
    if times.size == 0:
        return []
    cuts = np.flatnonzero(np.diff(times) > max_gap_s) + 1
    edges = np.concatenate([[0], cuts, [times.size]])
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def _fit_segment(t: np.ndarray, xyz: np.ndarray, sigma: np.ndarray, degree: int, smoothing: float):
    """A callable t -> xyz for one segment (constant for one row, lower degree for few rows)."""
    m = t.size
    if m == 1:
        value = xyz[0].copy()
        return lambda x: np.repeat(value[None, :], np.size(x), axis=0)
    k = min(degree, m - 1)
    t0 = float(t[0])
    splines = [make_splrep(t - t0, xyz[:, axis], w=1.0 / sigma, k=k, s=smoothing * m) for axis in range(3)]
    return lambda x: np.stack([s(np.asarray(x) - t0) for s in splines], axis=1)


def _outliers(times: np.ndarray, xyz: np.ndarray, sigma: np.ndarray, outlier_m: float, window_s: float) -> np.ndarray:
    """Rows farther than ``outlier_m`` (and 3 sigma) from the median of the rows within ``window_s``.

    A running median, not a first spline fit: FITPACK adds knots until it passes through a wrong
    frame. Rows with fewer than two neighbours in their window are not judged.
    """
    lo = np.searchsorted(times, times - window_s, side="left")
    hi = np.searchsorted(times, times + window_s, side="right")
    out = np.zeros(times.size, dtype=bool)
    for i in np.flatnonzero(hi - lo >= 3):
        median = np.median(xyz[lo[i]:hi[i]], axis=0)
        distance = float(np.linalg.norm(xyz[i] - median))
        out[i] = distance > outlier_m and distance > 3.0 * sigma[i]
    return out


def _fit_all(times, xyz, sigma, max_gap_s, degree, smoothing):
    """Fits of every segment and each row's distance to its segment's fit."""
    fits = [(seg, _fit_segment(times[seg], xyz[seg], sigma[seg], degree, smoothing))
            for seg in segments(times, max_gap_s)]
    residual = np.zeros(times.size)
    for seg, fit in fits:
        residual[seg] = np.linalg.norm(fit(times[seg]) - xyz[seg], axis=1)
    return fits, residual


def fit_track(
    evidence_times: np.ndarray,
    evidence_xyz: np.ndarray,
    evidence_counts: np.ndarray,
    label_times: np.ndarray,
    *,
    max_gap_s: float = 1.0,
    max_extrapolation_s: float = 0.5,
    degree: int = 3,
    smoothing: float = 1.0,
    point_sigma_m: float = 0.3,
    floor_sigma_m: float = 0.1,
    outlier_m: float = 1.5,
    outlier_window_s: float = 0.5,
    support_window_s: float = 0.5,
) -> Track:
    """The pseudo-label track at ``label_times`` from per-frame evidence.

    Args:
        evidence_times, evidence_xyz, evidence_counts: per-frame centroids (sorted by time) and the
            returns behind each.
        label_times: where the track is evaluated.
        max_gap_s: longest stretch without evidence the spline may bridge (s).
        max_extrapolation_s: how far before the first / after the last row of a segment a label is
            still given (s).
        degree: spline degree (3, cubic, as Deng et al.); fewer rows lower it.
        smoothing: multiplies FITPACK's s = m.
        point_sigma_m: scatter of single returns about the drone's centre (m): half the size of
            the larger drones (DJI M300 0.81 m) plus range noise [E].
        floor_sigma_m: noise floor of a frame centroid however many returns (m): motion within the
            0.1 s frame at 1-2 m/s and the visible-half bias of the returns [E].
        outlier_m: rows farther than this (and beyond 3 sigma) from the median of their
            neighbours are dropped before the fit (a wrong cluster in one frame must not bend the track).
        outlier_window_s: the half-window (s) of that running median.
        support_window_s: the half-window (s) in which ``support_points`` and ``residual_m`` of a
            label are counted.

    Returns:
        A :class:`Track` with ``valid`` False (xyz NaN) in gaps and quality ``support_points``
        (returns within the support window), ``nearest_evidence_s`` (time to the nearest row; inf
        without evidence) and ``residual_m`` (RMS distance of those rows to the track; NaN if none).
    """
    label_times = np.asarray(label_times, dtype=np.float64)
    times = np.asarray(evidence_times, dtype=np.float64)
    xyz = np.asarray(evidence_xyz, dtype=np.float64).reshape(-1, 3)
    counts = np.asarray(evidence_counts, dtype=np.float64)
    order = np.argsort(times, kind="stable")
    times, xyz, counts = _merge_equal_times(times[order], xyz[order], counts[order])
    sigma = np.sqrt(point_sigma_m**2 / np.maximum(counts, 1.0) + floor_sigma_m**2)

    outliers = _outliers(times, xyz, sigma, outlier_m, outlier_window_s)
    if outliers.any():
        keep = ~outliers
        times, xyz, counts, sigma = times[keep], xyz[keep], counts[keep], sigma[keep]
    fits, residual = _fit_all(times, xyz, sigma, max_gap_s, degree, smoothing)

    out = np.full((label_times.size, 3), np.nan)
    valid = np.zeros(label_times.size, dtype=bool)
    for seg, fit in fits:
        lo, hi = times[seg.start] - max_extrapolation_s, times[seg.stop - 1] + max_extrapolation_s
        inside = (label_times >= lo) & (label_times <= hi)
        if inside.any():
            out[inside] = fit(label_times[inside])
            valid |= inside
    quality = _quality(times, counts, residual, label_times, support_window_s)
    return Track(label_times, out, valid, quality)


def _quality(times: np.ndarray, counts: np.ndarray, residual: np.ndarray, label_times: np.ndarray,
             window: float) -> dict[str, np.ndarray]:
    """Per-label support, distance in time to the nearest evidence, and local residual."""
    if times.size == 0:
        return {"support_points": np.zeros(label_times.size), "nearest_evidence_s": np.full(label_times.size, np.inf),
                "residual_m": np.full(label_times.size, np.nan)}
    cum_counts = np.concatenate([[0.0], np.cumsum(counts)])
    cum_sq = np.concatenate([[0.0], np.cumsum(residual**2)])
    lo = np.searchsorted(times, label_times - window, side="left")
    hi = np.searchsorted(times, label_times + window, side="right")
    rows = hi - lo
    support = cum_counts[hi] - cum_counts[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.where(rows > 0, np.sqrt((cum_sq[hi] - cum_sq[lo]) / np.maximum(rows, 1)), np.nan)
    right = np.clip(np.searchsorted(times, label_times), 0, times.size - 1)
    left = np.clip(right - 1, 0, times.size - 1)
    nearest = np.minimum(np.abs(times[right] - label_times), np.abs(times[left] - label_times))
    return {"support_points": support, "nearest_evidence_s": nearest, "residual_m": rms}
