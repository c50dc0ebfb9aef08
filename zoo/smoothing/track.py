"""What every smoother shares: the smoothed track, the ``Smoother`` protocol, input checks and track CSV files.

This is the leaf of the smoothing package: the GP, the robust and the online smoothers all import it and
it imports none of them. It holds the result type (:class:`SmoothedTrack`), the interface the smoothers
have in common (:class:`Smoother`), the checks and small time-axis helpers they all run on a track, the
torch dtype of every smoothing computation, and the reading and writing of ``timestamp,x,y,z`` CSV files.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple, Protocol

import numpy as np
import pandas as pd
import torch

from datamodules.atomic import atomic_write
from datamodules.recording import RecordingError

TRACK_COLUMNS = ("timestamp", "x", "y", "z")
#: columns that tell several tracks of one file apart (a benchmark's ``predictions.csv``: flights x lights)
TRACK_KEYS = ("sequence_id", "light")
SMOOTHED_COLUMNS = (*TRACK_COLUMNS, "std_x", "std_y", "std_z")
#: what a detecting localiser (SRP-PHAT) adds to each row of its tracks (``aaute predict``, ``aaute track``)
DETECTION_COLUMNS = ("detection_score", "detected", "state")
#: The torch dtype of every smoothing computation: relative times of long tracks need float64.
DTYPE = torch.float64


class TrackFileError(RecordingError):
    """A track CSV file does not hold what :func:`zoo.smoothing.smooth_track_file` expects."""


def per_axis(value: float | Sequence[float], name: str) -> tuple[float, float, float]:
    """One positive finite value per axis (x, y, z) from one value or three.

    Raises:
        ValueError: a value that is not positive and finite, or not one or three values.
    """
    values = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,))
    if not np.all(np.isfinite(values)) or np.any(values <= 0):
        raise ValueError(f"{name} must be positive and finite, one value or one per axis; got {value!r}")
    return (float(values[0]), float(values[1]), float(values[2]))


@contextmanager
def torch_threads(num_threads: int | None) -> Iterator[None]:
    """Run with ``num_threads`` intra-op threads, restoring the previous count afterwards."""
    if num_threads is None:
        yield
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(num_threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


class Hyperparameters(Protocol):
    """What the hyperparameters of every smoother carry: per-axis values in physical units."""

    @property
    def lengthscale(self) -> tuple[float, float, float]: ...

    @property
    def outputscale(self) -> tuple[float, float, float]: ...

    @property
    def noise(self) -> tuple[float, float, float]: ...

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


@dataclass
class SmoothedTrack:
    """Smoothed positions at the query times, in the order the times were given.

    Attributes:
        timestamps: (M,) float64 query times, as given (absolute).
        mean: (M, 3) posterior mean of x, y, z in metres.
        std: (M, 3) predictive standard deviation of the smoothed position (without observation noise).
        beyond_horizon: (M,) True where the nearest observation is farther than ``horizon`` seconds:
            there the mean drifts back to the track mean and the std towards the prior std.
        hyperparameters: what was used (the fitted values when fitting).
        backend: the backend that ran (``exact``, ``statespace`` or ``local``).
        horizon: the horizon in seconds that ``beyond_horizon`` refers to.
        weights: (M,) robust weight E[w] of each observation (robust smoothers only; 1 is a typical
            frame, near 0 an ignored outlier), or None.
    """

    timestamps: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    beyond_horizon: np.ndarray
    hyperparameters: Hyperparameters
    backend: str
    horizon: float
    weights: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    @property
    def variance(self) -> np.ndarray:
        """(M, 3) predictive variance, m^2."""
        return self.std**2


class Smoother(Protocol):
    """An offline smoother of a 3-D track, such as :class:`~zoo.smoothing.GPSmoother` and
    :class:`~zoo.smoothing.RobustSmoother` (what :func:`~zoo.smoothing.make_smoother` returns)."""

    def smooth(
        self, timestamps: np.ndarray, xyz: np.ndarray, query_times: np.ndarray | None = None
    ) -> SmoothedTrack:
        """Smooth one track and predict at ``query_times`` (default: the observation times)."""
        ...


def prepare(timestamps: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A track as float64 times (N,) and positions (N, 3), checked.

    Raises:
        ValueError: shapes that do not match, an empty track, or a non-finite value.
    """
    t = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    y = np.asarray(xyz, dtype=np.float64)
    if y.ndim != 2 or y.shape[1] != 3 or y.shape[0] != t.shape[0]:
        raise ValueError(f"expected {t.shape[0]} x 3 positions for {t.shape[0]} timestamps, got {y.shape}")
    if t.shape[0] == 0:
        raise ValueError("cannot smooth an empty track")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(y))):
        raise ValueError("timestamps and positions must be finite (no NaN or inf)")
    return t, y


def distance_to_nearest(sorted_t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Distance from each query to the nearest of the sorted times."""
    right = np.clip(np.searchsorted(sorted_t, q), 0, len(sorted_t) - 1)
    left = np.clip(right - 1, 0, len(sorted_t) - 1)
    return np.minimum(np.abs(sorted_t[right] - q), np.abs(q - sorted_t[left]))


class MergedTimes(NamedTuple):
    """Observation times and query times on one sorted axis; see :func:`merge_queries`.

    Attributes:
        times: (N + M,) the merged times, sorted (an observation before a query at the same time).
        observed: (N + M,) True at the steps that are observations.
        source: (N + M,) the index of each step in ``concatenate([t, tq])``: the observation's index
            where ``observed``.
        query_steps: (M,) the step of each query, in the order the queries were given.
    """

    times: np.ndarray
    observed: np.ndarray
    source: np.ndarray
    query_steps: np.ndarray

    def scatter(self, y: np.ndarray) -> np.ndarray:
        """Observations (N, D) laid on the merged steps: (N + M, D), zero at the queries."""
        data = np.zeros((self.times.shape[0], y.shape[1]))
        data[self.observed] = y[self.source[self.observed]]
        return data


def merge_queries(t: np.ndarray, tq: np.ndarray) -> MergedTimes:
    """Merge query times ``tq`` (M,) into sorted observation times ``t`` (N,) as steps without data.

    A state-space smoother runs over the merged axis and reads its answers at ``query_steps``.
    """
    times_all = np.concatenate([t, tq])
    order = np.argsort(times_all, kind="stable")
    observed = order < t.shape[0]
    query_steps = np.empty(tq.shape[0], dtype=np.int64)
    query_steps[order[~observed] - t.shape[0]] = np.flatnonzero(~observed)
    return MergedTimes(times_all[order], observed, order, query_steps)


# ------------------------------------------------------------------------------------------- track files


def read_track_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (N,) and xyz (N, 3) of a ``timestamp,x,y,z`` CSV (MMAUD/TAME convention).

    Raises:
        TrackFileError: unreadable file, missing columns, non-numeric or non-finite values, < 2 rows,
            a repeated timestamp, or several tracks (:data:`TRACK_KEYS` columns: use :func:`read_tracks_csv`).
    """
    parts = read_tracks_csv(path)
    if len(parts) > 1:
        raise TrackFileError(f"{path}: {len(parts)} tracks ({', '.join(TRACK_KEYS)}); expected one")
    return parts[0].timestamps, parts[0].xyz


@dataclass
class TrackPart:
    """One track of a track file: its :data:`TRACK_KEYS` values (empty for a single-track file), its points and,
    from a detecting localiser's file (:data:`DETECTION_COLUMNS`), each row's detection score, detected flag
    and state (``detected``, ``held``, ``fallback``, ...)."""

    keys: dict[str, str]
    timestamps: np.ndarray
    xyz: np.ndarray
    scores: np.ndarray | None = None
    detected: np.ndarray | None = None
    states: np.ndarray | None = None


def read_tracks_csv(path: Path) -> list[TrackPart]:
    """The tracks of a ``timestamp,x,y,z`` CSV, one per value of its :data:`TRACK_KEYS` columns (in file order),
    with their :data:`DETECTION_COLUMNS` when the file has a ``detected`` column. Of an ``aaute track`` output
    (``raw_x,raw_y,raw_z`` beside its smoothed ``x,y,z``) the positions read are the raw ones.

    Raises:
        TrackFileError: unreadable file, missing columns, non-numeric or non-finite values, < 2 rows, a
            timestamp repeated within one track (several tracks in a file without their key columns), or
            detection columns that are not a number, 0 / 1 and a name.
    """
    path = Path(path)
    try:
        frame = pd.read_csv(path, dtype=str, skipinitialspace=True, keep_default_na=False)
    except (OSError, UnicodeDecodeError, pd.errors.ParserError, pd.errors.EmptyDataError) as error:
        raise TrackFileError(f"{path}: cannot read a track CSV ({error})") from error
    frame.columns = [str(c).strip() for c in frame.columns]
    missing = [c for c in TRACK_COLUMNS if c not in frame.columns]
    if missing:
        raise TrackFileError(f"{path}: missing column(s) {missing}; expected the header "
                             f"{','.join(TRACK_COLUMNS)}, found {list(frame.columns)}")
    if len(frame) < 2:
        raise TrackFileError(f"{path}: {len(frame)} data row(s); a track needs at least 2")
    raw = all(f"raw_{axis}" in frame.columns for axis in "xyz")  # aaute track's rows: x,y,z are smoothed already
    values = {}
    for column in ("timestamp", "raw_x", "raw_y", "raw_z") if raw else TRACK_COLUMNS:
        numbers = pd.to_numeric(frame[column].str.strip(), errors="coerce").to_numpy(dtype=np.float64)
        bad = np.flatnonzero(~np.isfinite(numbers))
        if bad.size:
            row = int(bad[0])
            raise TrackFileError(f"{path}: column {column!r} has {bad.size} missing, non-numeric or "
                                 f"non-finite value(s), first on data row {row + 1}: "
                                 f"{frame[column].iloc[row]!r}")
        values[column.removeprefix("raw_")] = numbers
    xyz = np.stack([values["x"], values["y"], values["z"]], axis=1)
    detection = _detection_columns(path, frame) if "detected" in frame.columns else None
    keys = [column for column in TRACK_KEYS if column in frame.columns]
    groups = frame.groupby(keys, sort=False).indices.items() if keys else [((), np.arange(len(frame)))]
    parts = []
    for key, rows in groups:
        named = dict(zip(keys, (key,) if isinstance(key, str) else key, strict=True))
        t = values["timestamp"][rows]
        repeated = pd.Series(t).duplicated()
        if repeated.any():
            first = int(rows[int(np.flatnonzero(repeated)[0])])
            where = f" in track {', '.join(f'{k}={v}' for k, v in named.items())}" if named else ""
            hint = "" if named else f" (several tracks in one file need the columns {', '.join(TRACK_KEYS)})"
            raise TrackFileError(f"{path}: timestamp {frame['timestamp'].iloc[first].strip()} repeated on data row "
                                 f"{first + 1}{where}; expected one position per time{hint}")
        parts.append(TrackPart(named, t, xyz[rows], *([c[rows] for c in detection] if detection else [])))
    return parts


def _detection_columns(path: Path, frame: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scores (float, NaN allowed), detected flags (bool: 0 / 1, 0.0 / 1.0 or false / true) and states (str) of a
    track file's rows; without a ``detection_score`` column every score is NaN, without ``state`` a row is
    ``detected`` or ``fallback``."""
    flags = frame["detected"].str.strip().str.lower().replace({"1.0": "1", "0.0": "0", "true": "1", "false": "0"})
    text = {"detected": flags,
            "detection_score": frame["detection_score"].str.strip() if "detection_score" in frame.columns
            else pd.Series("nan", index=frame.index),
            "state": frame["state"].str.strip() if "state" in frame.columns
            else flags.map({"1": "detected"}).fillna("fallback")}
    scores = pd.to_numeric(text["detection_score"], errors="coerce")  # "nan" and "" read as NaN
    checks = {"detection_score": ("a number", scores.isna() & ~text["detection_score"].str.lower().isin(["nan", ""])),
              "detected": ("0 or 1", ~text["detected"].isin(["0", "1"])),
              "state": ("a state name", text["state"] == "")}
    for column, (expected, bad) in checks.items():
        if bad.any():
            row = int(np.flatnonzero(bad.to_numpy())[0])
            raise TrackFileError(f"{path}: column {column!r} is not {expected} on data row {row + 1}: "
                                 f"{frame[column].iloc[row]!r}")
    return scores.to_numpy(dtype=np.float64), (text["detected"] == "1").to_numpy(), text["state"].to_numpy(dtype=str)


def write_smoothed_tracks(path: Path, parts: Sequence[tuple[dict[str, str], SmoothedTrack]],
                          overwrite: bool = True) -> Path:
    """Write several smoothed tracks to one CSV atomically: their key columns, then ``timestamp,x,...,std_z``."""
    path = Path(path)
    frames = []
    for keys, track in parts:
        frame = pd.DataFrame(np.column_stack([track.mean, track.std]), columns=list(SMOOTHED_COLUMNS[1:]))
        frame.insert(0, "timestamp", [repr(float(v)) for v in track.timestamps])
        for position, (column, value) in enumerate(keys.items()):
            frame.insert(position, column, value)
        frames.append(frame)
    with atomic_write(path, overwrite) as tmp, open(tmp, "w", newline="") as stream:
        pd.concat(frames, ignore_index=True).to_csv(stream, index=False, float_format="%.6f", lineterminator="\n")
    return path


def write_smoothed_csv(path: Path, track: SmoothedTrack, overwrite: bool = True) -> Path:
    """Write ``timestamp,x,y,z,std_x,std_y,std_z`` atomically (temporary sibling, then rename)."""
    path = Path(path)
    frame = pd.DataFrame(np.column_stack([track.mean, track.std]), columns=list(SMOOTHED_COLUMNS[1:]))
    frame.insert(0, "timestamp", [repr(float(v)) for v in track.timestamps])
    with atomic_write(path, overwrite) as tmp, open(tmp, "w", newline="") as stream:
        frame.to_csv(stream, index=False, float_format="%.6f", lineterminator="\n")
    return path
