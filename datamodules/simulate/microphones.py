"""Microphone geometries (rig frame, z up, metres above the roof surface).

MMAUD has "four audio array nodes" but publishes no geometry (``simulation_sources.md`` section 3, 8).
The default, ``distributed4``, puts four single-microphone nodes on the corners of a 3 m square
around the rig at heights 0.2, 0.7, 1.2 and 1.7 m with one shared sample clock (DESIGN.md
section 5): a small single array observes direction only, not range (``simulation_sources.md`` 4.3), and
the spread heights make the ground-reflection interference differ between channels.
``respeaker4`` (45.7 mm square, ReSpeaker USB Mic Array v2.0) and ``respeaker6`` (R = 46.3 mm)
are the arrays of the NTU group's related work [V S6, S7, S38, S39]; they sit at 1.2 m here.
"""

from __future__ import annotations

import numpy as np

ARRAY_HEIGHT = 1.2  #: height of the compact arrays' centre above the roof (m) [E]


def distributed4(side: float = 3.0, heights: tuple[float, ...] = (0.2, 0.7, 1.2, 1.7)) -> np.ndarray:
    """Four nodes on the corners of a ``side`` square centred on the rig, one height each."""
    h = side / 2.0
    corners = np.array([[h, h], [-h, h], [-h, -h], [h, -h]])
    return np.column_stack([corners, np.asarray(heights, dtype=np.float64)])


def respeaker4(side: float = 0.0457, height: float = ARRAY_HEIGHT) -> np.ndarray:
    """ReSpeaker USB 4-mic array: a square of side 45.7 mm (channels 1-4)."""
    return distributed4(side, (height,) * 4)


def respeaker6(radius: float = 0.0463, height: float = ARRAY_HEIGHT) -> np.ndarray:
    """ReSpeaker 6-mic circular array, R = 46.3 mm."""
    angles = np.arange(6) * np.pi / 3.0
    return np.column_stack([radius * np.cos(angles), radius * np.sin(angles), np.full(6, height)])


GEOMETRIES = {"distributed4": distributed4, "respeaker4": respeaker4, "respeaker6": respeaker6}


def mic_geometry(name_or_positions: str | list | np.ndarray) -> np.ndarray:
    """A preset by name, or explicit positions (channels x 3, metres) checked for shape."""
    if isinstance(name_or_positions, str):
        try:
            return GEOMETRIES[name_or_positions]()
        except KeyError:
            raise ValueError(
                f"unknown microphone geometry {name_or_positions!r}; known: {sorted(GEOMETRIES)}"
            ) from None
    positions = np.asarray(name_or_positions, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3 or positions.shape[0] < 1:
        raise ValueError(f"microphone positions must be channels x 3 (metres); got shape {positions.shape}")
    return positions
