"""Fusion of the two LiDARs by time, and DBSCAN against isolated (solar) returns.

The AAUTE paper's steps 7-8 [B]: the Mid-360's dynamic part and the Avia's sampled points are
interleaved by timestamp, each frame keeping its own stamp (as Deng et al. do,
``reference/mmaud_and_teacher.md`` section 3.2), and DBSCAN over the accumulation keeps only
points with enough neighbours: sunlight false returns are single points scattered over the range
gate (section 4.1), the drone's returns pile up along its path.

Deng et al. run this DBSCAN over a whole sequence; to keep memory bounded by a window, the frames
are decided in blocks of ``block_s`` with ``pad_s`` of context on both sides (the same answer as
a sequence-wide DBSCAN wherever the drone's track does not run out of the padded window).
Each surviving frame becomes one *evidence* row: the centroid of its returns in the window's
dominant cluster (the one with most returns in the window among those present in that frame).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from datamodules.teacher.clustering import dbscan


@dataclass
class FramePoints:
    """Candidate drone returns of one frame of one sensor."""

    time: float  #: representative time of the returns (frame stamp + mid-frame offset)
    sensor: str
    points: np.ndarray  #: N x 3


@dataclass
class Evidence:
    """One frame's estimate of the drone position."""

    time: float
    xyz: np.ndarray
    count: int  #: returns behind the centroid
    sensor: str


def _decide(frames: list[FramePoints], start: float, stop: float, eps: float, min_samples: int,
            cube_m: float) -> list[Evidence]:
    """Evidence of the frames in [start, stop) from a DBSCAN over all ``frames`` (the padded window)."""
    if not any(start <= f.time < stop for f in frames):
        return []
    points = np.concatenate([f.points for f in frames])
    if points.shape[0] < min_samples:
        return []
    labels = dbscan(points, eps, min_samples, cube_m)
    clustered = labels >= 0
    if not clustered.any():
        return []
    window_count = np.bincount(labels[clustered])
    bounds = np.cumsum([0] + [f.points.shape[0] for f in frames])
    out = []
    for f, a, b in zip(frames, bounds[:-1], bounds[1:], strict=True):
        if not start <= f.time < stop:
            continue
        own = labels[a:b]
        present = np.unique(own[own >= 0])
        if present.size == 0:
            continue
        dominant = present[np.argmax(window_count[present])]
        members = f.points[own == dominant]
        out.append(Evidence(f.time, members.mean(axis=0), int(members.shape[0]), f.sensor))
    return out


def denoise_fused(frames: Iterable[FramePoints], eps: float = 1.0, min_samples: int = 10, block_s: float = 2.0,
                  pad_s: float = 2.0, cube_m: float = 0.25) -> Iterator[Evidence]:
    """Evidence rows, in time order, from time-ordered candidate frames of both sensors.

    Args:
        frames: candidate frames sorted by time (empty frames are ignored).
        eps, min_samples: the noise DBSCAN. The AAUTE paper gives no values; Deng et al. use
            eps 1 m, min_samples 10 for this step (section 3.2 [V]).
        block_s: frames are decided in blocks of this length (s).
        pad_s: context (s) on each side of a block that enters its DBSCAN.
        cube_m: DBSCAN sample reduction (see :func:`~datamodules.teacher.clustering.dbscan`).
    """
    buffer: deque[FramePoints] = deque()
    start: float | None = None
    last = -np.inf
    for frame in frames:
        if frame.time < last:
            raise ValueError(f"fusion needs frames in time order ({frame.time:.6f} after {last:.6f})")
        last = frame.time
        if frame.points.shape[0] == 0:
            continue
        if start is None:
            start = frame.time
        buffer.append(frame)
        while frame.time >= start + block_s + pad_s:
            yield from _decide(list(buffer), start, start + block_s, eps, min_samples, cube_m)
            start = _next_start(buffer, start + block_s, block_s)
            while buffer and buffer[0].time < start - pad_s:
                buffer.popleft()
    while start is not None and buffer and buffer[-1].time >= start:
        yield from _decide(list(buffer), start, start + block_s, eps, min_samples, cube_m)
        start = _next_start(buffer, start + block_s, block_s)
        while buffer and buffer[0].time < start - pad_s:
            buffer.popleft()


def _next_start(buffer: deque[FramePoints], start: float, block_s: float) -> float:
    """The next block's start, skipping empty stretches of time in whole blocks."""
    later = [f.time for f in buffer if f.time >= start]
    if later and later[0] >= start + block_s:
        return start + np.floor((later[0] - start) / block_s) * block_s
    return start
