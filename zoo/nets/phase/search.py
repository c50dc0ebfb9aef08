"""SRP-PHAT's coarse-to-fine search for the points of highest steered response.

:class:`CandidateSearch` runs the stages the :mod:`zoo.nets.phase.srp_phat` docstring describes, on
windows of correlations: a coarse grid of cells (split near the array) scored on max-pooled
correlations, levels of 27-cube refinement, then per frame a Gauss-Newton fit of each candidate to the
frame's pair delays and a hill climb on its exact response. It owns the search region (clamping every
step to it) and caches each geometry's coarse grid, its sparse scoring matrix and its table of refinement
cubes' columns (:mod:`zoo.nets.phase.cubes`), none of which depends on the audio.
"""

from __future__ import annotations

import numpy as np
import torch

from datamodules.features import mic_pairs, pair_indices
from zoo.nets.phase.cubes import CHILDREN, CubeColumns, child_ids
from zoo.nets.phase.steering import (
    POOL_WIDTHS,
    Steering,
    cube_grid,
    gather,
    pooled_layouts,
    sparse_warnings_ignored,
)

#: coarse cells are split until they span at most this many lags (half-range) for every pair
MAX_COARSE_WIDTH = 32.0
#: levels refined on a window's mean correlation before its rays are scanned over range
WINDOW_LEVELS = 2
#: the delay fit: lags searched around a candidate's delays, Gauss-Newton steps at most, damping, largest step (m)
FIT_SEARCH, FIT_STEPS, FIT_DAMPING, FIT_MAX_STEP = 8, 30, 1e-4, 5.0
#: the delay fit stops once no point moves farther than this in a step (m: 1/60 of the finest grid step)
FIT_TOLERANCE = 1e-3
#: the 27 cubes around a point (x slowest, z fastest; the centre included), in steps
OFFSETS = torch.cartesian_prod(*[torch.tensor([-1.0, 0.0, 1.0])] * 3)


#: the symmetric 3 x 3 matrix's cofactors c00 c01 c02 c11 c12 c22 as f0 * f1 - f2 * f3 of its entries, indexed
#: in the flattened 3 x 4 block [A | b] (a00 0, a01 1, a02 2, a11 5, a12 6, a22 10)
COFACTORS = np.array([[5, 2, 1, 0, 1, 0], [10, 6, 6, 10, 2, 5], [6, 1, 2, 2, 0, 1], [6, 10, 5, 2, 6, 1]])
#: the cofactor matrix (3 x 3) from the six distinct cofactors
COFACTOR_MATRIX = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])


def solve_normal(normal: np.ndarray) -> np.ndarray:
    """Damped Gauss-Newton steps (3 x M, float32) from normal equations (3 x 4 x M: J'WJ beside J'Wr).

    The diagonal is raised by ``FIT_DAMPING / 3`` of the trace (in place), then ``-(J'WJ)^-1 J'Wr`` is
    taken by the cofactors (Cramer's rule) in float64: a handful of whole-row operations instead of a
    batched LU solve, the same values to float rounding.
    """
    count = normal.shape[-1]
    diagonal = normal.reshape(12, count)[0:11:5]  # a00 a11 a22 (a view)
    diagonal += np.add.reduce(diagonal, axis=0) * np.float32(FIT_DAMPING / 3)
    entries = normal.reshape(12, count).astype(np.float64)
    factors = entries[COFACTORS]  # 4 x 6 x M
    cofactors = factors[0] * factors[1] - factors[2] * factors[3]
    determinant = np.add.reduce(entries[:3] * cofactors[:3], axis=0)
    step = np.add.reduce(cofactors[COFACTOR_MATRIX] * entries[3:12:4], axis=1) / -determinant
    return step.astype(np.float32)


def best_candidates(points: torch.Tensor, values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per frame, the candidate (B x F x 3) of highest ``values`` (B x F x K) among ``points``
    (B x F x K x 3), and that value (B x F)."""
    top = values.argmax(dim=-1, keepdim=True)  # B x F x 1
    best = torch.gather(points, 2, top[..., None].expand(-1, -1, 1, 3))[:, :, 0]
    return best, torch.gather(values, 2, top)[..., 0]


class CandidateSearch:
    """Coarse grid, refinement, delay fit and exact hill climb over a region (see the module docstring)."""

    def __init__(self, steering: Steering, region: torch.Tensor, coarse_step: float = 1.0, fine_step: float = 0.0625,
                 candidates: int = 32, frame_candidates: int = 4, search_groups: int = 1, refine_levels: int = 1,
                 fit_delays: bool = True, fit_steps: int = FIT_STEPS):
        """Args:
            steering: the geometry the responses are read with.
            region: the searched region (3 x 2, m, rig frame); :meth:`set_region` changes it.
            coarse_step, fine_step, candidates, frame_candidates, search_groups, refine_levels, fit_delays, fit_steps:
                as in :class:`zoo.nets.phase.srp_phat.SRPPhat`.
        """
        self.steering = steering
        self.coarse_step, self.fine_step = float(coarse_step), float(fine_step)
        self.frame_candidates, self.search_groups = int(frame_candidates), int(search_groups)
        if self.search_groups < 1:
            raise ValueError(f"srp_phat: search_groups must be >= 1, got {search_groups}")
        self.candidates = int(candidates)
        self.refine_levels = int(refine_levels)
        self.uses_delay_fit = bool(fit_delays)
        self.fit_steps = int(fit_steps)
        if self.fit_steps < 1:
            raise ValueError(f"srp_phat: fit_steps must be >= 1, got {fit_steps}")
        self._coarse: dict[bytes, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}
        self._coarse_matrices: dict[bytes, torch.Tensor] = {}
        self._cubes: dict[bytes, CubeColumns] = {}  #: per geometry, the refinement cubes' columns
        self.set_region(region)

    def set_region(self, region: torch.Tensor) -> None:
        """Search ``region`` (3 x 2) from now on; the coarse grids are rebuilt."""
        self.region = region
        self._low, self._high = region[:, 0].float(), region[:, 1].float()
        self._coarse.clear()
        self._coarse_matrices.clear()
        self._cubes.clear()

    def clamp(self, points: torch.Tensor) -> torch.Tensor:
        """Points (... x 3) moved to the nearest point of the region."""
        return torch.maximum(torch.minimum(points, self._high), self._low)

    def cubes(self, mics: torch.Tensor) -> CubeColumns:
        """The geometry's table of refinement cubes' columns (:class:`~zoo.nets.phase.cubes.CubeColumns`)."""
        key = mics.numpy().tobytes()
        if key not in self._cubes:
            self._cubes[key] = CubeColumns(self.steering, mics)
        return self._cubes[key]

    def prepare(self, mics: torch.Tensor) -> None:
        """Build everything of the geometry that does not depend on the audio now (otherwise the first window
        does): the coarse grid, its scoring matrix and the columns of every coarse cell's refinement cubes."""
        grid, sides, _ = self.coarse_grid(mics)
        self.coarse_matrix(mics)
        table = self.cubes(mics)
        if not table.filled(0):
            steps = sides / 2  # as :meth:`refine` halves them, so the cubes are the same to the bit
            children = self.clamp(grid[:, None, :] + OFFSETS * steps[:, None, None])
            table.fill(0, children, steps[:, None].expand(-1, CHILDREN))

    def coarse_grid(self, mics: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The coarse cells (centres G x 3 and sides G) and their columns in the flattened pooled
        correlations (G x pairs), computed once per geometry.

        Cells of ``coarse_step`` are split into eight until the delays each spans stay within
        ``MAX_COARSE_WIDTH`` lags (cells near the array span many more than far ones), so every cell's
        pooled score bounds its contents about equally tightly and a far peak is not crowded out of
        the candidates by loose near cells.
        """
        key = mics.numpy().tobytes()
        if key not in self._coarse:
            centres, sides = cube_grid(self.region, self.coarse_step)[0], []
            step, done = self.coarse_step, []
            offsets = torch.cartesian_prod(*[torch.tensor([-0.25, 0.25])] * 3)
            while centres.numel():
                width = self.steering.pair_geometry(centres, mics)[1].amax(dim=1) * self.steering.lag_scale(step)
                keep = (width <= MAX_COARSE_WIDTH) | (step / 2 < self.fine_step)
                done.append(centres[keep])
                sides.append(torch.full((int(keep.sum()),), step))
                centres = (centres[~keep][:, None, :] + offsets * step).reshape(-1, 3)
                step /= 2
            grid, side = torch.cat(done), torch.cat(sides)
            self._coarse[key] = (grid, side, self.steering.columns(grid, mics, side[:, None]))
        return self._coarse[key]

    def coarse_matrix(self, mics: torch.Tensor) -> torch.Tensor:
        """The sparse (CSR) matrix whose row g reads coarse cell g's pooled multipath response from the
        flattened pooled correlations (what :func:`~zoo.nets.phase.steering.gather` computes at the cells'
        columns), built once per geometry: one sparse product scores every cell far faster than gathering."""
        key = mics.numpy().tobytes()
        if key not in self._coarse_matrices:
            grid, _, columns = self.coarse_grid(mics)
            weights = self.steering.terms(mics.shape[0]).weights
            values = (weights / weights.sum())[None, :].expand_as(columns)
            rows = torch.arange(grid.shape[0])[:, None].expand_as(columns)
            used = columns >= 0  # -1 reads the zero column: nothing
            pairs = len(mic_pairs(mics.shape[0]))
            size = (grid.shape[0], len(POOL_WIDTHS) * pairs * self.steering.recipe.num_lags() + 1)
            with sparse_warnings_ignored():
                matrix = torch.sparse_coo_tensor(torch.stack([rows[used], columns[used]]), values[used].float(), size)
                matrix = matrix.coalesce().to_sparse_csr()
                # 32-bit indices: the sparse product otherwise converts them at every call
                self._coarse_matrices[key] = torch.sparse_csr_tensor(
                    matrix.crow_indices().int(), matrix.col_indices().int(), matrix.values(), size)
        return self._coarse_matrices[key]

    def refine(self, flat: torch.Tensor, points: torch.Tensor, steps: torch.Tensor, mics: torch.Tensor, keep: int,
               names: torch.Tensor | None = None, level: int = 0
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """One level: the 27 cubes of half the step around each point (N x k x 3), scored on the pooled
        correlations ``flat`` (N x columns); the ``keep`` best (points, steps, scores, names). With the
        points' ``names`` (N x k, :func:`~zoo.nets.phase.cubes.child_ids`) and their refinement ``level``,
        the cubes' columns come from the geometry's :meth:`cubes` table."""
        n, k = points.shape[:2]
        steps = steps / 2
        children = self.clamp(points[:, :, None, :] + OFFSETS * steps[..., None, None])  # N x k x 27 x 3
        child_steps = steps[:, :, None].expand(-1, -1, CHILDREN)
        if names is None:
            columns = self.steering.columns(children.reshape(n, -1, 3), mics, child_steps.reshape(n, -1, 1))
            columns = columns.remainder_(flat.shape[1])  # -1 (reads nothing): the zero column's index
        else:
            columns = self.cubes(mics).children(level, names.reshape(-1), children.reshape(n * k, CHILDREN, 3),
                                                child_steps.reshape(n * k, CHILDREN))
        weights = self.steering.terms(mics.shape[0]).weights
        scores = gather(flat, columns.reshape(n, k * CHILDREN, -1), weights, wrapped=True)
        best = scores.topk(min(keep, k * CHILDREN), dim=1)
        chosen = (torch.gather(children.reshape(n, -1, 3), 1, best.indices[..., None].expand(-1, -1, 3)),
                  torch.gather(child_steps.reshape(n, -1), 1, best.indices), best.values)
        if names is None:
            return *chosen, None
        parents = torch.gather(names, 1, best.indices // CHILDREN)
        return *chosen, child_ids(parents, best.indices % CHILDREN)

    def refine_exact(self, frames: torch.Tensor, points: torch.Tensor, mics: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
        """Hill-climb each point (N x K x 3) on a frame's exact response: at every level the best of the 27
        points one step around it, the step halving from ``2 ** (refine_levels - 1) * fine_step`` down to
        ``fine_step``. Returns the points and their responses (N x K)."""
        n, k = points.shape[:2]
        if self.refine_levels < 1:
            return points, self.steering.response(frames, points, mics)
        for level in reversed(range(self.refine_levels)):
            step = self.fine_step * 2 ** level
            children = self.clamp(points[:, :, None, :] + OFFSETS * step)  # N x K x 27 x 3
            scores = self.steering.response(frames, children.reshape(n, -1, 3), mics).reshape(n, k, -1)
            best = scores.argmax(dim=-1, keepdim=True)
            points = torch.gather(children, 2, best[..., None].expand(-1, -1, 1, 3))[:, :, 0]
        return points, torch.gather(scores, 2, best)[..., 0]  # the last level's: no second reading

    def fit_delays(self, frames: torch.Tensor, points: torch.Tensor, mics: torch.Tensor) -> torch.Tensor:
        """Move each candidate (N x K x 3) to the point whose pair delays best match the frame's.

        For every pair, the correlation peak within ``FIT_SEARCH`` lags of the candidate's delay is
        located to a fraction of a lag (parabola through the peak and its neighbours); a few damped
        Gauss-Newton steps then fit the point to those delays, weighted by the peaks' heights. The
        delays pin the direction, and their small differences (the wavefront's curvature) the range,
        which a grid search cannot resolve without a grid finer than its cost allows.
        """
        n, k = points.shape[:2]
        pairs, lags = frames.shape[1:]
        position = self.steering.lag_positions(points, mics, direct_only=True)  # N x K x P
        window = torch.arange(-FIT_SEARCH, FIT_SEARCH + 1)
        index = (position.round().long()[..., None] + window).clamp(1, lags - 2)  # N x K x P x W
        # every lag as an index into the flattened correlations (one gather, not three index tensors)
        base = ((torch.arange(n) * pairs)[:, None, None] + torch.arange(pairs)) * lags  # N x 1 x P
        flat = frames.reshape(-1)
        peak = flat.take(index + base[..., None]).argmax(dim=-1, keepdim=True)
        centre = torch.gather(index, -1, peak)[..., 0] + base
        y0, y1, y2 = (flat.take(centre + d) for d in (-1, 0, 1))
        curvature = y0 - 2 * y1 + y2
        shift = torch.where(curvature < 0, 0.5 * (y0 - y2) / curvature.clamp(max=-1e-9), torch.zeros_like(y1))
        measured = (centre - base).to(frames.dtype) + shift.clamp(-0.5, 0.5)
        weight = y1.clamp_min(0.0) + 1e-3
        return torch.from_numpy(self._gauss_newton(points.numpy(), measured.numpy(), weight.numpy(), mics))

    def _gauss_newton(self, points: np.ndarray, measured: np.ndarray, weight: np.ndarray, mics: torch.Tensor
                      ) -> np.ndarray:
        """The damped Gauss-Newton steps of :meth:`fit_delays`: points (N x K x 3) fitted to the measured
        direct lag columns (N x K x pairs) with weights (N x K x pairs), float32.

        In numpy, each quantity a row over the candidates (coordinate-major, so every operation runs on
        contiguous rows) and the normal equations solved in closed form (:func:`solve_normal`): at these few
        hundred numbers per step the operations' overhead, not their arithmetic, is the cost.
        """
        shape = points.shape
        first, second = (index.numpy() for index in pair_indices(mics.shape[0]))
        m = mics.numpy().astype(np.float32)[:, :, None]  # C x 3 x 1
        channels, pairs = m.shape[0], len(first)
        scale = np.float32(self.steering.recipe.lag_rate / self.steering.speed_of_sound)
        half = np.float32((self.steering.recipe.num_lags() - 1) // 2)
        low, high = self._low.numpy()[:, None], self._high.numpy()[:, None]
        largest = np.float32(FIT_MAX_STEP)
        difference = np.zeros((pairs, channels), dtype=np.float32)  # pair lag column = difference @ distances
        difference[np.arange(pairs), first], difference[np.arange(pairs), second] = scale, -scale
        points = np.ascontiguousarray(points.reshape(-1, 3).T)  # 3 x M
        count = points.shape[1]
        target = np.ascontiguousarray(measured.reshape(count, pairs).T) - half  # P x M
        weight = np.ascontiguousarray(weight.reshape(count, pairs).T)[:, None]  # P x 1 x M
        unit_range = np.empty((channels, 4, count), dtype=np.float32)  # per mic: unit vector to the point, distance
        direction, distance = unit_range[:, :3], unit_range[:, 3]
        for _ in range(self.fit_steps):
            np.subtract(points, m, out=direction)
            np.sqrt(np.add.reduce(np.square(direction), axis=1), out=distance)
            np.maximum(distance, np.float32(1e-6), out=distance)
            direction /= distance[:, None]
            # per pair: the Jacobian of its lag column (rows 0-2) and its residual (row 3)
            jacobian = (difference @ unit_range.reshape(channels, -1)).reshape(pairs, 4, count)
            jacobian[:, 3] -= target
            weighted = jacobian[:, :3] * weight
            normal = np.add.reduce(weighted[:, :, None] * jacobian[:, None], axis=0)  # 3 x 4 x M: J'WJ | J'Wr
            step = solve_normal(normal)
            np.minimum(np.maximum(step, -largest, out=step), largest, out=step)
            step += points
            # np.minimum / np.maximum: np.clip's same values behind several layers of Python
            moved = np.minimum(np.maximum(step, low, out=step), high, out=step)
            converged = float(np.maximum.reduce(np.abs(moved - points), axis=None)) < FIT_TOLERANCE
            points = moved
            if converged:
                break
        return np.ascontiguousarray(points.T).reshape(shape)

    def fitted_candidates(self, correlation: torch.Tensor, mics: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Every frame's ``frame_candidates`` fitted points (B x F x K x 3) and their exact responses
        (B x F x K), for windows of correlations B x F x pairs x lags.

        The grid levels search each window (or each of its ``search_groups`` groups of frames) on its
        frames' mean correlation (non-coherent, so the slow drift of the delays does not cancel it);
        then each frame fits its window's (group's) best candidates to its own pair delays and refines them
        on its exact response.
        """
        b, f, p, lags = correlation.shape
        corr = correlation.to(torch.float32).contiguous()
        groups = torch.tensor_split(torch.arange(f), min(self.search_groups, f))
        mean = torch.stack([corr[:, int(rows[0]):int(rows[-1]) + 1].mean(dim=1) for rows in groups], dim=1)
        self.prepare(mics)
        grid, sides, _ = self.coarse_grid(mics)
        k = min(self.candidates, grid.shape[0])
        flat, flat_columns = pooled_layouts(mean.reshape(-1, p, lags))
        with sparse_warnings_ignored():
            scores = self.coarse_matrix(mics) @ flat_columns  # G x B: every cell's pooled response at once
        best = scores.topk(k, dim=0)  # G x B -> k x B
        names = best.indices.T  # B x k: the coarse cells, by index (the names of their cubes' parents)
        points, steps = grid[names], sides[names]
        for level in range(WINDOW_LEVELS):
            points, steps, _, names = self.refine(flat, points, steps, mics, k, names, level)
        points = points[:, : self.frame_candidates].reshape(b, len(groups), -1, 3)
        # per frame: fit its group's candidates to the pair delays measured near their own, then refine
        # them on the exact (multipath) response
        frames = corr.reshape(b * f, p, lags)
        group_of_frame = torch.cat([torch.full((len(rows),), g) for g, rows in enumerate(groups)])
        points = points[:, group_of_frame].reshape(b * f, -1, 3)
        if self.uses_delay_fit:
            points = self.fit_delays(frames, points, mics)
        points, scores = self.refine_exact(frames, points, mics)
        return points.reshape(b, f, -1, 3), scores.reshape(b, f, -1)

    def peaks(self, correlation: torch.Tensor, mics: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Peak point (B x F x 3) and response (B x F) of every frame of every window (B x F x pairs x lags):
        the best of its :meth:`fitted_candidates`."""
        return best_candidates(*self.fitted_candidates(correlation, mics))
