"""The physical limit of a benchmark table: the Cramér–Rao bound of every test window, as a result row.

A suite's ``bound`` key (``false``, ``true`` or ``{band_hz: [low, high]}``; default ``true`` for simulated data,
``false`` for real) adds one ``bound`` job per protocol x seed. It takes the same test windows as the constant
predictor and gives each the bound of :mod:`zoo.bounds` for its recording's microphone geometry, its true
position, the window's length and the drone's SNR spectrum at every microphone during it (the simulator's
record, or :func:`datamodules.snr.estimate_snr_spectrum` from the audio, which the row then says). The
microphones must share one clock and have known positions: a recording whose positions are all zero is
refused. Training positions enter as a Gaussian prior (their spread per axis, Van Trees' bound), so a window
where the time differences cannot fix the position (a singular geometry) is bounded by what knowing the flight
region gives rather than by infinity.

The row's E columns hold the RMS of the per-window bound (overall, per drone, per range band; the same under
both light conditions: the bound concerns audio), ``bound_median_m`` the median; the per-window values go to
``bounds.csv`` (the prediction columns with empty estimates, plus ``bound_m``) for the figures.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from benchmarks.results import DRONES, RANGES, range_name
from datamodules.errors import AauteError
from datamodules.snr import SnrSpectrum, recording_snr
from zoo.bounds import SPEED_OF_SOUND, window_bounds

BOUND_METHOD = "Physical limit (CRLB)"
BOUND_MODEL = "crlb"
BOUND_KEYS = {"band_hz"}


class BoundError(AauteError, ValueError):
    """A recording or setting the bound cannot be computed for (the message names it)."""


def bound_options(value: Any, data_kind: str, where: str) -> dict[str, Any] | None:
    """The suite's ``bound`` key as job options (None: no bound job); ``where`` names the suite in errors."""
    if value is None:
        value = data_kind == "simulated"
    if value is False:
        return None
    if value is True:
        return {"band_hz": None}
    if not isinstance(value, dict) or set(value) - BOUND_KEYS:
        raise BoundError(f"{where}: bound must be false, true or {{band_hz: [low, high]}}, got {value!r}")
    band = value.get("band_hz")
    if band is not None:
        if (not isinstance(band, list | tuple) or len(band) != 2
                or not all(isinstance(v, int | float) for v in band) or not 0 <= band[0] < band[1]):
            raise BoundError(f"{where}: bound.band_hz must be [low, high] Hz with 0 <= low < high, got {band!r}")
        band = [float(band[0]), float(band[1])]
    return {"band_hz": band}


def prior_spread(train_positions: np.ndarray) -> float:
    """RMS per-axis standard deviation of the training positions (m): the prior of the Bayesian bound."""
    positions = np.asarray(train_positions, dtype=np.float64)
    positions = positions[np.all(np.isfinite(positions), axis=1)]
    if len(positions) < 2:
        raise BoundError("the bound's prior needs at least two training positions with ground truth")
    return float(np.sqrt(np.mean(np.var(positions, axis=0))))


def recording_inputs(path: Path, options: dict[str, Any]) -> tuple[SnrSpectrum, np.ndarray, float]:
    """(SNR spectrum, microphone positions, audio start time) of one recording."""
    from datamodules.formats import open_recording

    recording = open_recording(path, **options)
    audio = recording.audio
    if audio is None:
        raise BoundError(f"{path}: the recording has no audio, so it has no localisation bound")
    mics = np.asarray(audio.mic_positions, dtype=np.float64)
    unknown = (recording.meta or {}).get("mic_positions_known") is False
    if unknown or mics.shape[0] < 4 or not np.any(mics) or not np.all(np.isfinite(mics)):
        raise BoundError(f"{path}: microphone positions unknown or all zero ({mics.shape[0]} channels); the bound "
                         f"needs at least 4 microphones at known positions (set bound: false in the suite)")
    try:
        spectrum = recording_snr(recording)
    except ValueError as error:
        raise BoundError(f"{path}: {error}") from None
    return spectrum, mics, float(audio.t0)


def bound_frame(datamodule, band_hz: list[float] | None, speed_of_sound: float = SPEED_OF_SOUND
                ) -> pd.DataFrame:
    """Every test window's bound (``bound_m``) with the prediction columns (estimates empty), once per light."""
    train = datamodule.sequences["train"]
    prior = prior_spread(np.concatenate([p.gt[p.gt_valid.astype(bool)] for p in train]))
    seconds = float(datamodule.hparams.window_seconds)
    band = None if band_hz is None else (band_hz[0], band_hz[1])
    options = dict(datamodule.hparams.reader_options or {})
    recordings: dict[Path, tuple[SnrSpectrum, np.ndarray, float]] = {}
    parts = []
    for piece in datamodule.sequences["test"]:
        if piece.path not in recordings:
            recordings[piece.path] = recording_inputs(piece.path, options)
        spectrum, mics, t0 = recordings[piece.path]
        valid = piece.gt_valid.astype(bool)
        bounds = np.full(len(piece), np.nan)
        if valid.any():
            bounds[valid] = window_bounds(spectrum, mics, piece.gt[valid], piece.times[valid] - t0, seconds, band,
                                          speed_of_sound, prior)
        part = pd.DataFrame({"sequence_id": piece.sequence_id, "recording_id": piece.recording_id,
                             "drone": piece.drone or "", "timestamp": piece.times,
                             "gt_valid": valid.astype(int), "bound_m": bounds, "snr_source": spectrum.source})
        part[["x", "y", "z"]] = np.nan
        part[["gt_x", "gt_y", "gt_z"]] = piece.gt
        part[["smooth_x", "smooth_y", "smooth_z"]] = np.nan
        parts.append(part)
    if not parts:
        raise BoundError("the split has no test windows to bound")
    frame = pd.concat(parts, ignore_index=True)
    return pd.concat([frame.assign(light=light) for light in datamodule.test_lights], ignore_index=True)


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def bound_metrics(frame: pd.DataFrame, band_hz: list[float] | None) -> dict[str, Any]:
    """The row's columns: RMS of the bound overall (E, RMSE), per drone and per range band; the median; SNR source."""
    valid = frame[(frame["gt_valid"] == 1) & np.isfinite(frame["bound_m"])]
    if valid.empty:
        raise BoundError("no test window with ground truth to bound")
    distance = np.linalg.norm(valid[["gt_x", "gt_y", "gt_z"]].to_numpy(float), axis=1)
    row: dict[str, Any] = {}
    for light in valid["light"].unique():
        in_light = (valid["light"] == light).to_numpy()
        bound = valid["bound_m"].to_numpy(float)
        row[f"E_{light}"] = row[f"RMSE_{light}"] = _rms(bound[in_light])
        for drone in DRONES:
            rows = in_light & (valid["drone"] == drone).to_numpy()
            if rows.any():
                row[f"E_{light}_{drone}"] = _rms(bound[rows])
        for low, high in RANGES:
            rows = in_light & (distance >= low) & (distance < (np.inf if high is None else high))
            if rows.any():
                row[f"E_{light}_{range_name(low, high)}"] = _rms(bound[rows])
    first_light = valid[valid["light"] == valid["light"].iloc[0]]
    row["bound_median_m"] = float(np.median(first_light["bound_m"]))
    row["snr_source"] = ",".join(sorted(valid["snr_source"].unique()))
    row["bound_band_hz"] = "full" if band_hz is None else f"{band_hz[0]:g}-{band_hz[1]:g}"
    return row


def bound_sentence(rows: pd.DataFrame) -> str:
    """The caption's account of the CRLB row ('' when the table has none)."""
    bound = rows[rows["kind"] == "bound"]
    if bound.empty:
        return ""
    medians = ", ".join(f"{value:.3g}" for value in pd.to_numeric(bound["bound_median_m"], errors="coerce").dropna())
    sources = "; ".join(dict.fromkeys(bound["snr_source"].astype(str)))
    bands = "; ".join(dict.fromkeys("the full band" if band in ("", "full") else f"band {band} Hz"
                                    for band in bound["bound_band_hz"].astype(str)))
    estimated = " (estimated from the audio)" if "estimated" in sources else ""
    return (f"{BOUND_METHOD}: the Cramér–Rao bound of time-difference localisation for each test window "
            f"(Knapp–Carter / Hahn–Tretter delay information, the rig's microphone geometry, the true position, "
            f"the window length, the drone's SNR per microphone and 25 Hz bin from the {sources} record"
            f"{estimated}, {bands}, training positions as a Gaussian prior); its E is the RMS of the "
            f"per-window bound on the RMS position error, median {medians} m. It is a local bound on any unbiased "
            f"estimator from the direct path alone, shown for reference and never ranked.")
