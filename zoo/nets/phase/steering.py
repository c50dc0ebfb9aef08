"""Steering geometry of the phase nets: which correlation lag each point in space reads.

A point's steered response is the weighted mean over its terms (per microphone pair the direct-direct
path difference and, over a reflecting ground, the three where a ground-image path meets the other) of
the pair's GCC-PHAT at the term's delay. :class:`Steering` holds that physics (speed of sound, ground
plane, reflection weight, the array's no-search zone) and reads it two ways: exactly, interpolated
between lags (:meth:`Steering.response`), and on cubes, max-pooled over the lags a cube spans, as one
sparse matrix product (:meth:`Steering.grid_response`). The search region, its cube grids and the
batches' microphone geometries live here too: both :mod:`zoo.nets.phase.srp_phat` and
:mod:`zoo.nets.phase.phase_student` steer through this module.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from functools import lru_cache
from typing import NamedTuple

import torch

from datamodules.features import SPEED_OF_SOUND, PhaseRecipe, mic_pairs, pair_indices
from datamodules.simulate.microphones import mic_geometry

#: half-widths (in lags) of the max-pooled correlations the cube responses read
POOL_WIDTHS = (0, 1, 2, 4, 8, 16, 32, 64)


class SteeringTerms(NamedTuple):
    """The steered terms, one entry per term: pairs' direct terms first, then (over a ground plane) the
    image-direct, direct-image and image-image terms, each block in :func:`~datamodules.features.mic_pairs`
    order."""

    first: torch.Tensor  #: the term's first (virtual) microphone
    second: torch.Tensor  #: its second (virtual) microphone
    rows: torch.Tensor  #: the correlation row (pair) it reads
    weights: torch.Tensor  #: its weight in the response


@contextmanager
def sparse_warnings_ignored() -> Iterator[None]:
    """Silence torch's beta-support warnings for sparse tensors."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Ss]parse.*")
        yield


# ------------------------------------------------------------------------------ region, grids, geometries


def default_mics(mic_positions: str | list[list[float]], channels: int, model: str) -> torch.Tensor:
    """The geometry (channels x 3, float64) a net uses when a batch carries none: a preset name or positions.
    Raises ValueError, naming ``model``, when its count is not ``channels``."""
    mics = torch.as_tensor(mic_geometry(mic_positions), dtype=torch.float64)
    if mics.shape[0] != channels:
        raise ValueError(f"{model}: {mics.shape[0]} mic positions for in_channels {channels}")
    return mics


def search_region(region_min: Sequence[float], region_max: Sequence[float], model: str) -> torch.Tensor:
    """The region (3 x 2: per axis min and max, m, rig frame); ValueError, naming ``model``, unless each min
    lies below its max."""
    region = torch.tensor([region_min, region_max], dtype=torch.float64).T  # 3 x 2
    if region.shape != (3, 2) or bool((region[:, 0] >= region[:, 1]).any()):
        raise ValueError(f"{model} region must be 3 mins below 3 maxes, got {region_min} {region_max}")
    return region


def with_bounds(region: torch.Tensor, bounds: list[list[float]] | torch.Tensor) -> torch.Tensor:
    """``region`` with x and y replaced by the bird's-eye area [[x_min, x_max], [y_min, y_max]] (m)."""
    new = torch.as_tensor(bounds, dtype=torch.float64)
    if new.shape != (2, 2) or bool((new[:, 0] >= new[:, 1]).any()):
        raise ValueError(f"bounds must be [[x_min, x_max], [y_min, y_max]] with min < max, got {bounds}")
    return torch.cat([new, region[2:]])


def cube_grid(region: torch.Tensor, step: float) -> tuple[torch.Tensor, tuple[int, int, int]]:
    """The centres (G x 3, float32; x slowest, z fastest) of the cubes of side ``step`` filling ``region``
    (3 x 2) from its minimum corner, and the grid's shape."""
    axes = [torch.arange(float(lo) + step / 2, float(hi), step, dtype=torch.float64) for lo, hi in region]
    return torch.cartesian_prod(*axes).float(), tuple(len(axis) for axis in axes)


def geometry_groups(phase: torch.Tensor, mics_batch: torch.Tensor | None, default: torch.Tensor, model: str
                    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """A batch's distinct microphone geometries (channels x 3, float64) and the rows of each; the
    ``default`` geometry for all rows when the batch carries none. Raises ValueError, naming ``model``,
    when a geometry does not fit the phase features (B x pairs x frames x lags) or the default's count."""
    groups = [(default, torch.arange(phase.shape[0]))]
    if mics_batch is not None:
        unique, inverse = torch.unique(mics_batch.detach().cpu().double(), dim=0, return_inverse=True)
        groups = [(unique[g], torch.nonzero(inverse == g).flatten()) for g in range(unique.shape[0])]
    pairs = phase.shape[1]
    for mics, _ in groups:
        if mics.shape[0] != default.shape[0] or len(mic_pairs(mics.shape[0])) != pairs:
            raise ValueError(f"{model}: {mics.shape[0]} mic positions for phase features of {pairs} pairs")
    return groups


# ------------------------------------------------------------------------------ pooled correlations


def _pool_levels(corr: torch.Tensor) -> list[torch.Tensor]:
    """N x pairs x lags max-pooled over +-w lags for each w of POOL_WIDTHS (each N x pairs x lags).

    Each level is the maximum of the previous one at the two lags the widths' difference away (clamped to
    the ends; and at its own lag where the two spans leave a gap), so a width of 64 costs what a width of 1
    does; the values are exactly those of a max pool of width ``2 w + 1`` padded with -inf."""
    lags = corr.shape[-1]
    levels = [corr]
    for i in range(1, len(POOL_WIDTHS)):
        previous = levels[-1]
        reach = POOL_WIDTHS[i] - POOL_WIDTHS[i - 1]  # the previous level's spans at +-reach leave no gap:
        assert 0 < reach <= 2 * POOL_WIDTHS[i - 1] + 1, POOL_WIDTHS  # each width at most 3x the last plus 1
        padded = torch.cat([previous[..., :1].expand(-1, -1, reach), previous,
                            previous[..., -1:].expand(-1, -1, reach)], dim=-1)
        level = torch.maximum(padded[..., :lags], padded[..., 2 * reach:])
        levels.append(torch.maximum(level, previous) if reach > POOL_WIDTHS[i - 1] else level)  # else a gap
    return levels


def pooled_layouts(corr: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """N x pairs x lags -> the correlations max-pooled at POOL_WIDTHS, flattened (level, pair, lag) with a zero
    last, in both layouts: N x columns (:func:`pooled`, what :func:`gather` reads) and columns x N
    (:func:`pooled_columns`, what the sparse steering matrices multiply)."""
    n, pairs, lags = corr.shape
    levels = torch.stack(_pool_levels(corr), dim=1)  # N x levels x pairs x lags
    rows = torch.cat([levels.reshape(n, -1), torch.zeros(n, 1, dtype=corr.dtype)], dim=1)
    columns = torch.zeros((rows.shape[1], n), dtype=corr.dtype)
    columns[:-1].view(len(POOL_WIDTHS), pairs, lags, n).copy_(levels.permute(1, 2, 3, 0))
    return rows, columns


def pooled(corr: torch.Tensor) -> torch.Tensor:
    """N x pairs x lags -> N x (levels * pairs * lags + 1): max-pooled at POOL_WIDTHS, flattened, a zero last."""
    n = corr.shape[0]
    return torch.cat([torch.stack(_pool_levels(corr), dim=1).reshape(n, -1), torch.zeros(n, 1)], dim=1)


def pooled_columns(corr: torch.Tensor) -> torch.Tensor:
    """:func:`pooled` transposed (columns x N, contiguous): the right-hand side of a sparse steering product."""
    return pooled_layouts(corr)[1]


def gather(flat: torch.Tensor, columns: torch.Tensor, weights: torch.Tensor, wrapped: bool = False) -> torch.Tensor:
    """Weighted mean over terms of ``flat`` (N x columns, a zero column last: :func:`pooled`) at ``columns``
    (N x K x T or K x T, from :meth:`Steering.columns`; ``wrapped``: with the zero column as its index, not -1)."""
    if columns.dim() == 2:
        values = flat[:, columns]
    else:
        index = columns.reshape(flat.shape[0], -1)
        if not wrapped:  # -1: the zero column, last
            index = index.remainder(flat.shape[1])
        values = torch.gather(flat, 1, index).reshape(columns.shape)
    return (values * (weights / weights.sum())).sum(dim=-1)


# ------------------------------------------------------------------------------ steering


@lru_cache(maxsize=4)
def signed_differences(size: int, plus: torch.Tensor, minus: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """The size x D matrix whose column d is +1 at row ``plus[d]`` and -1 at row ``minus[d]``: a row vector
    times it gives the D differences ``v[plus] - v[minus]``, exactly (each sum holds two non-zero terms)."""
    columns = torch.arange(len(plus))
    matrix = torch.zeros(size, len(plus), dtype=dtype)
    matrix[plus, columns] = 1.0
    matrix[minus, columns] = -1.0
    return matrix


def _block_pairs(blocks: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Every (later, earlier) pair of term blocks, ordered by the later block: (1, 0), (2, 0), (2, 1), ..."""
    pairs = [(t, e) for t in range(1, blocks) for e in range(t)]
    return torch.tensor([t for t, _ in pairs]), torch.tensor([e for _, e in pairs])


@lru_cache(maxsize=4)
def _level_of_span(limit: int) -> torch.Tensor:
    """For each whole number of lags 0 .. ``limit``, the first POOL_WIDTHS level that wide (the last beyond)."""
    spans = torch.arange(limit + 1, dtype=torch.float64)
    return torch.bucketize(spans, torch.tensor(POOL_WIDTHS, dtype=torch.float64)).clamp(max=len(POOL_WIDTHS) - 1)


class Steering:
    """The steered response's physics for one phase recipe (see the module docstring)."""

    def __init__(self, recipe: PhaseRecipe, speed_of_sound: float = SPEED_OF_SOUND,
                 ground_height: float | None = 0.0, reflection_weight: float = 1.0, min_range: float = 4.0):
        """Args:
            recipe: the phase recipe whose correlations are steered (lags, lag rate, band).
            speed_of_sound: m/s.
            ground_height: z (m, rig frame) of the reflecting ground plane, or None for free-field steering.
            reflection_weight: weight of each of the three reflected terms against the direct one.
            min_range: points closer than this to the microphones' centre (m) read 0.
        """
        self.recipe = recipe
        self.speed_of_sound = float(speed_of_sound)
        self.ground_height = None if ground_height is None else float(ground_height)
        self.reflection_weight = float(reflection_weight)
        self.min_range = float(min_range)
        self._terms: dict[int, SteeringTerms] = {}  #: channel count -> its terms
        self._matrix_key: tuple | None = None  #: geometry, grid and step of the cached steering matrix
        self._matrix: torch.Tensor | None = None
        #: (virtual mics, terms, dtype) -> the +-1 matrix whose product with distances gives the terms' differences
        self._differences: dict[tuple[int, int, torch.dtype], torch.Tensor] = {}
        #: (terms, pairs, dtype) -> the +-1 matrix giving every later-minus-earlier block difference of lags
        self._block_differences: dict[tuple[int, int, torch.dtype], torch.Tensor] = {}

    def terms(self, channels: int) -> SteeringTerms:
        """The steered terms: per term the two (virtual) microphones, the correlation row it reads and its weight.

        Virtual microphones ``channels .. 2 * channels - 1`` are the ground images of the real ones (the
        reflected path from a source to a microphone is as long as the direct path to its image). Pair
        ``(i, j)`` reads: direct-direct ``(i, j)``, then with a ground plane image-direct ``(i', j)``,
        direct-image ``(i, j')`` and image-image ``(i', j')``, all on the pair's own correlation row.
        """
        if channels not in self._terms:  # built once per channel count: the search asks thousands of times
            first, second = pair_indices(channels)
            rows = torch.arange(len(first))
            if self.ground_height is None:
                self._terms[channels] = SteeringTerms(first, second, rows, torch.ones(len(first)))
            else:
                image = channels
                firsts = torch.cat([first, first + image, first, first + image])
                seconds = torch.cat([second, second, second + image, second + image])
                weights = torch.cat([torch.ones(len(first)), torch.full((3 * len(first),), self.reflection_weight)])
                self._terms[channels] = SteeringTerms(firsts, seconds, rows.repeat(4), weights)
        return self._terms[channels]

    def virtual_mics(self, mics: torch.Tensor) -> torch.Tensor:
        """The microphones, then (with a ground plane) their mirror images in it."""
        if self.ground_height is None:
            return mics
        mirrored = mics.clone()
        mirrored[:, 2] = 2 * self.ground_height - mics[:, 2]
        return torch.cat([mics, mirrored])

    def pair_geometry(self, points: torch.Tensor, mics: torch.Tensor, direct_only: bool = False
                      ) -> tuple[torch.Tensor, torch.Tensor]:
        """For ``points`` (... x 3): each term's fractional lag column and the norm of the gradient of
        its path difference (``|u_i - u_j|`` for unit vectors from the (virtual) mics, 0..2), ... x terms.
        ``direct_only``: the direct-direct terms (one per pair) alone."""
        first, second, virtual, flat, cross, squared, distance = self._distances(points, mics, direct_only)
        # index_select: the same values as fancy indexing of columns, several times faster
        dot = (squared - cross.index_select(1, first) - cross.index_select(1, second)
               + (virtual[first] * virtual[second]).sum(dim=1))
        cosine = dot / (distance.index_select(1, first) * distance.index_select(1, second))
        gradient = (2 - 2 * cosine).clamp_min(0).sqrt()
        shape = (*points.shape[:-1], len(first))
        return self._lag_columns(distance, first, second).reshape(shape), gradient.reshape(shape)

    def lag_positions(self, points: torch.Tensor, mics: torch.Tensor, direct_only: bool = False) -> torch.Tensor:
        """The first half of :meth:`pair_geometry` alone (each term's fractional lag column, ... x terms),
        without the gradient's work: what the exact response and the delay fit read."""
        first, second, *_, distance = self._distances(points, mics, direct_only)
        return self._lag_columns(distance, first, second).reshape(*points.shape[:-1], len(first))

    def _distances(self, points: torch.Tensor, mics: torch.Tensor, direct_only: bool) -> tuple[torch.Tensor, ...]:
        """The terms' (virtual) microphone indices, the virtual mics, the flattened points, their products
        with the mics, squared norms and distances to every (virtual) mic (M x V)."""
        first, second = self.terms(mics.shape[0])[:2]
        if direct_only:
            pairs = len(mic_pairs(mics.shape[0]))
            first, second = first[:pairs], second[:pairs]
        virtual = self.virtual_mics(mics).to(points.dtype)
        flat = points.reshape(-1, 3)
        cross = flat @ virtual.T  # M x V
        squared = (flat * flat).sum(dim=1, keepdim=True)
        mic_squared = (virtual * virtual).sum(dim=1)
        distance = (squared - 2 * cross + mic_squared).clamp_min(1e-12).sqrt()
        return first, second, virtual, flat, cross, squared, distance

    def _lag_columns(self, distance: torch.Tensor, first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
        """Fractional lag column of each term (M x terms) from the distances (M x V). ``first`` and ``second``
        are always the leading entries of :meth:`terms`, so V and their count name them."""
        key = (distance.shape[1], len(first), distance.dtype)
        if key not in self._differences:
            self._differences[key] = signed_differences(distance.shape[1], first, second, distance.dtype)
        # one product with a +-1 matrix: each entry sums one distance, minus another and exact zeros, so it
        # equals the two columns' difference to the last bit (two index_selects and a subtraction cost more)
        delay = (distance @ self._differences[key]) / self.speed_of_sound
        half = (self.recipe.num_lags() - 1) // 2
        return delay * self.recipe.lag_rate + half

    def near(self, points: torch.Tensor, mics: torch.Tensor) -> torch.Tensor:
        """Whether points (... x 3) lie within ``min_range`` of the microphones' centre (... x 1): no drone
        flies inside the array, and there the diffuse ambient's coherence (all delays near zero) peaks."""
        centre = mics.mean(dim=0).to(points.dtype)
        return (torch.linalg.vector_norm(points - centre, dim=-1) < self.min_range)[..., None]

    def distinct(self, position: torch.Tensor, channels: int) -> torch.Tensor:
        """Which terms (... x terms, as :meth:`terms` orders them) lie apart from the pair's earlier terms.

        Where a reflected term falls within ``lag_rate / f_max`` lags (the correlation peak's half-width)
        of an earlier term of the same pair, the two paths merge into one peak; counting it again would
        favour points near the ground plane, where every reflected term meets the direct one.
        """
        terms = position.shape[-1]
        pairs = len(mic_pairs(channels))
        blocks = terms // pairs
        if blocks == 1:
            return torch.ones_like(position, dtype=torch.bool)
        key = (terms, pairs, position.dtype)
        if key not in self._block_differences:
            later, earlier = _block_pairs(blocks)
            self._block_differences[key] = signed_differences(
                terms, ((later * pairs)[:, None] + torch.arange(pairs)).flatten(),
                ((earlier * pairs)[:, None] + torch.arange(pairs)).flatten(), position.dtype)
        width = self.recipe.lag_rate / self.recipe.f_max
        # every (later, earlier) block pair's difference in one product with a +-1 matrix (exact, as in
        # _lag_columns): block pairs x pairs per point
        flat = position.reshape(-1, terms)
        apart = ((flat @ self._block_differences[key]).abs_() > width).reshape(flat.shape[0], -1, pairs)
        keep = [torch.ones_like(flat[:, :pairs], dtype=torch.bool)]
        first = 0
        for t in range(1, blocks):  # block t against blocks 0 .. t-1: rows first .. first + t - 1 of apart
            kept = apart[:, first]
            for row in range(first + 1, first + t):
                kept = kept & apart[:, row]  # explicit: all() over a short middle axis is several times slower
            keep.append(kept)
            first += t
        return torch.stack(keep, dim=1).reshape(position.shape)

    def lag_scale(self, step: float | torch.Tensor) -> float | torch.Tensor:
        """Lags spanned per unit gradient of path difference by a cube of side ``step`` (half-diagonal)."""
        return step * (math.sqrt(3) / 2) / self.speed_of_sound * self.recipe.lag_rate

    def columns(self, points: torch.Tensor, mics: torch.Tensor, step: float | torch.Tensor) -> torch.Tensor:
        """Column of each cube (centres ... x 3, side ``step``) and term in the :func:`pooled` correlations
        -> ... x terms; -1 (the zero column) where the term lies outside the lags, merges with an earlier
        one, or the cube is :meth:`near` the array."""
        pairs = len(mic_pairs(mics.shape[0]))
        rows = self.terms(mics.shape[0]).rows
        lags = self.recipe.num_lags()
        position, gradient = self.pair_geometry(points, mics)
        width = gradient * self.lag_scale(step)
        # the level of each whole number of lags from a table (a binary search per term is several times slower)
        level = _level_of_span(POOL_WIDTHS[-1] + 1).take(width.ceil().clamp(max=POOL_WIDTHS[-1] + 1).long())
        index = position.round().long()
        outside = (index < 0) | (index >= lags) | ~self.distinct(position, mics.shape[0]) | self.near(points, mics)
        columns = (level * pairs + rows) * lags + index.clamp(0, lags - 1)
        return torch.where(outside, torch.full_like(columns, -1), columns)  # -1: the zero column appended

    def response(self, correlation: torch.Tensor, points: torch.Tensor, mics: torch.Tensor) -> torch.Tensor:
        """Steered response (N x K) of correlations (N x P x L) at ``points`` (N x K x 3): the weighted mean
        over terms, linearly interpolated between lags."""
        n, rows, lags = correlation.shape
        terms = self.terms(mics.shape[0])
        position = self.lag_positions(points, mics)  # N x K x T
        low = position.floor().clamp(0, lags - 2)
        frac = (position - low).clamp(0, 1)
        # each term's lag as an index into the flattened correlations (one gather, not three index tensors),
        # added in the positions' float type (whole numbers below 2^24: exact) and converted once; the next
        # lag's value read from the correlations shifted by one
        offset = ((torch.arange(n) * rows)[:, None, None] + terms.rows) * lags
        if n * rows * lags < 2 ** 24 or position.dtype == torch.float64:
            index = (low + offset.to(low.dtype)).long()
        else:
            index = low.long() + offset
        flat = correlation.reshape(-1)
        a, b = flat.take(index), flat[1:].take(index)
        inside = (position >= 0) & (position <= lags - 1) & self.distinct(position, mics.shape[0])
        values = torch.where(inside, a + frac * (b - a), torch.zeros((), dtype=a.dtype))
        response = (values * (terms.weights / terms.weights.sum()).to(values.dtype)).sum(dim=-1)
        # a point near the array reads 0: set per point, not per term (the same zero, a 24th of the work)
        return torch.where(self.near(points, mics)[..., 0], torch.zeros((), dtype=response.dtype), response)

    def grid_response(self, correlation: torch.Tensor, points: torch.Tensor, mics: torch.Tensor, step: float
                      ) -> torch.Tensor:
        """Steered response of correlations (N x pairs x lags) at the centres ``points`` (G x 3) of cubes of
        side ``step``: N x 2 x G, the multipath response (direct and ground-image terms, as the search
        scores it) and the direct terms alone. Each term reads its pair's correlation max-pooled over the
        delays its cube spans, so a peak anywhere inside a cube is seen; points within ``min_range`` of
        the array read 0. The reading is one sparse matrix product (2G x pooled columns, built once per
        grid and geometry): about 100 times faster than gathering the terms on a CPU."""
        key = (mics.numpy().tobytes(), points.numpy().tobytes(), float(step))
        if self._matrix_key != key:
            self._matrix_key, self._matrix = key, self.steering_matrix(points, mics, step)
        flat = pooled_columns(correlation.to(torch.float32))
        with sparse_warnings_ignored():
            values = (self._matrix @ flat).T  # N x 2G
        return values.reshape(-1, 2, points.shape[0])

    def steering_matrix(self, points: torch.Tensor, mics: torch.Tensor, step: float) -> torch.Tensor:
        """The sparse (CSR) matrix whose row g reads point g's multipath response from the flattened pooled
        correlations, and row G + g its direct response (a term outside the lags or merged reads nothing)."""
        columns = self.columns(points, mics, step)  # G x terms, -1: reads nothing
        pairs = len(mic_pairs(mics.shape[0]))
        weights = self.terms(mics.shape[0]).weights
        count = points.shape[0]
        direct = torch.cat([torch.ones(pairs), torch.zeros(len(weights) - pairs)]) / pairs
        rows = torch.arange(2 * count)[:, None].expand(-1, columns.shape[1])
        values = torch.stack([weights / weights.sum(), direct])[:, None, :].expand(-1, count, -1).reshape(2 * count, -1)
        used = (torch.cat([columns, columns]) >= 0) & (values > 0)
        size = (2 * count, len(POOL_WIDTHS) * pairs * self.recipe.num_lags() + 1)
        indices = torch.stack([rows[used], torch.cat([columns, columns])[used]])
        with sparse_warnings_ignored():
            return torch.sparse_coo_tensor(indices, values[used], size).coalesce().to_sparse_csr()
