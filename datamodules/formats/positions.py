"""Microphone positions as configuration: parsing and checking them, and the refusal to steer without them.

Positions are one ``[x, y, z]`` in metres per audio channel, in channel order, in the rig frame. They
are given by the user (never guessed for a method that steers with them), in one of two forms:

* a ``mic_positions`` key of a mapping YAML or ``aaute_layout.yaml``: a list of ``[x, y, z]``;
* a positions file (:func:`read_mic_positions`): YAML (``.yaml``/``.yml``, that list or a mapping
  with a ``mic_positions`` key), or text/CSV with one ``x, y, z`` row per channel (commas or spaces,
  an optional header line such as ``x,y,z``, ``#`` comments)::

      # x, y, z in metres, one row per channel
      x,y,z
      1.5,1.5,0.2
      -1.5,1.5,0.7

A recording read without positions carries ``meta["mic_positions_known"] = False`` (and zeros as
positions); phase recipes refuse it (:func:`require_mic_positions`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from datamodules.recording import Recording, RecordingError

#: coordinates beyond this (m) are implausible for a microphone rig (millimetres or centimetres given?)
PLAUSIBLE_RIG_M = 100.0


def parse_mic_positions(value: Any, channels: int | None, what: str) -> np.ndarray:
    """Positions (channels x 3, m) from a list of ``[x, y, z]``, checked.

    Args:
        value: a nested list (or array) of numbers, one row per channel.
        channels: the recording's channel count (None: any count).
        what: the source, for messages (a file, a mapping key).

    Raises:
        RecordingError: not rows of three numbers, a count other than ``channels``, non-finite values,
            coordinates beyond :data:`PLAUSIBLE_RIG_M` or two microphones at one point.
    """
    try:
        positions = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise RecordingError(f"{what}: microphone positions must be a list of [x, y, z] in metres, one per "
                             f"channel; got {value!r}") from None
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise RecordingError(f"{what}: microphone positions must be a list of [x, y, z] in metres, one per "
                             f"channel; got an array of shape {positions.shape}")
    if channels is not None and positions.shape[0] != channels:
        raise RecordingError(f"{what}: {positions.shape[0]} microphone position(s) for {channels} audio "
                             f"channel(s); give one [x, y, z] per channel, in channel order")
    if not np.isfinite(positions).all():
        raise RecordingError(f"{what}: microphone positions hold NaN or infinite values")
    largest = float(np.abs(positions).max(initial=0.0))
    if largest > PLAUSIBLE_RIG_M:
        raise RecordingError(f"{what}: a microphone lies {largest:g} m from the rig's origin; positions are in "
                             f"metres (millimetres or centimetres given?)")
    if positions.shape[0] > 1:
        gaps = np.linalg.norm(positions[:, None] - positions[None], axis=-1) + np.eye(positions.shape[0])
        if gaps.min() < 1e-6:
            i, j = np.unravel_index(np.argmin(gaps), gaps.shape)
            raise RecordingError(f"{what}: microphones {int(i)} and {int(j)} are at the same point "
                                 f"{positions[i].tolist()}")
    return positions


def read_mic_positions(path: str | Path, channels: int | None = None) -> np.ndarray:
    """Microphone positions (channels x 3, m) from a YAML or text/CSV file (see the module docstring).

    Raises:
        RecordingError: an unreadable file or positions that :func:`parse_mic_positions` refuses.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as error:
        raise RecordingError(f"{path}: cannot read the microphone positions ({error.strerror})") from None
    if path.suffix.lower() in (".yaml", ".yml"):
        import yaml

        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError as error:
            raise RecordingError(f"{path}: not valid YAML ({error})") from None
        if isinstance(value, dict):
            value = value.get("mic_positions")
        return parse_mic_positions(value, channels, str(path))
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        cells = line.replace(",", " ").split()
        try:
            rows.append([float(c) for c in cells])
        except ValueError:
            if rows or not all(c.isidentifier() for c in cells):  # only a first line of names is a header
                raise RecordingError(f"{path}: line {number} is not three numbers x, y, z (m): {line!r}") from None
    if any(len(r) != 3 for r in rows):
        bad = next(i for i, r in enumerate(rows) if len(r) != 3)
        raise RecordingError(f"{path}: row {bad + 1} holds {len(rows[bad])} numbers; expected x, y, z (m)")
    return parse_mic_positions(rows, channels, str(path))


def positions_known(recording: Recording) -> bool:
    """Whether the recording's microphone positions were given (simulated and converted-with-positions ones)."""
    return recording.audio is not None and recording.meta.get("mic_positions_known", True) is not False


def require_mic_positions(recording: Recording, path: str | Path, use: str) -> None:
    """Refuse to steer with positions nobody gave (``use`` names what needs them).

    Raises:
        RecordingError: one line naming the recording and how to give its positions.
    """
    if not positions_known(recording):
        raise RecordingError(f"{path}: {use} needs the microphone positions, but recording "
                             f"{recording.sequence_id!r} was read without them (meta mic_positions_known: false); "
                             f"give mic_positions (one [x, y, z] in metres per channel) in the mapping YAML or "
                             f"aaute_layout.yaml and convert it again")
