"""Which smoother runs: smoothers by preset name, and smoothing of detections, batches and track files.

:func:`make_smoother` is the one place that maps a preset name to a smoother class: ``paper`` and ``tuned``
to :class:`~zoo.smoothing.gp.GPSmoother`, ``robust`` (the default, :data:`DEFAULT_PRESET`) to
:class:`~zoo.smoothing.robust.RobustSmoother`. It sits above both smoother modules, so neither imports the
other to build one. The helpers below run any :class:`~zoo.smoothing.track.Smoother` on the shapes the
task, the benchmarks and the command line hold: one sequence with detection flags, a batch of sequences,
a CSV file.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Hashable, Sequence
from pathlib import Path

import numpy as np

from zoo.smoothing.gp import PRESETS, GPSmoother
from zoo.smoothing.robust import ROBUST_PRESETS, RobustSmoother
from zoo.smoothing.track import SmoothedTrack, Smoother, read_track_csv, write_smoothed_csv

log = logging.getLogger(__name__)

#: The smoother preset used where none is asked for (the robust Student-t smoother, see zoo.smoothing.robust).
DEFAULT_PRESET = "robust"


def make_smoother(preset: str | None = None, **options: object) -> Smoother:
    """A smoother by preset name: ``paper`` / ``tuned`` make a :class:`GPSmoother`, ``robust`` (default) a
    :class:`RobustSmoother`; ``options`` are that class's arguments. Both have
    ``smooth(timestamps, xyz, query_times=None) -> SmoothedTrack``.

    Raises:
        ValueError: an unknown preset name.
    """
    name = DEFAULT_PRESET if preset is None else preset
    if name in ROBUST_PRESETS:
        return RobustSmoother(name, **options)  # type: ignore[arg-type]
    if name not in PRESETS:
        raise ValueError(f"unknown smoother preset {name!r}; expected one of {sorted({*PRESETS, *ROBUST_PRESETS})}")
    return GPSmoother(name, **options)  # type: ignore[arg-type]


def measured_rows(detected: np.ndarray | None, count: int) -> np.ndarray:
    """The rows (bool, ``count``) a smoother takes as measurements: the detected ones, or every row when there
    are no detection flags or fewer than two detections."""
    measured = np.ones(count, dtype=bool) if detected is None else np.asarray(detected, dtype=bool)
    return measured if int(measured.sum()) >= 2 else np.ones(count, dtype=bool)


def smooth_detected(smoother: Smoother, timestamps: np.ndarray, xyz: np.ndarray, detected: np.ndarray) -> np.ndarray:
    """One sequence's smoothed positions (N x 3): the mean of :func:`smooth_detected_track`."""
    return smooth_detected_track(smoother, timestamps, xyz, detected).mean


def smooth_detected_track(smoother: Smoother, timestamps: np.ndarray, xyz: np.ndarray, detected: np.ndarray
                          ) -> SmoothedTrack:
    """One sequence smoothed at every timestamp from its detected rows alone.

    Rows a net marks undetected hold a remembered or fallback position, not a measurement: the smoother
    bridges them from the detections, and keeps the net's own position where the nearest detection is
    beyond its horizon (there it would only drift back to the detections' mean; the std stays the
    smoother's). With fewer than two detections, or no detection flags at all, every row is smoothed.
    """
    t = np.asarray(timestamps, dtype=np.float64)
    positions = np.asarray(xyz, dtype=np.float64)
    measured = measured_rows(detected, len(t))
    track = smoother.smooth(t[measured], positions[measured], t)  # every query is measured when all are
    return dataclasses.replace(track, mean=np.where(track.beyond_horizon[:, None], positions, np.asarray(track.mean)))


def smooth_predictions(
    timestamps: np.ndarray, xyz: np.ndarray, sequence_ids: Sequence[Hashable] | np.ndarray, **options: object
) -> dict[Hashable, SmoothedTrack]:
    """Smooth each sequence of a batch of predictions on its own.

    Args:
        timestamps: (N,) seconds.
        xyz: (N, 3) predicted positions.
        sequence_ids: (N,) the sequence of each row.
        **options: :func:`make_smoother` arguments (``preset`` default ``robust``).

    Returns:
        ``{sequence_id: SmoothedTrack}``; the rows of each track are that sequence's rows in their input
        order, i.e. ``np.flatnonzero(np.asarray(sequence_ids) == sequence_id)``.
    """
    ids = np.asarray(sequence_ids)
    t = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if ids.shape != t.shape:
        raise ValueError(f"expected one sequence id per timestamp ({t.shape[0]}), got shape {ids.shape}")
    positions = np.asarray(xyz, dtype=np.float64)
    smoother = make_smoother(**options)  # type: ignore[arg-type]
    out: dict[Hashable, SmoothedTrack] = {}
    for sequence in dict.fromkeys(ids.tolist()):
        rows = np.flatnonzero(ids == sequence)
        out[sequence] = smoother.smooth(t[rows], positions[rows])
    return out



def smooth_track_file(src: Path, dst: Path, **options: object) -> SmoothedTrack:
    """Smooth the track in CSV ``src`` and write it with per-axis std to ``dst`` (atomically).

    Args:
        src: ``timestamp,x,y,z`` CSV; extra columns are ignored.
        dst: output CSV ``timestamp,x,y,z,std_x,std_y,std_z``, one row per input row, in input order.
        **options: :func:`make_smoother` arguments (``preset``, default ``robust``, ``fit``, ...).

    Raises:
        TrackFileError: bad input; ``dst`` is then left untouched.
    """
    timestamps, xyz = read_track_csv(Path(src))
    track = make_smoother(**options).smooth(timestamps, xyz)  # type: ignore[arg-type]
    write_smoothed_csv(Path(dst), track)
    log.info("smoothed %d points of %s (%s backend) -> %s", len(track), src, track.backend, dst)
    return track
