"""A folder of WAV files as one recording: how audio extracted from MMAUD V1 bags is passed around.

Layout (one flight per folder)::

    <flight>/
      ch1.wav ch2.wav ...        one mono WAV per channel, or one WAV per node (node1.wav, ...: any
                                 channel count each); channels in the files' natural name order
                                 (ch2 before ch10), each file's channels in its own order
      mic_positions.csv          optional: one "x, y, z" row (m) per channel (or .txt / .yaml / .yml;
                                 format: datamodules.formats.positions)
      ground_truth.csv           optional: columns t, x, y, z (s on the audio's clock, m); an optional
                                 column valid (0/1)
      aaute_layout.yaml          optional: t0 (time of the first sample, s; default 0), drone,
                                 sequence_id, mic_positions (instead of the file), nodes_share_clock

Every WAV must have the same sample rate (an error names the odd file). Files of different lengths
are cut to the shortest with a warning naming each longer file. WAVs carry no time, so all files
start at ``t0``; several files are nodes that may not share a clock (``meta["nodes_share_clock"]``
false unless the layout file says so). Audio is memory-mapped, read by range.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import numpy as np

from datamodules.formats.derived_npy import LAYOUT_FILE, read_layout_file
from datamodules.formats.node_audio import AudioNode, combine_nodes
from datamodules.formats.positions import parse_mic_positions, read_mic_positions
from datamodules.formats.ros_messages import full_scale
from datamodules.recording import (
    DRONE_TYPES,
    AudioStream,
    Recording,
    RecordingError,
    Track,
    check_monotonic,
    check_track_values,
    json_safe,
)

log = logging.getLogger(__name__)

GROUND_TRUTH_FILE = "ground_truth.csv"
POSITION_FILES = ("mic_positions.csv", "mic_positions.txt", "mic_positions.yaml", "mic_positions.yml")
LAYOUT_KEYS = ("t0", "drone", "sequence_id", "mic_positions", "nodes_share_clock")
WAV_FORMATS = {"int16": "S16LE", "int32": "S32LE", "float32": "F32LE"}


def wav_files(folder: Path) -> list[Path]:
    """The folder's WAV files in natural name order (ch2 before ch10)."""
    def natural(path: Path) -> list[Any]:
        return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name.lower())]

    return sorted((p for p in folder.glob("*.wav") if not p.name.startswith(".")), key=natural)


def is_wav_folder(folder: Path) -> bool:
    """Whether ``folder`` holds WAV files and no recordings of another layout (.mcap, .bag) beside them."""
    if not folder.is_dir() or not wav_files(folder):
        return False
    return not any(p.suffix in (".mcap", ".bag") for p in folder.iterdir())


class WavFileAudio(AudioStream):
    """One WAV file, memory-mapped; integer samples scaled by their full scale."""

    def __init__(self, path: Path, t0: float):
        from scipy.io import wavfile

        try:
            rate, data = wavfile.read(path, mmap=True)
        except (ValueError, OSError) as error:
            raise RecordingError(f"{path}: not a readable WAV file ({error})") from None
        self.path = path
        self.data = data if data.ndim == 2 else data[:, None]
        if self.data.dtype.kind not in "fi":
            raise RecordingError(f"{path}: {self.data.dtype} WAV samples; expected signed integer or float PCM")
        self.sample_rate = float(rate)
        self.t0 = float(t0)
        self.num_samples = int(self.data.shape[0])
        self.mic_positions = np.zeros((self.data.shape[1], 3))
        self.sample_format = WAV_FORMATS.get(self.data.dtype.name)
        self._scale = full_scale(self.data.dtype)

    def read(self, start: int, stop: int) -> np.ndarray:
        self._check_range(start, stop)
        block = np.asarray(self.data[start:stop], dtype=np.float32).T
        return np.ascontiguousarray(block / np.float32(self._scale) if self._scale != 1.0 else block)


def read_ground_truth_csv(path: Path) -> Track:
    """Ground truth from a CSV of columns t, x, y, z (and optionally valid).

    Raises:
        RecordingError: missing columns, unparsable values, times that do not increase, bad positions.
    """
    import pandas as pd

    try:
        table = pd.read_csv(path, comment="#")
    except (ValueError, OSError) as error:
        raise RecordingError(f"{path}: not a readable CSV ({error})") from None
    table.columns = [str(c).strip().lower() for c in table.columns]
    missing = [c for c in ("t", "x", "y", "z") if c not in table.columns]
    if missing:
        raise RecordingError(f"{path}: ground truth needs columns t, x, y, z (s, m); missing {missing}, "
                             f"found {list(table.columns)}")
    try:
        times = table["t"].to_numpy(np.float64)
        xyz = table[["x", "y", "z"]].to_numpy(np.float64)
        valid = table["valid"].to_numpy(bool) if "valid" in table.columns else None
    except (ValueError, TypeError) as error:
        raise RecordingError(f"{path}: ground truth values must be numbers ({error})") from None
    check_monotonic(times, str(path))
    check_track_values(times, xyz, valid, str(path))
    return Track(times, xyz) if valid is None else Track(times, xyz, valid)


def read_wav_folder(folder: str | Path, *, sequence_id: str | None = None, drone: str | None = None,
                    t0: float | None = None) -> Recording:
    """Open a WAV folder (see the module docstring) as a recording.

    Raises:
        RecordingError: no WAV files, unreadable files, sample rates that differ, bad positions or
            ground truth (each naming the file).
    """
    folder = Path(folder)
    files = wav_files(folder)
    if not files:
        raise RecordingError(f"{folder}: no .wav files in this folder")
    layout = read_layout_file(folder, LAYOUT_KEYS)
    start = float(t0 if t0 is not None else layout.get("t0", 0.0))
    nodes = [AudioNode(p.name, WavFileAudio(p, start), 0.0, {"file": p.name}) for p in files]
    rates = {n.name: n.stream.sample_rate for n in nodes}
    if len(set(rates.values())) > 1:
        raise RecordingError(f"{folder}: the WAV files have different sample rates ("
                             + ", ".join(f"{name} {rate:g} Hz" for name, rate in rates.items())
                             + "); resample them to one rate")
    shortest = min(n.stream.num_samples for n in nodes)
    for node in nodes:
        if node.stream.num_samples > shortest:
            log.warning("%s: %s is %.3f s longer than the shortest file; its end is left out", folder, node.name,
                        (node.stream.num_samples - shortest) / node.stream.sample_rate)
    audio, meta = combine_nodes(nodes, str(folder), bool(layout.get("nodes_share_clock", False)))
    meta.update(source_format="wav_folder", source_path=str(folder.resolve()), wav_files=[p.name for p in files])
    if len(files) > 1:  # files hold no stamps: how well they were aligned when extracted is not known here
        meta["audio_alignment_uncertainty_s"] = None
    given = [p for p in POSITION_FILES if (folder / p).is_file()]
    if len(given) > 1 or (given and "mic_positions" in layout):
        raise RecordingError(f"{folder}: microphone positions given twice ({', '.join(given)}"
                             f"{', ' + LAYOUT_FILE if 'mic_positions' in layout else ''}); keep one")
    if given:
        audio.mic_positions = read_mic_positions(folder / given[0], audio.num_channels)
    elif "mic_positions" in layout:
        audio.mic_positions = parse_mic_positions(layout["mic_positions"], audio.num_channels,
                                                  f"{folder / LAYOUT_FILE} mic_positions")
    meta["mic_positions_known"] = bool(given or "mic_positions" in layout)
    truth = folder / GROUND_TRUTH_FILE
    ground_truth = read_ground_truth_csv(truth) if truth.is_file() else None
    chosen = drone or layout.get("drone")
    if chosen is None:
        found = [d for d in DRONE_TYPES if d in folder.name.lower()]
        chosen = found[0] if len(found) == 1 else None
    return Recording(sequence_id=str(sequence_id or layout.get("sequence_id") or folder.name), drone=chosen,
                     audio=audio, ground_truth=ground_truth, meta=json_safe(meta))
