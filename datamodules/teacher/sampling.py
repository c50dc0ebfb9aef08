"""Farthest point sampling of Avia frames (the AAUTE paper's step 6 [B]).

Bounds the points an Avia frame contributes (Deng et al. keep at most 100,
``reference/mmaud_and_teacher.md`` section 3.2 [V]) while keeping the frame's spatial extent: a
close drone can return a few hundred points in one 0.1 s frame, which would otherwise outweigh
every other frame in the fusion and the spline. Neither scikit-learn nor SciPy offers FPS, so it
is the textbook greedy loop, vectorised over points.
"""

from __future__ import annotations

import numpy as np


def farthest_point_sampling(points: np.ndarray, max_points: int = 100) -> np.ndarray:
    """Indices (sorted) of at most ``max_points`` points chosen by farthest point sampling.

    Squared Euclidean distances as in Deng et al. The start is the point nearest the frame's
    per-axis median, not a random one (Deng starts at random), so the result is deterministic.
    """
    points = np.asarray(points, dtype=np.float64)
    n = points.shape[0]
    if n <= max_points:
        return np.arange(n)
    if max_points <= 0:
        return np.zeros(0, dtype=np.int64)
    chosen = np.empty(max_points, dtype=np.int64)
    start = int(np.argmin(np.sum((points - np.median(points, axis=0)) ** 2, axis=1)))
    chosen[0] = start
    nearest = np.sum((points - points[start]) ** 2, axis=1)
    for k in range(1, max_points):
        index = int(np.argmax(nearest))
        chosen[k] = index
        np.minimum(nearest, np.sum((points - points[index]) ** 2, axis=1), out=nearest)
    return np.sort(chosen)
