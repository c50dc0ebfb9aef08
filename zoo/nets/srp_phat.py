"""SRP-PHAT: steered-response-power localisation from the phase recipe, no training.

For every short frame of a window, the steered response of a point ``g`` is the mean over
microphone pairs of their GCC-PHAT at the pair's delay ``(|g - m_i| - |g - m_j|) / c`` and, over a
reflecting ground (the roof, z = 0 in the rig frame), at the three delays where the ground image of
either path meets the other (image-direct, direct-image, image-image; terms that merge into one
peak count once). Over a hard ground each pair's correlation holds all four peaks at similar
heights, so a free-field search often locks onto a cross term and misplaces the range; steering
the image terms makes them confirm the true point instead. Points within ``min_range`` of the
array are not searched (the diffuse ambient's coherence peaks there). The
point of highest response is found coarse to fine: a grid over the flight region, where each cell
scores the largest correlation over the range of delays its volume spans (cells are split near the
array, where they span more), then cubes of half the step around the best cells, all on the
window's mean correlation (or on each of ``search_groups`` consecutive groups of its frames, whose
candidates serve that group's frames: a near drone's delays move too far in 2 s for one mean); then,
per frame, each of the best candidates is fitted to the delays of
that frame's correlation peaks near its own (Gauss-Newton), which resolves range from the
wavefront's curvature where a grid step could not, then hill-climbed on the frame's exact
response (linear interpolation between lags).

A frame counts as a detection when its peak response exceeds a threshold set from a null statistic:
the same search on independent white noise per microphone (nothing coherent, like channels shifted
apart by seconds): the quantile ``1 - false_alarm`` of the best frame of each null window, so
``false_alarm`` is a share of windows at any frame count; no ground truth is involved. A window's
position is the coordinate-wise median of its detected frames. With ``confirm_seconds``, a detected
window counts only when the sequence's previous detection is that recent and near (two detections
confirm a track), so an isolated false detection is neither output nor held. When no
frame of a window is detected, the last detected position of the same sequence is held for
``hold_seconds``, then the mean of the sequence's detections so far (``fallback: mean``) or the
search region's centre (``fallback: centre``) is returned (the centre before the first detection).
That memory follows the batches' ``sequence`` and ``time`` entries (windows in time order, as the
test and predict loaders give them); without them every window stands alone.

Outputs: ``position`` (B x 3), ``detection_score`` (B: the window's highest frame response over the
threshold; above 1 means detected) and ``detected`` (B, bool). ``fit`` trains nothing: the net has
no trainable parameters, so ``aaute fit`` returns at once and ``aaute test`` evaluates it directly.
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import numpy as np
import torch
import torch.nn.functional as F

from datamodules.features import GccPhat, mic_pairs, pair_indices, phase_recipe, split_frames
from datamodules.simulate.microphones import mic_geometry
from zoo.nets.base import TrajectoryNet
from zoo.registry import register_model

log = logging.getLogger(__name__)

#: the simulator's speed of sound: 331.3 * sqrt(1 + 30 / 273.15) m/s at 30 C (MMAUD V1, Singapore)
SPEED_OF_SOUND = 349.0
#: half-widths (in lags) of the max-pooled correlations the coarse levels read
POOL_WIDTHS = (0, 1, 2, 4, 8, 16, 32, 64)
#: coarse cells are split until they span at most this many lags (half-range) for every pair
MAX_COARSE_WIDTH = 32.0
#: levels refined on a window's mean correlation before its rays are scanned over range
WINDOW_LEVELS = 2
#: the delay fit: lags searched around a candidate's delays, Gauss-Newton steps, damping, largest step (m)
FIT_SEARCH, FIT_STEPS, FIT_DAMPING, FIT_MAX_STEP = 8, 30, 1e-4, 5.0
#: what an undetected window returns once the hold has expired
FALLBACKS = ("mean", "centre")


@contextmanager
def _sparse_warnings_ignored() -> Iterator[None]:
    """Silence torch's beta-support warnings for sparse tensors."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Ss]parse.*")
        yield


@register_model("srp_phat")
class SRPPhat(TrajectoryNet):
    """Steered response power with PHAT weighting over a 3D grid (see the module docstring)."""

    inputs = {"audio_phase": "gcc_phat"}
    category = "non-learned"
    trains_position = False
    context_keys = ("mic_positions", "time", "sequence")

    def __init__(
        self,
        in_channels: int = 4,
        mic_positions: str | list[list[float]] = "distributed4",
        speed_of_sound: float = SPEED_OF_SOUND,
        region_min: Sequence[float] = (-2.0, -5.0, 0.5),
        region_max: Sequence[float] = (8.0, 25.0, 25.0),
        coarse_step: float = 1.0,
        fine_step: float = 0.0625,
        candidates: int = 32,
        frame_candidates: int = 4,
        search_groups: int = 1,
        false_alarm: float = 0.01,
        null_windows: int = 300,
        hold_seconds: float = 10.0,
        confirm_seconds: float = 0.0,
        confirm_distance: float = 5.0,
        ground_height: float | None = 0.0,
        reflection_weight: float = 1.0,
        refine_levels: int = 1,
        fit_delays: bool = True,
        min_range: float = 4.0,
        fallback: str = "mean",
        input_recipes: dict[str, str] | None = None,
    ):
        """Args:
            mic_positions: the geometry used when a batch carries none (a preset name or channels x 3, m).
            speed_of_sound: m/s (349: the simulator's 30 C air).
            region_min, region_max: the search region (m, rig frame); x and y follow the data's
                ``bev_bounds`` when the task sets them. The default is the MMAUD flight region.
            coarse_step: the grid's cell side (m) far from the array; cells are halved near it, down to
                ``fine_step``.
            candidates: best cells kept at each level of a window's search.
            frame_candidates: best cells kept per frame before the exact last level.
            search_groups: the grid levels search this many consecutive groups of a window's frames
                (each on its frames' mean correlation) and each frame fits its own group's candidates;
                1: the whole window's mean.
            false_alarm: share of null windows allowed over each detection threshold.
            null_windows: windows of white noise that set the thresholds.
            hold_seconds: how long a sequence keeps its last detection before falling back to its mean.
            confirm_seconds, confirm_distance: a detection counts only when the sequence's previous one
                lies within ``confirm_seconds`` before it and ``confirm_distance`` (m) of it (a track is
                confirmed by two detections, as radar trackers confirm tracks), so an isolated false
                detection is neither output nor held; 0 s: every detection counts.
            ground_height: z (m, rig frame) of the reflecting ground plane (the roof surface is z = 0 in
                the rig frame), or None for free-field steering. Each pair's correlation then holds, besides
                the direct-direct peak, peaks where the ground image of one or both paths meets the other:
                steering all four lets the reflection confirm the direct peak instead of competing with it.
            reflection_weight: weight of each of the three reflected terms against the direct one (1: a
                hard ground such as concrete, reflection factor about 0.95).
            refine_levels: per frame, levels of 27-point refinement (from ``2 ** (levels - 1) * fine_step``
                down to ``fine_step``) on the exact multipath response after the delay fit.
            fit_delays: fit each frame's candidates to its direct pair delays (Gauss-Newton) first.
            fallback: after the hold, ``mean`` (of the sequence's detections so far) or ``centre`` (of
                the search region: the flight region's prior, unbiased by false or near detections).
            min_range: points closer than this to the microphones' centre (m) score 0: the drone keeps
                clear of the rig, and the diffuse ambient's coherence makes false peaks inside the array.
        """
        super().__init__(in_channels, input_recipes=input_recipes)
        self.recipe = phase_recipe(self.inputs["audio_phase"])
        self.default_mics = torch.as_tensor(mic_geometry(mic_positions), dtype=torch.float64)
        if self.default_mics.shape[0] != in_channels:
            raise ValueError(f"srp_phat: {self.default_mics.shape[0]} mic positions for in_channels {in_channels}")
        self.speed_of_sound = float(speed_of_sound)
        self.region = torch.tensor([region_min, region_max], dtype=torch.float64).T  # 3 x 2
        if self.region.shape != (3, 2) or bool((self.region[:, 0] >= self.region[:, 1]).any()):
            raise ValueError(f"srp_phat region must be 3 mins below 3 maxes, got {region_min} {region_max}")
        self.coarse_step, self.fine_step = float(coarse_step), float(fine_step)
        self.frame_candidates, self.search_groups = int(frame_candidates), int(search_groups)
        if self.search_groups < 1:
            raise ValueError(f"srp_phat: search_groups must be >= 1, got {search_groups}")
        self.candidates, self.false_alarm, self.null_windows = int(candidates), float(false_alarm), int(null_windows)
        self.hold_seconds = float(hold_seconds)
        self.confirm_seconds, self.confirm_distance = float(confirm_seconds), float(confirm_distance)
        self.ground_height = None if ground_height is None else float(ground_height)
        self.reflection_weight = float(reflection_weight)
        self.refine_levels = int(refine_levels)
        self.fit_delays = bool(fit_delays)
        self.min_range = float(min_range)
        if fallback not in FALLBACKS:
            raise ValueError(f"srp_phat fallback must be one of {FALLBACKS}, got {fallback!r}")
        self.fallback = fallback
        self._thresholds: dict[bytes, float] = {}
        self._coarse: dict[bytes, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}
        self._tracks: dict[int, dict] = {}  #: sequence index -> hold/fallback memory
        self._steering_key: tuple | None = None  #: geometry, grid and step of the cached steering matrix
        self._steering: torch.Tensor | None = None

    # ------------------------------------------------------------------------------ configuration

    def set_bounds(self, bounds: list[list[float]] | torch.Tensor) -> None:
        """Search x and y inside the data's bird's-eye area [[x_min, x_max], [y_min, y_max]] (m)."""
        new = torch.as_tensor(bounds, dtype=torch.float64)
        if new.shape != (2, 2) or bool((new[:, 0] >= new[:, 1]).any()):
            raise ValueError(f"bounds must be [[x_min, x_max], [y_min, y_max]] with min < max, got {bounds}")
        self.region = torch.cat([new, self.region[2:]])
        self._coarse.clear()
        self._thresholds.clear()

    def _check_region(self, mics: torch.Tensor) -> None:
        centre = mics.mean(dim=0)
        outside = (centre < self.region[:, 0] - 5.0) | (centre > self.region[:, 1] + 5.0)
        if bool(outside.any()):
            log.warning("srp_phat: the search region %s lies more than 5 m from the microphones' centre %s; "
                        "check region_min/region_max and the data's bev_bounds",
                        self.region.tolist(), [round(v, 2) for v in centre.tolist()])

    # ------------------------------------------------------------------------------ search

    def _terms(self, channels: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The steered terms: per term the two (virtual) microphones, the correlation row it reads and its weight.

        Virtual microphones ``channels .. 2 * channels - 1`` are the ground images of the real ones (the
        reflected path from a source to a microphone is as long as the direct path to its image). Pair
        ``(i, j)`` reads: direct-direct ``(i, j)``, then with a ground plane image-direct ``(i', j)``,
        direct-image ``(i, j')`` and image-image ``(i', j')``, all on the pair's own correlation row.
        """
        first, second = pair_indices(channels)
        rows = torch.arange(len(first))
        if self.ground_height is None:
            return first, second, rows, torch.ones(len(first))
        image = channels
        firsts = torch.cat([first, first + image, first, first + image])
        seconds = torch.cat([second, second, second + image, second + image])
        weights = torch.cat([torch.ones(len(first)), torch.full((3 * len(first),), self.reflection_weight)])
        return firsts, seconds, rows.repeat(4), weights

    def _virtual_mics(self, mics: torch.Tensor) -> torch.Tensor:
        """The microphones, then (with a ground plane) their mirror images in it."""
        if self.ground_height is None:
            return mics
        mirrored = mics.clone()
        mirrored[:, 2] = 2 * self.ground_height - mics[:, 2]
        return torch.cat([mics, mirrored])

    def _pair_geometry(self, points: torch.Tensor, mics: torch.Tensor, direct_only: bool = False
                       ) -> tuple[torch.Tensor, torch.Tensor]:
        """For ``points`` (... x 3): each term's fractional lag column and the norm of the gradient of
        its path difference (``|u_i - u_j|`` for unit vectors from the (virtual) mics, 0..2), ... x terms.
        ``direct_only``: the direct-direct terms (one per pair) alone."""
        first, second = self._terms(mics.shape[0])[:2]
        if direct_only:
            pairs = len(mic_pairs(mics.shape[0]))
            first, second = first[:pairs], second[:pairs]
        virtual = self._virtual_mics(mics).to(points.dtype)
        flat = points.reshape(-1, 3)
        cross = flat @ virtual.T  # M x V
        squared = (flat * flat).sum(dim=1, keepdim=True)
        mic_squared = (virtual * virtual).sum(dim=1)
        distance = (squared - 2 * cross + mic_squared).clamp_min(1e-12).sqrt()
        delay = (distance[:, first] - distance[:, second]) / self.speed_of_sound
        half = (self.recipe.num_lags() - 1) // 2
        position = delay * self.recipe.lag_rate + half
        dot = squared - cross[:, first] - cross[:, second] + (virtual[first] * virtual[second]).sum(dim=1)
        cosine = dot / (distance[:, first] * distance[:, second])
        gradient = (2 - 2 * cosine).clamp_min(0).sqrt()
        shape = (*points.shape[:-1], len(first))
        return position.reshape(shape), gradient.reshape(shape)

    def _near(self, points: torch.Tensor, mics: torch.Tensor) -> torch.Tensor:
        """Whether points (... x 3) lie within ``min_range`` of the microphones' centre (... x 1): no drone
        flies inside the array, and there the diffuse ambient's coherence (all delays near zero) peaks."""
        centre = mics.mean(dim=0).to(points.dtype)
        return (torch.linalg.vector_norm(points - centre, dim=-1) < self.min_range)[..., None]

    def _distinct(self, position: torch.Tensor, channels: int) -> torch.Tensor:
        """Which terms (... x terms, as :meth:`_terms` orders them) lie apart from the pair's earlier terms.

        Where a reflected term falls within ``lag_rate / f_max`` lags (the correlation peak's half-width)
        of an earlier term of the same pair, the two paths merge into one peak; counting it again would
        favour points near the ground plane, where every reflected term meets the direct one.
        """
        terms = position.shape[-1]
        pairs = len(mic_pairs(channels))
        if terms == pairs:
            return torch.ones_like(position, dtype=torch.bool)
        grouped = position.reshape(*position.shape[:-1], terms // pairs, pairs)
        width = self.recipe.lag_rate / self.recipe.f_max
        keep = [torch.ones_like(grouped[..., 0, :], dtype=torch.bool)]
        for t in range(1, grouped.shape[-2]):
            apart = ((grouped[..., t:t + 1, :] - grouped[..., :t, :]).abs() > width).all(dim=-2)
            keep.append(apart)
        return torch.stack(keep, dim=-2).reshape(position.shape)

    def _coarse_grid(self, mics: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The coarse cells (centres G x 3 and sides G) and their columns in the flattened pooled
        correlations (G x pairs), computed once per geometry.

        Cells of ``coarse_step`` are split into eight until the delays each spans stay within
        ``MAX_COARSE_WIDTH`` lags (cells near the array span many more than far ones), so every cell's
        pooled score bounds its contents about equally tightly and a far peak is not crowded out of
        the candidates by loose near cells.
        """
        key = mics.numpy().tobytes()
        if key not in self._coarse:
            axes = [torch.arange(float(lo) + self.coarse_step / 2, float(hi), self.coarse_step, dtype=torch.float64)
                    for lo, hi in self.region]
            centres, sides = torch.cartesian_prod(*axes).float(), []
            step, done = self.coarse_step, []
            offsets = torch.cartesian_prod(*[torch.tensor([-0.25, 0.25])] * 3)
            while centres.numel():
                width = self._pair_geometry(centres, mics)[1].amax(dim=1) * self._lag_scale(step)
                keep = (width <= MAX_COARSE_WIDTH) | (step / 2 < self.fine_step)
                done.append(centres[keep])
                sides.append(torch.full((int(keep.sum()),), step))
                centres = (centres[~keep][:, None, :] + offsets * step).reshape(-1, 3)
                step /= 2
            grid, side = torch.cat(done), torch.cat(sides)
            self._coarse[key] = (grid, side, self._columns(grid, mics, side[:, None]))
        return self._coarse[key]

    def _lag_scale(self, step: float | torch.Tensor) -> float | torch.Tensor:
        """Lags spanned per unit gradient of path difference by a cube of side ``step`` (half-diagonal)."""
        return step * (math.sqrt(3) / 2) / self.speed_of_sound * self.recipe.lag_rate

    def _columns(self, points: torch.Tensor, mics: torch.Tensor, step: float | torch.Tensor) -> torch.Tensor:
        """Column of each point (... x 3) and term in the flattened pooled correlations -> ... x terms."""
        pairs = len(mic_pairs(mics.shape[0]))
        rows = self._terms(mics.shape[0])[2]
        lags = self.recipe.num_lags()
        position, gradient = self._pair_geometry(points, mics)
        width = gradient * self._lag_scale(step)
        level = torch.bucketize(width.ceil(), torch.tensor(POOL_WIDTHS, dtype=width.dtype))
        level = level.clamp(max=len(POOL_WIDTHS) - 1)
        index = position.round().long()
        outside = (index < 0) | (index >= lags) | ~self._distinct(position, mics.shape[0]) | self._near(points, mics)
        columns = (level * pairs + rows) * lags + index.clamp(0, lags - 1)
        return torch.where(outside, torch.full_like(columns, -1), columns)  # -1: the zero column appended

    def _gather(self, flat: torch.Tensor, columns: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """Weighted mean over terms of ``flat`` (N x columns, a zero column last) at ``columns``
        (N x K x T or K x T)."""
        rows = slice(None) if columns.dim() == 2 else torch.arange(flat.shape[0])[:, None, None]
        values = flat[rows, columns]
        return (values * (weights / weights.sum())).sum(dim=-1)

    def response(self, correlation: torch.Tensor, points: torch.Tensor, mics: torch.Tensor) -> torch.Tensor:
        """Steered response (N x K) of correlations (N x P x L) at ``points`` (N x K x 3): the weighted mean
        over terms, linearly interpolated between lags."""
        lags = correlation.shape[-1]
        _, _, rows, weights = self._terms(mics.shape[0])
        position = self._pair_geometry(points, mics)[0]  # N x K x T
        low = position.floor().clamp(0, lags - 2)
        frac = (position - low).clamp(0, 1)
        low = low.long()
        batch = torch.arange(correlation.shape[0])[:, None, None]
        a, b = correlation[batch, rows, low], correlation[batch, rows, low + 1]
        inside = (position >= 0) & (position <= lags - 1) & self._distinct(position, mics.shape[0])
        inside = inside & ~self._near(points, mics)
        values = torch.where(inside, a + frac * (b - a), torch.zeros((), dtype=a.dtype))
        return (values * (weights / weights.sum()).to(values.dtype)).sum(dim=-1)

    def _refine(self, flat: torch.Tensor, points: torch.Tensor, steps: torch.Tensor, mics: torch.Tensor,
                keep: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One level: the 27 cubes of half the step around each point (N x k x 3), scored on the pooled
        correlations; the ``keep`` best (points, steps, scores)."""
        n = points.shape[0]
        offsets = torch.cartesian_prod(*[torch.tensor([-1.0, 0.0, 1.0])] * 3)  # 27 x 3
        steps = steps / 2
        children = self._clamp((points[:, :, None, :] + offsets * steps[..., None, None]).reshape(n, -1, 3))
        child_steps = steps[:, :, None].expand(-1, -1, offsets.shape[0]).reshape(n, -1)
        weights = self._terms(mics.shape[0])[3]
        scores = self._gather(flat, self._columns(children, mics, child_steps[..., None]), weights)
        best = scores.topk(min(keep, children.shape[1]), dim=1)
        return (torch.gather(children, 1, best.indices[..., None].expand(-1, -1, 3)),
                torch.gather(child_steps, 1, best.indices), best.values)

    def _clamp(self, points: torch.Tensor) -> torch.Tensor:
        return torch.maximum(torch.minimum(points, self.region[:, 1].float()), self.region[:, 0].float())

    def _search(self, correlation: torch.Tensor, mics: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Peak point (B x F x 3) and response (B x F) of every frame of every window (B x F x pairs x lags):
        the best of its :meth:`fitted_candidates`."""
        return self.best_candidates(*self.fitted_candidates(correlation, mics))

    @staticmethod
    def best_candidates(points: torch.Tensor, values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per frame, the candidate (B x F x 3) of highest ``values`` (B x F x K) among ``points``
        (B x F x K x 3), and that value (B x F)."""
        top = values.argmax(dim=-1, keepdim=True)  # B x F x 1
        best = torch.gather(points, 2, top[..., None].expand(-1, -1, 1, 3))[:, :, 0]
        return best, torch.gather(values, 2, top)[..., 0]

    def fitted_candidates(self, correlation: torch.Tensor, mics: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Every frame's ``frame_candidates`` fitted points (B x F x K x 3) and their exact responses
        (B x F x K), for windows of correlations B x F x pairs x lags.

        The grid levels search each window (or each of its ``search_groups`` groups of frames) on its
        frames' mean correlation (non-coherent, so the slow drift of the delays does not cancel it);
        then each frame fits its window's (group's) best candidates to its own pair delays and refines them
        on its exact response.
        """
        b, f, p, lags = correlation.shape
        corr = correlation.to(torch.float32)
        groups = torch.tensor_split(torch.arange(f), min(self.search_groups, f))
        mean = torch.stack([corr[:, rows].mean(dim=1) for rows in groups], dim=1).reshape(-1, p, lags)
        grid, sides, columns = self._coarse_grid(mics)
        k = min(self.candidates, grid.shape[0])
        flat = self._pooled(mean)
        best = self._gather(flat, columns, self._terms(mics.shape[0])[3]).topk(k, dim=1)  # B x G -> B x k
        points, steps = grid[best.indices], sides[best.indices]
        for _ in range(WINDOW_LEVELS):
            points, steps, _ = self._refine(flat, points, steps, mics, k)
        points = points[:, : self.frame_candidates].reshape(b, len(groups), -1, 3)
        # per frame: fit its group's candidates to the pair delays measured near their own, then refine
        # them on the exact (multipath) response
        frames = corr.reshape(b * f, p, lags)
        group_of_frame = torch.cat([torch.full((len(rows),), g) for g, rows in enumerate(groups)])
        points = points[:, group_of_frame].reshape(b * f, -1, 3)
        if self.fit_delays:
            points = self._fit_delays(frames, points, mics)
        points, scores = self._refine_exact(frames, points, mics)
        return points.reshape(b, f, -1, 3), scores.reshape(b, f, -1)

    def _refine_exact(self, frames: torch.Tensor, points: torch.Tensor, mics: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor]:
        """Hill-climb each point (N x K x 3) on a frame's exact response: at every level the best of the 27
        points one step around it, the step halving from ``2 ** (refine_levels - 1) * fine_step`` down to
        ``fine_step``. Returns the points and their responses (N x K)."""
        offsets = torch.cartesian_prod(*[torch.tensor([-1.0, 0.0, 1.0])] * 3)  # 27 x 3 (the centre included)
        n, k = points.shape[:2]
        for level in reversed(range(self.refine_levels)):
            step = self.fine_step * 2 ** level
            children = self._clamp(points[:, :, None, :] + offsets * step)  # N x K x 27 x 3
            scores = self.response(frames, children.reshape(n, -1, 3), mics).reshape(n, k, -1)
            best = scores.argmax(dim=-1)
            points = torch.gather(children, 2, best[..., None, None].expand(-1, -1, 1, 3))[:, :, 0]
        return points, self.response(frames, points, mics)

    def _fit_delays(self, frames: torch.Tensor, points: torch.Tensor, mics: torch.Tensor) -> torch.Tensor:
        """Move each candidate (N x K x 3) to the point whose pair delays best match the frame's.

        For every pair, the correlation peak within ``FIT_SEARCH`` lags of the candidate's delay is
        located to a fraction of a lag (parabola through the peak and its neighbours); a few damped
        Gauss-Newton steps then fit the point to those delays, weighted by the peaks' heights. The
        delays pin the direction, and their small differences (the wavefront's curvature) the range,
        which a grid search cannot resolve without a grid finer than its cost allows.
        """
        n, k = points.shape[:2]
        lags = frames.shape[-1]
        position = self._pair_geometry(points, mics, direct_only=True)[0]  # N x K x P
        window = torch.arange(-FIT_SEARCH, FIT_SEARCH + 1)
        index = (position.round().long()[..., None] + window).clamp(1, lags - 2)  # N x K x P x W
        batch = torch.arange(n)[:, None, None, None]
        pairs = torch.arange(frames.shape[1])[None, None, :, None]
        values = frames[batch, pairs, index]
        peak = values.argmax(dim=-1, keepdim=True)
        centre = torch.gather(index, -1, peak)[..., 0]
        y0, y1, y2 = (frames[batch[..., 0], pairs[..., 0], centre + d] for d in (-1, 0, 1))
        curvature = y0 - 2 * y1 + y2
        shift = torch.where(curvature < 0, 0.5 * (y0 - y2) / curvature.clamp(max=-1e-9), torch.zeros_like(y1))
        measured = centre.to(frames.dtype) + shift.clamp(-0.5, 0.5)
        weight = y1.clamp_min(0.0) + 1e-3
        first, second = pair_indices(mics.shape[0])
        scale = self.recipe.lag_rate / self.speed_of_sound
        m = mics.to(points.dtype)
        for _ in range(FIT_STEPS):
            direction = points[..., None, :] - m  # N x K x C x 3
            unit = direction / torch.linalg.vector_norm(direction, dim=-1, keepdim=True).clamp_min(1e-6)
            jacobian = (unit[..., first, :] - unit[..., second, :]) * scale  # N x K x P x 3
            residual = self._pair_geometry(points, mics, direct_only=True)[0] - measured  # N x K x P
            jw = jacobian * weight[..., None]
            normal = jw.transpose(-1, -2) @ jacobian
            damping = FIT_DAMPING * normal.diagonal(dim1=-2, dim2=-1).mean(dim=-1)[..., None, None]
            normal = normal + damping * torch.eye(3)
            step = torch.linalg.solve(normal, -(jw.transpose(-1, -2) @ residual[..., None]))[..., 0]
            points = self._clamp(points + step.clamp(-FIT_MAX_STEP, FIT_MAX_STEP))
        return points

    def grid_response(self, correlation: torch.Tensor, points: torch.Tensor, mics: torch.Tensor, step: float
                      ) -> torch.Tensor:
        """Steered response of correlations (N x pairs x lags) at the centres ``points`` (G x 3) of cubes of
        side ``step``: N x 2 x G, the multipath response (direct and ground-image terms, as the search
        scores it) and the direct terms alone. Each term reads its pair's correlation max-pooled over the
        delays its cube spans, so a peak anywhere inside a cube is seen; points within ``min_range`` of
        the array read 0. The reading is one sparse matrix product (2G x pooled columns, built once per
        grid and geometry): about 100 times faster than gathering the terms on a CPU."""
        key = (mics.numpy().tobytes(), points.numpy().tobytes(), float(step))
        if self._steering_key != key:
            self._steering_key, self._steering = key, self._steering_matrix(points, mics, step)
        pooled = self._pooled(correlation.to(torch.float32))
        with _sparse_warnings_ignored():
            values = (self._steering @ pooled.T).T  # N x 2G
        return values.reshape(-1, 2, points.shape[0])

    def _steering_matrix(self, points: torch.Tensor, mics: torch.Tensor, step: float) -> torch.Tensor:
        """The sparse (CSR) matrix whose row g reads point g's multipath response from the flattened pooled
        correlations, and row G + g its direct response (a term outside the lags or merged reads nothing)."""
        columns = self._columns(points, mics, step)  # G x terms, -1: reads nothing
        pairs = len(mic_pairs(mics.shape[0]))
        weights = self._terms(mics.shape[0])[3]
        count = points.shape[0]
        direct = torch.cat([torch.ones(pairs), torch.zeros(len(weights) - pairs)]) / pairs
        rows = torch.arange(2 * count)[:, None].expand(-1, columns.shape[1])
        values = torch.stack([weights / weights.sum(), direct])[:, None, :].expand(-1, count, -1).reshape(2 * count, -1)
        used = (torch.cat([columns, columns]) >= 0) & (values > 0)
        size = (2 * count, len(POOL_WIDTHS) * pairs * self.recipe.num_lags() + 1)
        indices = torch.stack([rows[used], torch.cat([columns, columns])[used]])
        with _sparse_warnings_ignored():
            return torch.sparse_coo_tensor(indices, values[used], size).coalesce().to_sparse_csr()

    @staticmethod
    def _pooled(corr: torch.Tensor) -> torch.Tensor:
        """N x pairs x lags -> N x (levels * pairs * lags + 1): max-pooled at POOL_WIDTHS, flattened, a zero last."""
        pooled = torch.stack([corr if w == 0 else F.max_pool1d(corr, 2 * w + 1, stride=1, padding=w)
                              for w in POOL_WIDTHS], dim=1)
        return torch.cat([pooled.reshape(corr.shape[0], -1), torch.zeros(corr.shape[0], 1)], dim=1)

    # ------------------------------------------------------------------------------ null statistic

    def threshold(self, mics: torch.Tensor) -> float:
        """The detection threshold of a geometry: the ``1 - false_alarm`` quantile, over null windows, of
        the peak response of their best frame (so ``false_alarm`` is the share of null windows with a
        detection, whatever the recipe's frame count)."""
        key = mics.numpy().tobytes()
        if key not in self._thresholds:
            sample_rate = 48000.0
            gcc = GccPhat(self.recipe, sample_rate, mics.shape[0])
            generator = np.random.default_rng(0)
            frames_per_window = self.recipe.frames
            windows = self.null_windows
            noise = generator.standard_normal((mics.shape[0], windows * frames_per_window * gcc.frame))
            frames = split_frames(noise.astype(np.float32), gcc.frame, windows * frames_per_window)
            correlation = gcc.correlate(gcc.cross_spectra(frames))  # P x (windows * F) x L
            correlation = correlation.reshape(-1, windows, frames_per_window, correlation.shape[-1])
            found = [self._search(correlation.permute(1, 2, 0, 3)[start:start + 64], mics)
                     for start in range(0, windows, 64)]
            best = torch.cat([peaks.amax(dim=1) for _, peaks in found])  # each window's best frame
            value = float(torch.quantile(best, 1.0 - self.false_alarm))
            self._thresholds[key] = value
            log.info("srp_phat: detection threshold %.4f (null quantile %.3f of the best frame of %d white-noise "
                     "windows)", value, 1.0 - self.false_alarm, windows)
        return self._thresholds[key]

    def prepare(self, inputs: dict[str, torch.Tensor]) -> None:
        """Compute the coarse grid and detection threshold of the inputs' geometry (otherwise the first call does)."""
        for geometry, _ in self.geometry_groups(inputs["audio_phase"], inputs.get("mic_positions")):
            self._coarse_grid(geometry)
            self.threshold(geometry)

    def geometry_groups(self, phase: torch.Tensor, mics_batch: torch.Tensor | None, model: str | None = None
                        ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """The batch's distinct microphone geometries (channels x 3, float64) and the rows of each; the
        default geometry for all rows when the batch carries none. Raises ValueError, naming ``model``
        (default: this net), when a geometry does not fit the phase features (B x pairs x frames x lags)."""
        groups = [(self.default_mics, torch.arange(phase.shape[0]))]
        if mics_batch is not None:
            unique, inverse = torch.unique(mics_batch.detach().cpu().double(), dim=0, return_inverse=True)
            groups = [(unique[g], torch.nonzero(inverse == g).flatten()) for g in range(unique.shape[0])]
        pairs = phase.shape[1]
        for mics, _ in groups:
            if mics.shape[0] != self.in_channels or len(mic_pairs(mics.shape[0])) != pairs:
                raise ValueError(f"{model or self.model_name}: {mics.shape[0]} mic positions for phase features of "
                                 f"{pairs} pairs")
        return groups

    # ------------------------------------------------------------------------------ forward

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        phase = inputs["audio_phase"]
        b = phase.shape[0]
        mics_batch = inputs.get("mic_positions")
        positions = torch.empty(b, 3)
        scores = torch.empty(b)
        detected = torch.empty(b, dtype=torch.bool)
        with torch.no_grad():
            for mics, rows in self.geometry_groups(phase, mics_batch):
                if mics.numpy().tobytes() not in self._thresholds:
                    self._check_region(mics)
                threshold = self.threshold(mics)
                points, peak = self._search(phase[rows].detach().cpu().permute(0, 2, 1, 3), mics)
                hit = peak > threshold
                positions[rows] = self.window_positions(points, hit)
                scores[rows] = peak.max(dim=1).values / threshold
                detected[rows] = hit.any(dim=1)
        positions, detected = self.hold_or_fallback(positions, detected, inputs.get("sequence"), inputs.get("time"))
        return {"position": positions.to(phase.dtype).to(phase.device),
                "detection_score": scores.to(phase.dtype).to(phase.device), "detected": detected.to(phase.device)}

    @staticmethod
    def window_positions(points: torch.Tensor, hit: torch.Tensor) -> torch.Tensor:
        """A window's position (B x 3) from its frames' points (B x F x 3): the coordinate-wise median of the
        frames that ``hit`` (B x F) marks detected; NaN where none is."""
        return torch.where(hit[..., None], points, torch.full_like(points, float("nan"))).nanmedian(dim=1).values

    def hold_or_fallback(self, positions: torch.Tensor, detected: torch.Tensor, sequence: torch.Tensor | None,
                         time: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Positions (B x 3, NaN where not ``detected``) with the hold and fallback applied, and the
        detections that count (with ``confirm_seconds``, the confirmed ones). Windows of a sequence come in
        time order; a sequence whose time goes back starts afresh."""
        centre = self.region.mean(dim=1).float()
        if sequence is None or time is None:
            return torch.where(detected[:, None], positions, centre), detected
        out, detected = positions.clone(), detected.clone()
        for i, (seq, t) in enumerate(zip(sequence.tolist(), time.tolist(), strict=True)):
            track = self._tracks.get(seq)
            if track is None or t < track["time"]:  # a new sequence, or the same one again from its start
                track = self._tracks[seq] = {"time": t, "last": None, "last_time": -math.inf, "sum": 0.0, "count": 0,
                                             "previous": None}
            track["time"] = t
            if bool(detected[i]) and self.confirm_seconds > 0:
                previous, track["previous"] = track["previous"], (t, positions[i])
                confirmed = previous is not None and t - previous[0] <= self.confirm_seconds and \
                    float(torch.linalg.vector_norm(positions[i] - previous[1])) <= self.confirm_distance
                detected[i] = confirmed
            if bool(detected[i]):
                track.update(last=positions[i], last_time=t, sum=track["sum"] + positions[i], count=track["count"] + 1)
            elif track["last"] is not None and t - track["last_time"] <= self.hold_seconds:
                out[i] = track["last"]
            elif track["count"] and self.fallback == "mean":
                out[i] = track["sum"] / track["count"]
            else:
                out[i] = centre
        return out, detected
