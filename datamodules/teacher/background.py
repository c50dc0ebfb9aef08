"""Static background: space that is occupied again and again over the recording.

This step is **not in the AAUTE paper** (which only says "drop the largest and the smallest
cluster"); it is this project's addition, needed because a rooftop Mid-360 frame holds ~4,000
background returns and only 0-5 drone returns (``reference/mmaud_and_teacher.md`` section 2.2,
``reference/simulation.md`` section 5.3). It follows the voxel-occupancy differencing of Liang et
al. (section 3.3: points whose voxel is occupied in another accumulation are background).

Rule: space is cut into cubes whose side grows with the range from the sensor, so that every cube
subtends about 2-4 degrees: ``voxel_m`` up to ``near_range_m``, doubling with every doubling of
the range beyond (0.5 m to 15 m, 1 m to 30 m, 2 m to 60 m, 4 m beyond, with the defaults). The
Mid-360 fills 1-degree cells within 3-5 scans (``reference/simulation.md`` section 5.2 [E, S54]), so
a surface hits each such cube in nearly every chunk of 20 scans, even at grazing incidence far
away (fixed 0.5 m cubes left ~120 background returns per simulated chunk non-static, mostly the
roof at 20-30 m and facades at 40-60 m; range-scaled cubes leave ~15, and lost no drone return).
For each chunk we note which cubes hold at least one return. A cube is *static* when it is
occupied in at least ``max(min_chunks, min_fraction * N)`` of the recording's N chunks, and a
point is static when its cube or one within ``dilation`` cubes (same size) is; a drone occupies
a cube only while it is there. ``min_fraction`` = 0.8 trades the two errors: on the simulated
rooftop it leaves ~30 background returns per chunk non-static (~15 at 0.5), and only a drone that
stays within one cube for more than 80 % of the recording is taken for background.

The map is built over the whole recording (a first pass over the frames) because a drone may
hover for tens of seconds (the simulator chains 2-10 s hovers; a sliding window of 30 s took an
18 s hover for background). Its memory grows with the space seen (scene, the drone's path,
false returns: about 1 MB per hour of false returns), not with the number of frames.
"""

from __future__ import annotations

from itertools import product

import numpy as np
import pandas as pd

_BITS = 20
_OFFSET = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1
_LEVEL_SHIFT = 3 * _BITS
MAX_LEVEL = 3
_PACKED_OFFSET = (_OFFSET << (2 * _BITS)) | (_OFFSET << _BITS) | _OFFSET


def voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One int64 key per point naming its cube of side ``voxel_m`` (20 bits per axis, +-5e5 cubes)."""
    index = np.floor(np.asarray(points, dtype=np.float64) / voxel_m).astype(np.int64) + _OFFSET
    np.clip(index, 0, _MASK, out=index)
    return (index[:, 0] << (2 * _BITS)) | (index[:, 1] << _BITS) | index[:, 2]


def range_scaled_keys(points: np.ndarray, origin: np.ndarray, voxel_m: float, near_range_m: float) -> np.ndarray:
    """Keys of cubes of side ``voxel_m * 2**level``, level 0 within ``near_range_m`` of ``origin``
    and one more per doubling of the range (at most :data:`MAX_LEVEL`); the level is part of the key."""
    points = np.asarray(points, dtype=np.float64)
    if points.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    offset = points - origin
    squared = np.einsum("ij,ij->i", offset, offset)
    level = np.zeros(points.shape[0], dtype=np.int64)
    for k in range(MAX_LEVEL):
        level += squared > (near_range_m * 2.0**k) ** 2
    scale = (1.0 / (voxel_m * np.exp2(np.arange(MAX_LEVEL + 1))))[level]
    index = np.floor(points * scale[:, None])
    np.clip(index, -_OFFSET, _OFFSET - 1, out=index)
    # the packed key in exact float64 arithmetic (all terms are integers below 2**53; no BLAS call)
    packed = (index[:, 0] * 2.0 ** (2 * _BITS) + index[:, 1] * 2.0**_BITS + index[:, 2]).astype(np.int64)
    packed += _PACKED_OFFSET
    return (level << _LEVEL_SHIFT) | packed


def neighbour_offsets(dilation: int) -> np.ndarray:
    """Key offsets of the (2 d + 1)^3 cubes around a cube (d = ``dilation``)."""
    steps = range(-dilation, dilation + 1)
    return np.array([(dx << (2 * _BITS)) + (dy << _BITS) + dz for dx, dy, dz in product(steps, steps, steps)],
                    dtype=np.int64)


class StaticMap:
    """Occupancy counts of cubes over a recording's chunks, then the static test for points.

    Args:
        origin: the sensor's position (ranges are measured from it).
        voxel_m: cube side (m) near the sensor; 0.5 m, about the size of a drone plus its hover
            wander [P].
        near_range_m: range (m) up to which cubes have side ``voxel_m``; 15 m makes a 0.5 m cube
            subtend 1.9 degrees [P].
        min_fraction: a static cube is occupied in at least this share of the chunks (see above) [P].
        min_chunks: ... and in at least this many; with fewer chunks in the recording than
            this, a cube must be occupied in every chunk (and one chunk tells nothing) [P].
        dilation: neighbourhood (in cubes) in which a static cube makes a point static [P].
    """

    def __init__(self, origin: np.ndarray | None = None, voxel_m: float = 0.5, near_range_m: float = 15.0,
                 min_fraction: float = 0.8, min_chunks: int = 4, dilation: int = 1):
        self.origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
        self.voxel_m, self.near_range_m = voxel_m, near_range_m
        self.min_fraction, self.min_chunks, self.dilation = min_fraction, min_chunks, dilation
        self.n_chunks = 0
        self._keys = np.zeros(0, dtype=np.int64)
        self._counts = np.zeros(0, dtype=np.int64)
        self._pending: list[np.ndarray] = []
        self._static: np.ndarray | None = None

    def add_chunk(self, points: np.ndarray) -> None:
        """Count the cubes occupied by one chunk's returns."""
        self._pending.append(pd.unique(self.keys(points)))
        self.n_chunks += 1
        if len(self._pending) >= 16:
            self._merge()

    def keys(self, points: np.ndarray) -> np.ndarray:
        """The cube keys of points (see :func:`range_scaled_keys`)."""
        return range_scaled_keys(points, self.origin, self.voxel_m, self.near_range_m)

    def _merge(self) -> None:
        if not self._pending:
            return
        keys = np.concatenate([self._keys, *self._pending])
        counts = np.concatenate([self._counts, *(np.ones(k.size, dtype=np.int64) for k in self._pending)])
        self._keys, inverse = np.unique(keys, return_inverse=True)
        self._counts = np.bincount(inverse, weights=counts).astype(np.int64)
        self._pending = []

    @property
    def known(self) -> bool:
        """Whether the map can tell static from moving (it needs two chunks or more)."""
        return self.n_chunks >= 2

    def needed_chunks(self) -> int:
        """Occupied chunks that make a cube static."""
        if self.n_chunks < self.min_chunks:
            return self.n_chunks
        return max(self.min_chunks, int(np.ceil(self.min_fraction * self.n_chunks)))

    def finish(self) -> None:
        """Fix the static cubes (dilated) once every chunk has been added."""
        self._merge()
        static = self._keys[self._counts >= self.needed_chunks()] if self.known else np.zeros(0, dtype=np.int64)
        offsets = neighbour_offsets(self.dilation)
        self._static = np.unique((static[:, None] + offsets[None, :]).ravel()) if static.size else static
        self.n_static_cubes = int(static.size)

    def is_static(self, points: np.ndarray) -> np.ndarray:
        """Per point: does it lie in (or next to) a static cube? Call :meth:`finish` first."""
        if self._static is None:
            raise RuntimeError("StaticMap.finish() must be called before is_static()")
        keys = self.keys(points)
        if self._static.size == 0:
            return np.zeros(keys.size, dtype=bool)
        codes, cubes = pd.factorize(keys)  # hashing; the few distinct cubes are then looked up sorted
        order = np.argsort(cubes)
        where = np.searchsorted(self._static, cubes[order])
        where[where == self._static.size] = self._static.size - 1
        found = np.empty(cubes.size, dtype=bool)
        found[order] = self._static[where] == cubes[order]
        return found[codes]
