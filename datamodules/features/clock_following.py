"""Following the nodes' clocks through a stream: one clock model from the estimates of its successive stretches
(:func:`~datamodules.features.clock_calibration.estimate_clock_offsets` on each), leaving out those that
disagree with the others."""

from __future__ import annotations

import dataclasses
import itertools
import logging

import numpy as np

from datamodules.features.clock_calibration import ClockCalibration, ClockCalibrationConfig, with_std_floor

log = logging.getLogger(__name__)


#: lines are tried through the pairs of at most this many estimates, spread evenly over the stream (66 pairs)
CONSENSUS_ESTIMATES = 12


def _at_centres(pieces: list[tuple[float, float, ClockCalibration]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each stretch's centre (s of the stream), and its estimate's offsets and their stds there (K x nodes)."""
    centres = np.array([start + duration / 2 for start, duration, _ in pieces])
    offsets = np.stack([estimate.offsets_at(duration / 2) for _, duration, estimate in pieces])
    stds = np.stack([estimate.offsets_std_s for _, _, estimate in pieces])
    return centres, offsets, stds


def consistent_estimates(pieces: list[tuple[float, float, ClockCalibration]], threshold: float = 3.0,
                         max_drift_ppm: float = ClockCalibrationConfig.max_drift_ppm,
                         floor_s: float = ClockCalibrationConfig.std_floor) -> list[bool]:
    """Which of three or more stretch estimates (as :func:`combine_clock_estimates` takes them) agree with one
    line: the line through a pair of estimates (with a drift within ``max_drift_ppm``) that the most
    estimates agree with (every node within ``threshold`` of it, in units of the estimate's std and ``floor_s``
    in quadrature), ties to the smaller squared misfit; the pairs are those of
    :data:`CONSENSUS_ESTIMATES` estimates spread over the stream (all of them in a stream of as many). A stretch
    whose fit went wrong can be off by tenths of a millisecond with a std of hundredths, so the line of all of
    them would follow it."""
    if len(pieces) < 3:
        return [True] * len(pieces)
    tried = np.unique(np.linspace(0, len(pieces) - 1, min(len(pieces), CONSENSUS_ESTIMATES)).round().astype(int))
    centres, offsets, stds = _at_centres(pieces)
    offsets, stds = offsets[:, 1:], stds[:, 1:]  # node 0 is the reference
    sigma = np.hypot(np.nan_to_num(stds, nan=floor_s), floor_s)
    best, keep = None, [True] * len(pieces)
    for i, j in itertools.combinations(tried, 2):
        slope = (offsets[j] - offsets[i]) / (centres[j] - centres[i])
        if np.any(np.abs(slope) > max_drift_ppm * 1e-6):
            continue
        z = np.abs(offsets - offsets[i] - slope * (centres[:, None] - centres[i])) / sigma
        agree = (z < threshold).all(axis=1)
        rank = (int(agree.sum()), -float(np.sum(z[agree] ** 2)))
        if best is None or rank > best:
            best, keep = rank, agree.tolist()
    return keep


def combine_clock_estimates(pieces: list[tuple[float, float, ClockCalibration]], drift_significance: float = 3.0,
                            floor_s: float = ClockCalibrationConfig.std_floor) -> ClockCalibration:
    """One clock model from estimates of successive stretches of a stream (how a live stream follows drift).

    Each piece is ``(start, duration, estimate)``: the stretch's first sample and length (s of the stream) and
    the estimate from that stretch alone (its times count from the stretch's first sample), made without the
    estimator's floor (``std_floor=0``). Per node, the offset each estimate gives at its stretch's centre is one
    measurement, weighted by the inverse variance of its fit's own spread (weights with the floor followed the
    clocks worse on development flights); ``floor_s`` is added in quadrature to the result's offset stds;
    a straight line through them (offset and drift, by weighted least squares) is kept when the drift of one
    node is told from zero (``drift_significance`` standard errors, the estimator's rule under
    ``fit_drift=None``), else their weighted mean. Two estimates suffice for a line (asking for three, so that
    their scatter could check their stds, followed the clocks worse on development flights). Standard errors
    come from the fit, scaled up by the scatter of the measurements about it when that is larger than their
    stds say (Birge ratio). From three estimates on, those that disagree with the line most agree with are left
    out (:func:`consistent_estimates`). The result's times count from the stream's start."""
    if not pieces:
        raise ValueError("combine_clock_estimates needs at least one estimate")
    keep = consistent_estimates(pieces, floor_s=floor_s)
    if not all(keep):
        log.info("clock estimates of the stretches from %s s disagree with the others and are left out",
                 ", ".join(f"{start:.1f}" for (start, _, _), kept in zip(pieces, keep, strict=True) if not kept))
        pieces = [piece for piece, kept in zip(pieces, keep, strict=True) if kept]
    if len(pieces) == 1:
        start, _, only = pieces[0]
        std = with_std_floor(only.offsets_std_s, floor_s)
        return dataclasses.replace(only, offsets_s=only.offsets_at(-start), offsets_std_s=std, times=only.times + start)
    centres, offsets, stds = _at_centres(pieces)
    known = np.isfinite(stds) & (stds > 0)
    stds = np.where(known, stds, np.median(stds[known]) if known.any() else 1e-5)
    weights = 1.0 / stds ** 2

    def fit(design: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per node: parameters (nodes x p) and their standard errors for offsets = design @ parameters."""
        params, errors = np.zeros((offsets.shape[1], design.shape[1])), np.zeros((offsets.shape[1], design.shape[1]))
        for node in range(1, offsets.shape[1]):
            w = weights[:, node]
            normal = design.T @ (w[:, None] * design)
            params[node] = np.linalg.solve(normal, design.T @ (w * offsets[:, node]))
            dof = len(centres) - design.shape[1]
            chi2 = float(w @ (offsets[:, node] - design @ params[node]) ** 2) / dof if dof > 0 else 1.0
            errors[node] = np.sqrt(np.diag(np.linalg.inv(normal)) * max(1.0, chi2))
        return params, errors

    line, line_errors = fit(np.stack([np.ones_like(centres), centres], axis=1))
    if np.any(np.abs(line[:, 1]) > drift_significance * line_errors[:, 1]):
        params, errors = line, line_errors
    else:
        mean, mean_errors = fit(np.ones((len(centres), 1)))
        params, errors = np.pad(mean, ((0, 0), (0, 1))), np.pad(mean_errors, ((0, 0), (0, 1)))
    last = pieces[-1][2]
    return ClockCalibration(offsets_s=params[:, 0], offsets_std_s=with_std_floor(errors[:, 0], floor_s),
                            drifts_ppm=params[:, 1] * 1e6, drifts_std_ppm=errors[:, 1] * 1e6,
                            frames=sum(e.frames for _, _, e in pieces),
                            residual_rms_s=last.residual_rms_s)
