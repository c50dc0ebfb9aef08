"""The nodes' clock drifts from a static sound source (a rooftop HVAC unit, a generator, a hovering drone).

A source that does not move reaches every pair of microphones with one time difference for good; on nodes
whose clocks drift apart, the pair's apparent time difference moves along a straight line of slope
``drift_j - drift_i`` (node ``n``'s audio runs ``offset_n + drift_n t`` early, the convention of
:mod:`datamodules.features.clock_calibration`). Whatever the source's position, that slope is the drift
difference: the line's level mixes the source's geometry with the offsets, its slope does not.

:func:`static_source_drift` cuts the audio into stretches of ``stretch_seconds``, correlates each pair over each
stretch (GCC-PHAT of the stretch's mean cross-spectrum: a long average, so a source that stays put adds up and
one that moves smears) and finds per pair the straight line along which the stretches' correlations have the
highest median (a static source is on it in every stretch, a moving one crosses it now and then), then refits
it by least squares through each stretch's peak near it, those within ``tolerance`` of the line. The node
drifts (node 0 = 0) are the weighted least-squares solution of the pairs' slopes, over the pairs whose line
holds in enough stretches, a pair that disagrees with the others left out. A recording without such lines (no
static source, or one too faint) gives None, as does one whose pairs disagree on the drifts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from datamodules.features.phase import GccPhat, PhaseRecipe, mic_pairs, parabolic_offset
from datamodules.recording import AudioStream


@dataclass(frozen=True)
class StaticDrift:
    """Node drifts told by a static source (node 0 = 0)."""

    drifts_ppm: np.ndarray  #: per node
    drifts_std_ppm: np.ndarray  #: per node, from the pairs' line fits
    pair_slopes_ppm: np.ndarray  #: per pair ``(i, j)``: ``drift_j - drift_i`` as its line says
    share: float  #: the smallest share, over pairs, of stretches with a peak on the pair's line
    stretches: int  #: stretches correlated (those holding NaN samples left out)


def _stretch_correlations(audio: AudioStream, gcc: GccPhat, per: int, count: int) -> tuple[np.ndarray, np.ndarray]:
    """PHAT correlation of the mean cross-spectrum of ``count`` stretches of ``per`` frames spread over the audio:
    pairs x stretches x lags (float64; NaN for a stretch holding NaN samples), and the stretches' first samples."""
    span = per * gcc.frame
    starts = np.linspace(0, audio.num_samples - span, count).round().astype(int) if count > 1 else np.array([0])
    out = []
    with torch.no_grad():
        for start in starts:
            samples = audio.read(int(start), int(start) + span)
            if not np.isfinite(samples).all():
                out.append(None)
                continue
            frames = torch.from_numpy(np.ascontiguousarray(samples)).reshape(samples.shape[0], per, gcc.frame)
            cross = gcc.cross_spectra(frames).to(torch.complex128).mean(dim=1, keepdim=True)
            out.append(gcc.correlate(cross)[:, 0].double().numpy())
    shape = next((c.shape for c in out if c is not None), (len(gcc.first), 2 * gcc.half + 1))
    return np.stack([np.full(shape, np.nan) if c is None else c for c in out], axis=1), starts


def _ridge(corr: np.ndarray, t: np.ndarray, rate: float, max_slope: float, cell: int) -> tuple[float, float]:
    """The straight line ``lag = level + slope (t - t_mid)`` (lags in samples of ``rate``) along which the
    stretches' correlations (stretches x lags) have the highest median: a static source is on it in every
    stretch, a moving one only where it crosses it. Searched on cells of ``cell`` lags (each the maximum over
    two cells around it), slopes a cell over the recording's span apart."""
    stretches, lags = corr.shape
    width = lags // cell
    pooled = corr[:, :width * cell].reshape(stretches, width, cell).max(axis=2)
    pooled = np.maximum(pooled, np.concatenate([pooled[:, 1:], pooled[:, -1:]], axis=1))  # cells k and k + 1
    centred = t - t.mean()
    span = max(float(np.ptp(t)), 1e-9)
    step = cell / rate / span
    slopes = np.arange(-max_slope, max_slope + step, step)
    rows = np.arange(stretches)[:, None]
    columns = np.arange(width)[None, :]
    best, best_value = (0.0, 0.0), -np.inf
    for slope in slopes:
        shift = np.round(slope * centred * rate / cell).astype(np.int64)[:, None]
        index = columns + shift
        inside = (index >= 0) & (index < width)
        values = np.where(inside, pooled[rows, np.clip(index, 0, width - 1)], -np.inf)
        median = np.median(values, axis=0)
        k = int(median.argmax())
        if median[k] > best_value:
            best, best_value = (float(slope), (k + 1.0) * cell), float(median[k])  # the pooled pair's centre
    return best


def _line(corr: np.ndarray, t: np.ndarray, lags: np.ndarray, rate: float, max_slope: float, cell: int,
          tolerance: float) -> tuple[float, float, np.ndarray] | None:
    """Each stretch's peak near the ridge (:func:`_ridge`), and the line refitted through those within
    ``tolerance`` of it: slope, its std, and which stretches have their peak on the line."""
    slope, level = _ridge(corr, t, rate, max_slope, cell)
    centred = t - t.mean()
    expected = level + slope * centred * rate  # lag index per stretch
    index = np.empty(t.size, dtype=np.int64)
    for m in range(t.size):
        lo = int(np.clip(np.floor(expected[m]) - 2 * cell, 1, corr.shape[1] - 2))
        hi = int(np.clip(np.ceil(expected[m]) + 2 * cell, lo + 1, corr.shape[1] - 1))
        index[m] = lo + int(corr[m, lo:hi].argmax())
    peak = lags[index] + parabolic_offset(corr, index) / rate
    coef = np.array([level / rate + lags[0], slope])
    on = np.zeros(t.size, dtype=bool)
    for limit in (2 * cell / rate, tolerance, tolerance):  # from the ridge's cells down to the tolerance
        on = np.abs(peak - (coef[0] + coef[1] * centred)) <= limit
        if on.sum() < 3:
            return None
        design = np.stack([np.ones(int(on.sum())), centred[on]], axis=1)
        coef, *_ = np.linalg.lstsq(design, peak[on], rcond=None)
    residual = peak[on] - (coef[0] + coef[1] * centred[on])
    sigma2 = float(residual @ residual) / max(int(on.sum()) - 2, 1)
    slope_std = np.sqrt(sigma2 / max(float((centred[on] ** 2).sum()), 1e-12))
    return float(coef[1]), float(slope_std), on


def static_source_drift(audio: AudioStream, *, f_min: float = 300.0, f_max: float = 8000.0,
                        frame_seconds: float = 4096 / 48000, lag_rate: float = 96000.0, max_delay: float = 0.02,
                        stretch_seconds: float = 2.0, min_stretches: int = 10, max_stretches: int = 120, cell: int = 8,
                        tolerance: float = 2e-5, min_share: float = 0.5, max_drift_ppm: float = 100.0,
                        max_misfit_ppm: float = 1.0) -> StaticDrift | None:
    """The node drifts of ``audio`` from a static source (see the module docstring), or None when none tells them.

    ``max_delay`` bounds the pair time differences searched (geometry plus offsets, s); at least
    ``min_stretches`` stretches are needed (over a few, a drone moving slowly draws a line too), and a pair
    needs a peak on its line in ``min_share`` of them; the pairs' slopes must agree with one drift per node within
    ``max_misfit_ppm`` (RMS).
    """
    channels = audio.num_channels
    recipe = PhaseRecipe("static_drift", frame_seconds=frame_seconds, frames=1, max_delay=max_delay,
                         lag_rate=lag_rate, f_min=f_min, f_max=f_max)
    gcc = GccPhat(recipe, float(audio.sample_rate), channels)
    per = max(1, int(round(stretch_seconds / frame_seconds)))
    count = min(audio.num_samples // (per * gcc.frame), max_stretches)
    if channels < 2 or count < min_stretches:  # a short stretch: a slow drone's trail can pass for a line
        return None
    corr, starts = _stretch_correlations(audio, gcc, per, count)
    t = (starts + per * gcc.frame / 2) / float(audio.sample_rate)
    lags = (np.arange(corr.shape[-1]) - gcc.half) / lag_rate
    usable = np.isfinite(corr[0]).all(axis=1)
    corr, t = corr[:, usable], t[usable]
    if t.size < min_stretches:
        return None
    pairs = mic_pairs(channels)
    slopes, stds, shares = np.full(len(pairs), np.nan), np.full(len(pairs), np.nan), np.zeros(len(pairs))
    for p in range(len(pairs)):
        line = _line(corr[p], t, lags, lag_rate, 2 * max_drift_ppm * 1e-6, cell, tolerance)
        if line is not None:
            slopes[p], stds[p], shares[p] = line[0] * 1e6, max(line[1] * 1e6, 1e-3), float(line[2].mean())
    return _node_drifts(pairs, slopes, stds, shares, min_share, max_misfit_ppm, max_drift_ppm, t.size)


def _node_drifts(pairs: list[tuple[int, int]], slopes: np.ndarray, stds: np.ndarray, shares: np.ndarray,
                 min_share: float, max_misfit_ppm: float, max_drift_ppm: float, stretches: int
                 ) -> StaticDrift | None:
    """Node drifts (node 0 = 0) from the pairs' slopes ``drift_j - drift_i`` by weighted least squares over
    the pairs whose line holds ``min_share`` of the stretches; while they disagree by more than
    ``max_misfit_ppm`` (RMS), the worst-fitting pair (whose line is another source's) is left out. The pairs
    kept must tie every node to node 0 with one pair to spare, or nothing checks them. None when no such set
    agrees."""
    channels = max(max(p) for p in pairs) + 1
    design = np.zeros((len(pairs), channels - 1))
    for p, (i, j) in enumerate(pairs):
        if j > 0:
            design[p, j - 1] += 1.0
        if i > 0:
            design[p, i - 1] -= 1.0
    used = shares >= min_share
    spare = 1 if len(pairs) > 1 else 0  # a pair beyond those that tie the nodes, to check them against
    while used.sum() >= channels - 1 + spare and np.linalg.matrix_rank(design[used]) == channels - 1:
        weight = 1.0 / stds[used]
        a = design[used] * weight[:, None]
        solution, *_ = np.linalg.lstsq(a, slopes[used] * weight, rcond=None)
        misfit = slopes[used] - design[used] @ solution
        if np.sqrt(np.mean(misfit**2)) <= max_misfit_ppm:
            if np.any(np.abs(solution) > max_drift_ppm):
                return None
            std = np.sqrt(np.diag(np.linalg.pinv(a.T @ a)))
            return StaticDrift(np.concatenate([[0.0], solution]), np.concatenate([[0.0], std]), slopes,
                               float(shares[used].min()), stretches)
        worst = np.flatnonzero(used)[int(np.abs(misfit).argmax())]
        used[worst] = False
    return None
