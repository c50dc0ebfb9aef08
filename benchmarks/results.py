"""The ``results.csv`` schema: one row per benchmark job, appended atomically, read back with checks.

Every number of the leaderboard comes from this file. A row is one of four kinds:

- ``model``: a zoo model trained and tested (one model x protocol x seed), with its test metrics
  per light condition, per drone and per range, smoothed E (``smoother`` names the smoother's preset),
  and the provenance of the run;
- ``constant``: the constant-position predictor (the mean training target) on the same split;
- ``bound``: the physical limit, the Cramér–Rao bound of every test window of the split
  (:mod:`benchmarks.limit`): its E columns are the RMS of the per-window bound, ``bound_median_m`` the median;
- ``profile``: parameters, GMACs / FLOPs and latency of a model at its reference input shapes.

Metric columns are in metres: ``Dx/Dy/Dz`` mean absolute error per axis, ``E`` mean Euclidean
error, ``RMSE`` root mean squared Euclidean error; ``_ideal`` / ``_dark`` is the light condition;
``E_<light>_<drone>`` and ``E_<light>_r<lo>_<hi>`` break E down by drone type and by the drone's
distance from the rig origin. A column that does not apply to a row is empty, never zero.
"""

from __future__ import annotations

import csv
import fcntl
import io
import logging
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pandas as pd

from datamodules.atomic import atomic_write
from datamodules.errors import AauteError
from datamodules.recording import DRONE_TYPES

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
KINDS = ("model", "constant", "profile", "bound")
CATEGORIES = ("supervised", "self-supervised", "non-learned", "reference")
PROTOCOLS = ("by_sequence", "time_blocks", "random_windows")
LIGHTS = ("ideal", "dark")
DRONES = DRONE_TYPES
RANGES = ((0, 10), (10, 20), (20, 30), (30, None))  #: metres from the rig origin; None: no upper bound


def range_name(low: float, high: float | None) -> str:
    """Column suffix of a distance band: ``r0_10``, ..., ``r30_inf``."""
    return f"r{low:g}_{'inf' if high is None else f'{high:g}'}"


IDENTITY = ["schema_version", "kind", "suite", "job_id", "status", "error", "log_path"]
METHOD = ["model", "method", "category", "alpha", "protocol", "seed"]
DATA = ["data", "data_kind", "data_root", "data_fingerprint", "drones", "lights",
        "n_train_sequences", "n_val_sequences", "n_test_sequences",
        "n_train_windows", "n_val_windows", "n_test_windows"]
BUDGET = ["max_epochs", "limit_train_batches", "epochs_run", "best_epoch", "batch_size", "budget_note", "smoother"]
METRICS = [f"{name}_{light}" for light in LIGHTS for name in ("Dx", "Dy", "Dz", "E", "RMSE", "E_smooth")]
BREAKDOWN = ([f"E_{light}_{drone}" for light in LIGHTS for drone in DRONES]
             + [f"E_{light}_{range_name(*band)}" for light in LIGHTS for band in RANGES])
PROFILE = ["params_total_M", "params_used_M", "gmacs", "gflops", "profile_inputs",
           "latency_ms_1t", "latency_iqr_ms_1t", "latency_ms_all", "latency_iqr_ms_all", "threads_all",
           "throughput_batch", "throughput_1t", "throughput_all", "frontend_ms", "end_to_end_ms"]
PROVENANCE = ["config_hash", "checkpoint_path", "predictions_path", "git_commit", "git_dirty", "versions",
              "cpu", "gpu", "threads", "launcher", "slurm_job_id", "node", "started_at", "wall_time_s",
              "peak_rss_mb"]
BOUND = ["bound_median_m", "snr_source", "bound_band_hz"]
COLUMNS = IDENTITY + METHOD + DATA + BUDGET + METRICS + BREAKDOWN + PROFILE + BOUND + PROVENANCE
#: columns added to schema 1 after its first files were written: empty when an older file lacks them
LATER_COLUMNS = ("smoother", "slurm_job_id", "node", *BOUND, "peak_rss_mb")
#: columns of a model job's per-window predictions CSV (``predictions_path``; written by jobs, read by plots); a net
#: that detects (``srp_phat``) adds ``detection_score, detected, state`` after them
PREDICTION_COLUMNS = ["sequence_id", "recording_id", "drone", "light", "timestamp", "x", "y", "z",
                      "gt_x", "gt_y", "gt_z", "gt_valid", "smooth_x", "smooth_y", "smooth_z"]


class ResultsError(AauteError, ValueError):
    """A ``results.csv`` that cannot be read as this schema (the message names the file and the problem)."""


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return "" if value != value else f"{value:.6g}"  # NaN -> empty
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def format_row(row: Mapping[str, Any]) -> dict[str, str]:
    """``row`` as schema cells: unknown keys refused, missing ones empty, the schema version set."""
    unknown = sorted(set(row) - set(COLUMNS))
    if unknown:
        raise ResultsError(f"result row has columns outside schema {SCHEMA_VERSION}: {unknown}")
    if row.get("kind") not in KINDS:
        raise ResultsError(f"result row kind must be one of {KINDS}, got {row.get('kind')!r}")
    cells = {column: _cell(row.get(column)) for column in COLUMNS}
    cells["schema_version"] = str(SCHEMA_VERSION)
    return cells


@contextmanager
def results_lock(path: str | Path) -> Iterator[None]:
    """Hold an exclusive lock on ``results.csv`` (``flock`` on the sibling ``.<name>.lock``).

    Appending reads the file, checks it and renames a rewritten copy into place; without the lock two
    processes appending at once (two ``aaute benchmark`` runs, many Slurm jobs ending together) would
    each rename their own copy and one row would be lost.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_name(f".{path.name}.lock"), "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def append_rows(path: str | Path, rows: Iterable[Mapping[str, Any]]) -> None:
    """Append rows to ``results.csv`` atomically: the file is rewritten to a temporary sibling and renamed.

    An interrupted append therefore leaves either the old file or the new one, never half a row, and
    concurrent appenders take turns (:func:`results_lock`), so none loses another's rows. Columns a
    user added to the file (notes, ...) are kept, after the schema's, with their values; the new rows
    leave them empty.
    """
    path = Path(path)
    new = [format_row(row) for row in rows]
    if not new:
        return
    with results_lock(path):
        _append_formatted(path, new)


def _append_formatted(path: Path, new: list[dict[str, str]]) -> None:
    old = path.read_text() if path.exists() else ""
    columns = COLUMNS
    if old:
        header, earlier = read_cells(path)  # refuses a file of another schema
        columns = COLUMNS + [column for column in header if column not in COLUMNS]
        if header != columns:  # an older header or user columns out of place: rewrite its rows under this one
            new = earlier.reindex(columns=columns, fill_value="").to_dict("records") + new
            old = ""
        elif not old.endswith("\n") and len(old.splitlines()) - 1 > len(earlier):
            old = old[: old.rfind("\n") + 1]  # drop a line cut short by an interrupted writer
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns, lineterminator="\n", restval="")
    if not old:
        writer.writeheader()
    writer.writerows(new)
    if old and not old.endswith("\n"):
        old += "\n"  # a complete last line without its newline
    with atomic_write(path) as tmp:
        tmp.write_text(old + buffer.getvalue())


def read_cells(path: str | Path) -> tuple[list[str], pd.DataFrame]:
    """The file's header and its rows as text cells, after the schema checks of :func:`read_results`."""
    path = Path(path)
    if not path.is_file():
        raise ResultsError(f"{path}: no such results file (run 'aaute benchmark' first)")
    text = path.read_text()
    lines = text.splitlines()
    if not lines:
        raise ResultsError(f"{path}: empty file, expected a results.csv header")
    header = next(csv.reader([lines[0]]))
    missing = [column for column in COLUMNS if column not in header and column not in LATER_COLUMNS]
    if "schema_version" not in header:
        raise ResultsError(f"{path}: not a results.csv (no schema_version column)")
    if missing:
        raise ResultsError(f"{path}: missing column(s) {missing[:8]}{' ...' if len(missing) > 8 else ''} "
                           f"of results schema {SCHEMA_VERSION}")
    records = list(csv.reader(lines[1:]))
    if records and not text.endswith("\n") and len(records[-1]) != len(header):
        log.warning("%s: last line is incomplete (an interrupted write); ignored", path)
        records = records[:-1]
    for number, record in enumerate(records, start=2):
        if len(record) != len(header):
            raise ResultsError(f"{path}: line {number} has {len(record)} fields, the header {len(header)}")
    frame = pd.DataFrame(records, columns=header, dtype=str)
    for column in LATER_COLUMNS:
        if column not in frame:
            frame[column] = ""
    versions = set(frame["schema_version"]) - {str(SCHEMA_VERSION)}
    if versions:
        raise ResultsError(f"{path}: rows of results schema version(s) {sorted(versions)}; this version "
                           f"reads {SCHEMA_VERSION} (re-run the suite into a new file)")
    return header, frame


#: measured quantities: a number >= 0 or empty (the leaderboard ranks them)
MEASURES = [*METRICS, *BREAKDOWN, *(c for c in PROFILE if c not in ("profile_inputs", "threads_all")), "wall_time_s",
            "peak_rss_mb"]
NUMERIC = ["seed", "alpha", *DATA[6:], *BUDGET[:5], *METRICS, *BREAKDOWN,
           *(c for c in PROFILE if c != "profile_inputs"), "bound_median_m", "threads", "wall_time_s",
           "peak_rss_mb"]


def read_results(path: str | Path, check_values: bool = True) -> pd.DataFrame:
    """Read ``results.csv``; a file of another schema version or with missing columns is refused.

    A last line cut short (by a writer without atomic appends) is dropped with a warning; every
    other malformed line is an error naming its line number. With ``check_values``, a numeric cell
    that is text, and a measure (metric, breakdown, profile number) that is infinite, NaN or negative,
    is an error naming the file, line and column: such a number must never be ranked.
    """
    path = Path(path)
    _, frame = read_cells(path)
    for column in NUMERIC:
        text = frame[column].str.strip()
        values = pd.to_numeric(text, errors="coerce")  # empty cells -> NaN
        if check_values:
            wrong = values.isna()
            if column in MEASURES:
                wrong |= (values.abs() == float("inf")) | (values < 0)
            bad = text.ne("") & wrong
            if bad.any():
                row = int(bad.to_numpy().argmax())
                expected = "a finite number >= 0" if column in MEASURES else "a number"
                raise ResultsError(f"{path}: line {row + 2}, column {column}: {frame[column].iloc[row]!r} is not "
                                   f"{expected} (fix or empty the cell)")
        frame[column] = values
    return frame


def latest(frame: pd.DataFrame) -> pd.DataFrame:
    """The newest row of each job (a re-run supersedes earlier rows of the same ``job_id`` and suite)."""
    return frame.drop_duplicates(subset=["suite", "job_id"], keep="last").reset_index(drop=True)
