"""How good a pseudo-label track is: error against ground truth, and coverage.

Error: Euclidean distance between the pseudo-label and the ground truth at the ground-truth times
that carry a label (mean, median, 95th percentile; the AAUTE paper reports a 0.5 m mean [B]).

Coverage, two denominators:

- ``coverage``: labelled share of all ground-truth times;
- ``coverage_returns[k]``: labelled share of the ground-truth times at which the drone produced
  at least k LiDAR returns (both sensors) in the surrounding chunk, i.e. the ``window_s`` (one
  chunk, 2 s) centred on the time. Known only for simulated recordings, whose points carry an
  ``origin`` label (``ORIGIN_DRONE``). k = 1 asks for a label wherever any drone return exists;
  k = 10 (the paper's DBSCAN min_samples) asks for one wherever a cluster of drone returns could
  exist at all.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from datamodules.recording import ORIGIN_DRONE, Recording, Track


@dataclass
class TeacherScore:
    """Error and coverage of one track (or of several pooled)."""

    sequence_id: str
    n_times: int
    n_labelled: int
    mean_m: float
    median_m: float
    p95_m: float
    coverage: float
    coverage_returns: dict[int, float] = field(default_factory=dict)
    n_times_returns: dict[int, int] = field(default_factory=dict)
    errors: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)

    def as_row(self) -> dict[str, Any]:
        """A flat dict for tables."""
        row: dict[str, Any] = {"sequence": self.sequence_id, "gt_times": self.n_times, "labelled": self.n_labelled,
                               "mean_m": self.mean_m, "median_m": self.median_m, "p95_m": self.p95_m,
                               "coverage": self.coverage}
        for k, value in sorted(self.coverage_returns.items()):
            row[f"coverage_ret{k}"] = value
        return row


def track_at(track: Track, times: np.ndarray, tolerance_s: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """The track's xyz and validity at ``times``: its own label where one lies within
    ``tolerance_s``, else linear interpolation between two valid labels at most 0.2 s apart."""
    times = np.asarray(times, dtype=np.float64)
    xyz = np.full((times.size, 3), np.nan)
    valid = np.zeros(times.size, dtype=bool)
    if len(track) == 0:
        return xyz, valid
    right = np.clip(np.searchsorted(track.timestamps, times), 0, len(track) - 1)
    left = np.clip(right - 1, 0, len(track) - 1)
    pick = np.where(np.abs(track.timestamps[left] - times) < np.abs(track.timestamps[right] - times), left, right)
    exact = np.abs(track.timestamps[pick] - times) <= tolerance_s
    xyz[exact] = track.xyz[pick[exact]]
    valid[exact] = track.valid[pick[exact]]
    between = ~exact & (track.timestamps[left] <= times) & (times <= track.timestamps[right]) & (right > left)
    between &= track.valid[left] & track.valid[right] & (track.timestamps[right] - track.timestamps[left] <= 0.2)
    if between.any():
        a, b = left[between], right[between]
        w = ((times[between] - track.timestamps[a]) / (track.timestamps[b] - track.timestamps[a]))[:, None]
        xyz[between] = (1 - w) * track.xyz[a] + w * track.xyz[b]
        valid[between] = True
    return xyz, valid & np.isfinite(xyz).all(axis=1)


def drone_returns_near(recording: Recording, times: np.ndarray, window_s: float = 2.0) -> np.ndarray | None:
    """Drone returns (both sensors) in the ``window_s`` centred on each time; None if points carry no origin.

    A frame's returns count at its stamp plus half the frame period (they spread over the frame).
    """
    stamps, counts = [], []
    for stream in recording.lidar.values():
        if stream is None or len(stream) == 0:
            continue
        t = np.asarray(stream.timestamps, dtype=np.float64)
        offset = 0.5 * float(np.median(np.diff(t))) if t.size > 1 else 0.0
        n = np.zeros(t.size)
        for i in range(t.size):
            origin = stream[i].origin
            if origin is None:
                return None
            n[i] = np.count_nonzero(origin == ORIGIN_DRONE)
        stamps.append(t + offset)
        counts.append(n)
    if not stamps:
        return None
    t = np.concatenate(stamps)
    order = np.argsort(t)
    t, cum = t[order], np.concatenate([[0.0], np.cumsum(np.concatenate(counts)[order])])
    lo = np.searchsorted(t, np.asarray(times) - window_s / 2, side="left")
    hi = np.searchsorted(t, np.asarray(times) + window_s / 2, side="left")
    return cum[hi] - cum[lo]


def drone_return_mask(recording: Recording, times: np.ndarray, min_returns: int = 1,
                      window_s: float = 2.0) -> np.ndarray | None:
    """Times at which the drone produced at least ``min_returns`` returns in the surrounding chunk."""
    counts = drone_returns_near(recording, times, window_s)
    return None if counts is None else counts >= min_returns


def sensor_distance(recording: Recording, xyz: np.ndarray) -> np.ndarray:
    """Distance of each point to the nearest LiDAR (positions from ``meta['sensor_poses']``, else the origin)."""
    poses = [np.asarray(p, dtype=np.float64)[:3] for p in (recording.meta.get("sensor_poses") or {}).values()]
    poses = poses or [np.zeros(3)]
    return np.min([np.linalg.norm(np.asarray(xyz) - p, axis=1) for p in poses], axis=0)


def evaluate_track(track: Track, ground_truth: Track, *, mask: np.ndarray | None = None,
                   returns: np.ndarray | None = None, thresholds: tuple[int, ...] = (1, 10),
                   sequence_id: str = "") -> TeacherScore:
    """Score ``track`` against ``ground_truth`` at the ground-truth times selected by ``mask``.

    Args:
        track: pseudo-labels.
        ground_truth: reference positions.
        mask: which ground-truth times count (e.g. drone within 40 m); all if None.
        returns: drone returns near each ground-truth time (:func:`drone_returns_near`), if known.
        thresholds: the k of ``coverage_returns``.
        sequence_id: name in the score.
    """
    gt_t = np.asarray(ground_truth.timestamps, dtype=np.float64)
    keep = np.ones(gt_t.size, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    keep &= ground_truth.valid
    xyz, labelled = track_at(track, gt_t)
    errors = np.linalg.norm(xyz - ground_truth.xyz, axis=1)[keep & labelled]
    n_times = int(keep.sum())
    score = TeacherScore(
        sequence_id=sequence_id, n_times=n_times, n_labelled=int((keep & labelled).sum()),
        mean_m=float(errors.mean()) if errors.size else float("nan"),
        median_m=float(np.median(errors)) if errors.size else float("nan"),
        p95_m=float(np.percentile(errors, 95)) if errors.size else float("nan"),
        coverage=float((keep & labelled).sum() / n_times) if n_times else float("nan"),
        errors=errors,
    )
    if returns is not None:
        for k in thresholds:
            seen = keep & (np.asarray(returns) >= k)
            score.n_times_returns[k] = int(seen.sum())
            score.coverage_returns[k] = float((seen & labelled).sum() / seen.sum()) if seen.any() else float("nan")
    return score


def score_recording(recording: Recording, track: Track, *, max_range_m: float | None = None,
                    window_s: float = 2.0, thresholds: tuple[int, ...] = (1, 10)) -> TeacherScore | None:
    """Score a track against the recording's ground truth (None without ground truth).

    Args:
        recording: with ground truth; with per-point origins (simulated) the return coverages too.
        track: its pseudo-labels.
        max_range_m: only ground-truth times with the drone within this distance of a LiDAR count
            (the Mid-360's 40 m @ 10 % range for the accuracy target).
        window_s: the surrounding chunk of the return coverage.
        thresholds: the k of ``coverage_returns``.
    """
    gt = recording.ground_truth
    if gt is None or len(gt) == 0:
        return None
    mask = None if max_range_m is None else sensor_distance(recording, gt.xyz) <= max_range_m
    returns = drone_returns_near(recording, gt.timestamps, window_s)
    return evaluate_track(track, gt, mask=mask, returns=returns, thresholds=thresholds,
                          sequence_id=recording.sequence_id)


def pool_scores(scores: list[TeacherScore], name: str = "all") -> TeacherScore:
    """Several scores as one (errors and counts pooled, not averaged)."""
    errors = np.concatenate([s.errors for s in scores]) if scores else np.zeros(0)
    n_times = sum(s.n_times for s in scores)
    n_labelled = sum(s.n_labelled for s in scores)
    pooled = TeacherScore(
        sequence_id=name, n_times=n_times, n_labelled=n_labelled,
        mean_m=float(errors.mean()) if errors.size else float("nan"),
        median_m=float(np.median(errors)) if errors.size else float("nan"),
        p95_m=float(np.percentile(errors, 95)) if errors.size else float("nan"),
        coverage=n_labelled / n_times if n_times else float("nan"), errors=errors)
    ks = sorted({k for s in scores for k in s.coverage_returns})
    for k in ks:
        seen = sum(s.n_times_returns.get(k, 0) for s in scores)
        hit = sum(round(s.coverage_returns[k] * s.n_times_returns[k]) for s in scores
                  if k in s.coverage_returns and s.n_times_returns.get(k, 0))
        pooled.n_times_returns[k] = seen
        pooled.coverage_returns[k] = hit / seen if seen else float("nan")
    return pooled
