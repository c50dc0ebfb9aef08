"""Robust (Student-t) offline smoothing on the Matern-5/2 state-space form, and learning its hyperparameters.

Audio position estimates have heavy tails (2-5 % of the TAME frames on MMAUD V1 are more than 5 m off), so
a Gaussian likelihood lets single frames drag the track. The model here keeps the ``tuned`` preset's prior
(one Matern-5/2 GP per axis, in its exact 3-state SDE form) and replaces the Gaussian noise by a Student-t
whose scale mixture weight is **shared by x, y and z** of a frame (an audio frame is wrong as a whole):

    y_k = f(t_k) + e_k,   e_k | w_k ~ N(0, diag(r) / w_k),   w_k ~ Gamma(nu / 2, nu / 2).

Inference is mean-field variational Bayes, q(f) q(w): given the weights' means the posterior of f is a
Kalman smoother with noise r / E[w_k]; given q(f), q(w_k) is Gamma((nu + D) / 2, (nu + sum_d
E[(y_kd - f_kd)^2] / r_d) / 2). Learning (:func:`fit_robust_hyperparameters`) is variational EM on the
evidence lower bound: lengthscales, outputscales, noises and the degrees of freedom nu from the
predictions alone, never from ground truth.

Why not GPyTorch here: its ``StudentTLikelihood`` is per output (no weight shared across axes) and its
variational GP is cubic in the inducing points; a one-hour track at 10 Hz needs linear time. The M-step's
marginal likelihood is :func:`zoo.smoothing.kalman.scan_posterior` (torch parallel scans, exact
gradients); the E-step and :class:`RobustSmoother` run the blocked numpy engine
(:func:`zoo.smoothing.kalman.blocked_posterior`), about five times faster. GPyTorch's ``StudentTLikelihood``
with a variational GP is the cross-check in the tests.

Uncertainty: the posterior std of a white-noise model is overconfident, because audio errors are
correlated in time. Each preset carries a calibration factor per lag (``std_scale``) that multiplies the
posterior std; the benchmark chooses it leave-one-drone-out and reports the coverage of the left-out
drone (see :data:`ROBUST_PRESETS` and :mod:`zoo.smoothing.calibration`). The causal and fixed-lag forms of
this smoother are in :mod:`zoo.smoothing.online`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from scipy.optimize import minimize_scalar
from scipy.special import digamma, gammaln

from zoo.smoothing.gp import PRESETS
from zoo.smoothing.kalman import Batch, blocked_posterior, blocked_prior, scan_posterior
from zoo.smoothing.track import (
    DTYPE,
    SmoothedTrack,
    distance_to_nearest,
    merge_queries,
    per_axis,
    prepare,
    torch_threads,
)

log = logging.getLogger(__name__)

#: Degrees of freedom are kept in this range (nu above ~1e3 is Gaussian for any practical purpose).
DOF_BOUNDS = (0.5, 1000.0)
#: The lag (s) that stands for offline smoothing (in ``std_scale`` and :meth:`RobustHyperparameters.scale_for`).
OFFLINE = math.inf


@dataclass(frozen=True)
class RobustHyperparameters:
    """Matern-5/2 prior per axis plus a Student-t likelihood with one weight per frame.

    Attributes:
        lengthscale: seconds, per axis (x, y, z).
        outputscale: signal variance per axis, m^2.
        noise: scale of the Student-t noise per axis, m^2 (the variance of a frame of weight 1).
        dof: degrees of freedom nu of the shared weight (large: Gaussian; small: heavy tails).
        std_scale: ``((lag_s, factor), ...)``: the posterior std is multiplied by ``factor`` (linear in
            lag between the listed lags, the last one beyond; ``inf`` is offline) so that 95 % of the
            truth falls in the 2-sigma band. Empty: no calibration (factor 1).
        score_power, score_reference: a frame that comes with a detection score (a localiser's peak
            response over its detection threshold) has its noise multiplied by
            ``(score_reference / score) ** score_power`` (:meth:`noise_scale`): a weak peak is a less
            certain position. 0 (the default): every frame has the preset's noise.
        hold_scale: ``((lag_s, factor), ...)`` as ``std_scale``, for a position at a time without a frame (a
            localiser holding its last detection): its std is the prior's spread since the frames around
            it, which ``std_scale`` (fitted where frames are) does not calibrate. Empty: ``std_scale``'s.
        std_score_power: the std reported for a scored frame (and for a position held after it) is multiplied
            by ``(score / score_reference) ** std_score_power`` (:meth:`std_score_factor`), besides
            ``std_scale``: the noise's score scaling is chosen for the track, not for its std, which it
            leaves too wide at weak peaks and too narrow at strong ones. 0 (the default): no such factor.
    """

    lengthscale: tuple[float, float, float]
    outputscale: tuple[float, float, float]
    noise: tuple[float, float, float]
    dof: float
    std_scale: tuple[tuple[float, float], ...] = field(default=())
    score_power: float = 0.0
    score_reference: float = 1.0
    hold_scale: tuple[tuple[float, float], ...] = field(default=())
    std_score_power: float = 0.0

    def __post_init__(self) -> None:
        for name in ("lengthscale", "outputscale", "noise"):
            object.__setattr__(self, name, per_axis(getattr(self, name), name))
        if not (math.isfinite(self.dof) and self.dof > 0):
            raise ValueError(f"dof must be positive and finite, got {self.dof!r}")
        for name in ("std_scale", "hold_scale"):
            pairs = tuple(sorted((float(lag), float(factor)) for lag, factor in getattr(self, name)))
            if any(lag < 0 or not factor > 0 for lag, factor in pairs):
                raise ValueError(f"{name} needs (lag >= 0, factor > 0) pairs, got {getattr(self, name)!r}")
            object.__setattr__(self, name, pairs)
        for name in ("score_power", "std_score_power"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {getattr(self, name)!r}")
        if not (math.isfinite(self.score_reference) and self.score_reference > 0):
            raise ValueError(f"score_reference must be positive and finite, got {self.score_reference!r}")

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Lengthscale, outputscale and noise as float64 arrays of shape (3,)."""
        return np.array(self.lengthscale), np.array(self.outputscale), np.array(self.noise)

    def noise_scale(self, score: float) -> float:
        """The factor on the noise of a frame with detection ``score`` (1 without a power or a positive score)."""
        if self.score_power == 0 or not (math.isfinite(score) and score > 0):
            return 1.0
        return float((self.score_reference / score) ** self.score_power)

    def std_score_factor(self, score: float) -> float:
        """The factor on the reported std of a frame with detection ``score`` (1 without a power or a positive
        score)."""
        if self.std_score_power == 0 or not (math.isfinite(score) and score > 0):
            return 1.0
        return float((score / self.score_reference) ** self.std_score_power)

    def scale_for(self, lag: float) -> float:
        """The std calibration factor at ``lag`` seconds (``inf``: offline)."""
        return _factor_at(self.std_scale, lag)

    def hold_scale_for(self, lag: float) -> float:
        """The calibration factor at ``lag`` seconds of the std of a position with no frame at its time."""
        return _factor_at(self.hold_scale, lag) if self.hold_scale else self.scale_for(lag)


def _factor_at(pairs: tuple[tuple[float, float], ...], lag: float) -> float:
    """The factor of sorted ``(lag, factor)`` pairs at ``lag`` (linear between them, the last beyond; 1 if none)."""
    if not pairs:
        return 1.0
    lags = np.array([p[0] for p in pairs])
    factors = np.array([p[1] for p in pairs])
    finite = np.isfinite(lags)
    if not math.isfinite(lag) or not finite.any():
        return float(factors[-1])
    return float(np.interp(lag, lags[finite], factors[finite]))


#: Named robust presets.
#:
#: ``robust``: learned by :func:`fit_robust_hyperparameters` on the five MMAUD V1 TAME prediction tracks
#: (``../shared/data/mmaud_v1_tame/*_pred.csv``, all 11,063 frames pooled, each track centred on its own
#: mean) from the predictions alone: 12 EM rounds from the ``tuned`` preset with nu 3, then 25 more until
#: the bound moved by less than 1e-6 relative; rounded to three digits. Its bound, -12,912 nats, beats the
#: Gaussian model's marginal likelihood fitted the same way, -33,116 nats; 42 % of the frames end with a
#: weight below 0.5 (nu 1.24: very heavy tails). The std calibration factors (``std_scale``, per lag) are the
#: only use of ground truth: the 95th percentile of |truth - mean| / std over the frames and axes of all
#: five tracks, divided by 2, for the std alone (online: :class:`zoo.smoothing.OnlineSmoother`'s defaults, a
#: 5 s window and 3 iterations); the benchmark re-chooses them leave-one-drone-out to score
#: each drone. ``python -m benchmarks.studies.smoothing_bench --fit-preset`` recomputes all of it.
ROBUST_PRESETS: dict[str, RobustHyperparameters] = {
    "robust": RobustHyperparameters(
        lengthscale=(5.23, 7.51, 16.2), outputscale=(2.54, 23.6, 27.7), noise=(0.00535, 0.0354, 0.0474), dof=1.24,
        std_scale=((0.0, 2.71), (0.5, 3.41), (1.0, 3.70), (OFFLINE, 3.76)),
    ),
    # srp_phat's live detections (metre-scale errors, mostly systematic: the detections agree closely with
    # each other, so the fitted noise is small and the calibration factors large): fitted on development
    # flights only (seed 202, 15 x 60 s in default and 15 in quiet ambient) by
    # `python -m benchmarks.studies.live_phase_calibration --data DEFAULT_DIR QUIET_DIR`: variational EM on the
    # 10,657 detections (lengthscale, outputscale, noise, dof), then a detection's noise scaled by
    # (4 / score)^6 (4: the detections' median score, 4.47, rounded; a peak near the threshold is often a wrong
    # one: on those flights detections scoring below 1.9 have a median squared error of 17 m^2, above it 1.0 m^2)
    # and the fitted noise by 3, both chosen on the grid noise x {0.3, 1, 3}, power {0, 2, 4, 5, 6} by the E at
    # lag 1 s (causal E at or below raw); then the std's own factor (score / 4)^1, the power chosen on the grid
    # {0, 0.25, ..., 2} by the 2-std coverage in each sixth of the rows by score (without it the factor those
    # sixths need runs from 0.26 for the weakest detections to 2.5 for the strongest); last the std factors
    # per lag against the truth, each for a 2-std band over 95 % of its rows' errors: std_scale over the
    # detected rows, hold_scale over the held ones (one factor over both left the held rows' std 3-5x too wide).
    "srp_phat": RobustHyperparameters(
        lengthscale=(4.9, 5.26, 4.3), outputscale=(3.59, 26.1, 14.5), noise=(0.00285, 0.023, 0.0224), dof=0.7,
        std_scale=((0.0, 16.988), (0.5, 23.105), (1.0, 25.305), (OFFLINE, 28.72)),
        score_power=6.0, score_reference=4.0,
        hold_scale=((0.0, 8.934), (0.5, 11.285), (1.0, 12.142)), std_score_power=1.0,
    ),
}


# --------------------------------------------------------------------------------- variational E-step


def _weight_posterior(sq: np.ndarray, dof: float, dims: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """q(w) = Gamma(a, b) from the expected scaled squared residuals ``sq`` (N,): E[w], E[log w], b."""
    a = 0.5 * (dof + dims)
    b = 0.5 * (dof + sq)
    return a / b, digamma(a) - np.log(b), b


def _weight_kl_terms(mean_w, mean_log_w, b, dof: float, dims: int) -> float:
    """E[log p(w)] - E[log q(w)] summed over frames."""
    a = 0.5 * (dof + dims)
    half = 0.5 * dof
    log_p = half * math.log(half) - gammaln(half) + (half - 1) * mean_log_w - half * mean_w
    log_q = a * np.log(b) - gammaln(a) + (a - 1) * mean_log_w - b * mean_w
    return float(np.sum(log_p - log_q))


def _update_dof(mean_w: np.ndarray, mean_log_w: np.ndarray) -> float:
    """The nu maximising sum_k E[log Gamma(w_k; nu/2, nu/2)] (a concave 1-D problem, solved in log nu)."""
    s = float(np.mean(mean_log_w - mean_w))

    def negative(log_nu: float) -> float:
        half = 0.5 * math.exp(log_nu)
        return -(half * math.log(half) - gammaln(half) + half * s)

    result = minimize_scalar(negative, bounds=tuple(math.log(v) for v in DOF_BOUNDS), method="bounded",
                             options={"xatol": 1e-4})
    return float(math.exp(result.x))



@dataclass
class RobustFit:
    """What variational inference found on a batch of tracks.

    Attributes:
        mean: (N, 3) posterior mean of the centred data at every step.
        var: (N, 3) posterior variance of f.
        weights: (N,) E[w] per step (1: a typical frame; near 0: an outlier the smoother ignores).
        elbo: the evidence lower bound at the end, nats.
        iterations: variational iterations run.
    """

    mean: np.ndarray
    var: np.ndarray
    weights: np.ndarray
    elbo: float
    iterations: int


def infer(batch: Batch, hp: RobustHyperparameters, weights: np.ndarray | None = None,
          max_iterations: int = 30, tolerance: float = 1e-3,
          axes: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None, engine: str = "blocked") -> RobustFit:
    """Coordinate ascent on q(f) and q(w) with the hyperparameters fixed.

    ``axes`` (lengthscale, outputscale, noise arrays, one entry per column of ``batch.y``) replaces
    the preset's three axes, for tracks of another dimension. Stops when no weight moves by more than
    ``tolerance``. ``engine``: ``"blocked"`` (numpy, :func:`blocked_posterior`) or ``"scan"`` (the
    torch parallel scans); they agree to rounding.
    """
    lengthscale, outputscale, noise = hp.arrays() if axes is None else axes
    dims = batch.y.shape[1]
    if engine == "blocked":
        prior = blocked_prior(batch, lengthscale, outputscale)

        def posterior(w: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
            return blocked_posterior(prior, noise[None, :] / np.where(batch.observed, w, 1.0)[:, None])
    elif engine == "scan":
        def posterior(w: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
            with torch.no_grad():
                mean, var, loglik = scan_posterior(batch, w, lengthscale, outputscale, noise)
            return mean.numpy(), var.numpy(), float(loglik)
    else:
        raise ValueError(f"engine must be 'blocked' or 'scan', got {engine!r}")
    w = np.ones(len(batch.times)) if weights is None else weights.copy()
    elbo, done = -math.inf, 0
    for _ in range(max_iterations):
        done += 1
        mean, var, loglik = posterior(w)
        sq = (((batch.y - mean) ** 2 + var) / noise).sum(axis=1)
        new_w, mean_log_w, b = _weight_posterior(sq, hp.dof, dims)
        obs = batch.observed
        # the bound at (q(f) exact for noise r / w, new q(w)): log Z(w) plus the change of the likelihood term
        correction = 0.5 * dims * (mean_log_w - np.log(w)) - 0.5 * (new_w - w) * sq
        elbo = (loglik + float(np.sum(correction[obs]))
                + _weight_kl_terms(new_w[obs], mean_log_w[obs], b[obs], hp.dof, dims))
        change = float(np.max(np.abs(new_w - w)[obs])) if obs.any() else 0.0
        w = np.where(obs, new_w, 1.0)
        if change < tolerance:
            break
    mean, var, _ = posterior(w)
    return RobustFit(mean, var, w, elbo, done)


# ------------------------------------------------------------------------------------------- learning


def _stack_tracks(tracks: Iterable[tuple[np.ndarray, np.ndarray]]) -> tuple[Batch, list[np.ndarray]]:
    times, ys, starts, centres = [], [], [], []
    offset = 0.0
    for timestamps, xyz in tracks:
        t, y = prepare(timestamps, xyz)
        order = np.argsort(t, kind="stable")
        t, y = t[order] - t[order[0]], y[order]
        centre = y.mean(axis=0)
        times.append(t + offset)
        ys.append(y - centre)
        centres.append(centre)
        start = np.zeros(len(t), dtype=bool)
        start[0] = True
        starts.append(start)
        offset += float(t[-1]) + 1.0
    if not times:
        raise ValueError("no tracks to fit")
    y = np.concatenate(ys)
    return Batch(np.concatenate(times), y, np.ones(len(y), dtype=bool), np.concatenate(starts)), centres


@dataclass
class FitReport:
    """The learned hyperparameters and the bound that chose them.

    Attributes:
        hyperparameters: the fitted values (``std_scale`` carried over from the start).
        elbo: evidence lower bound of the Student-t model, nats (pooled over the tracks).
        gaussian_log_likelihood: exact marginal log-likelihood of the Gaussian model fitted the same way
            (``compare_gaussian=True``; else NaN): the bound's rival.
        downweighted: fraction of frames with E[w] < 0.5.
        rounds: EM rounds run.
    """

    hyperparameters: RobustHyperparameters
    elbo: float
    gaussian_log_likelihood: float
    downweighted: float
    rounds: int


def _m_step(batch: Batch, hp: RobustHyperparameters, weights: np.ndarray, iterations: int) -> RobustHyperparameters:
    """Maximise the Gaussian marginal likelihood with noise r / E[w] over log lengthscale, outputscale, noise."""
    params = [torch.log(torch.tensor(v, dtype=DTYPE)).requires_grad_() for v in hp.arrays()]
    optimizer = torch.optim.LBFGS(params, lr=1.0, max_iter=iterations, tolerance_grad=1e-6,
                                  tolerance_change=1e-9, line_search_fn="strong_wolfe")
    count = float(batch.observed.sum())

    def closure() -> torch.Tensor:
        optimizer.zero_grad()
        _, _, loglik = scan_posterior(batch, weights, params[0].exp(), params[1].exp(), params[2].exp(),
                                      smooth=False)
        loss = -loglik / count
        loss.backward()
        return loss

    optimizer.step(closure)
    values = [p.detach().exp().numpy() for p in params]
    return replace(hp, lengthscale=values[0], outputscale=values[1], noise=values[2])


def fit_robust_hyperparameters(
    tracks: Iterable[tuple[np.ndarray, np.ndarray]],
    init: RobustHyperparameters | str = "robust",
    *,
    rounds: int = 40,
    m_iterations: int = 8,
    fit_dof: bool = True,
    tolerance: float = 1e-6,
    compare_gaussian: bool = False,
) -> FitReport:
    """Variational EM for the Student-t smoother, pooled over tracks, from the positions alone.

    Each round: q(f) and q(w) (two coordinate-ascent sweeps), then nu in closed-form 1-D search, then
    ``m_iterations`` L-BFGS steps on the log lengthscales, outputscales and noises against the Gaussian
    marginal likelihood with per-frame noise r / E[w] (the only part of the bound that depends on them).
    Stops when the bound changes by less than ``tolerance`` relative.

    Raises:
        ValueError: fewer than 10 observations in all.
    """
    batch, _ = _stack_tracks(tracks)
    if len(batch.times) < 10:
        raise ValueError(f"fitting the robust smoother needs at least 10 observations, got {len(batch.times)}")
    hp = ROBUST_PRESETS[init] if isinstance(init, str) else init
    weights = np.ones(len(batch.times))
    previous = -math.inf
    fit = None
    for round_ in range(1, rounds + 1):
        fit = infer(batch, hp, weights, max_iterations=2, tolerance=0.0)
        weights = fit.weights
        if fit_dof:  # q(w) and nu alternate to their joint optimum with q(f) fixed (no smoother pass needed)
            sq = (((batch.y - fit.mean) ** 2 + fit.var) / hp.arrays()[2]).sum(axis=1)
            for _ in range(50):
                mean_w, mean_log_w, _ = _weight_posterior(sq, hp.dof, batch.y.shape[1])
                dof = _update_dof(mean_w, mean_log_w)
                converged = abs(dof - hp.dof) < 1e-4 * hp.dof
                hp = replace(hp, dof=dof)
                if converged:
                    break
            weights = _weight_posterior(sq, hp.dof, batch.y.shape[1])[0]
        hp = _m_step(batch, hp, weights, m_iterations)
        log.info("round %d: ELBO %.1f, nu %.2f, lengthscale %s, noise %s", round_, fit.elbo, hp.dof,
                 np.round(hp.lengthscale, 3), np.round(hp.noise, 3))
        if abs(fit.elbo - previous) < tolerance * abs(fit.elbo):
            break
        previous = fit.elbo
    final = infer(batch, hp, weights)
    gaussian = math.nan
    if compare_gaussian:
        start = PRESETS["tuned"]
        ghp = RobustHyperparameters(start.lengthscale, start.outputscale, start.noise, dof=DOF_BOUNDS[1])
        ones = np.ones(len(batch.times))
        ghp = _m_step(batch, ghp, ones, 100)
        with torch.no_grad():
            gaussian = float(scan_posterior(batch, ones, *ghp.arrays(), smooth=False)[2])
    return FitReport(hp, final.elbo, gaussian, float(np.mean(final.weights < 0.5)), round_)


# ---------------------------------------------------------------------------------------- offline use


def resolve_preset(preset: str | RobustHyperparameters | None, overrides: dict) -> RobustHyperparameters:
    """Hyperparameters from a preset name (None: ``robust``) or values, with the non-None ``overrides`` applied.

    Raises:
        ValueError: an unknown preset name.
    """
    if isinstance(preset, RobustHyperparameters):
        base = preset
    else:
        name = preset or "robust"
        if name not in ROBUST_PRESETS:
            raise ValueError(f"unknown robust preset {name!r}; expected one of {sorted(ROBUST_PRESETS)}")
        base = ROBUST_PRESETS[name]
    changes = {k: v for k, v in overrides.items() if v is not None}
    return replace(base, **changes) if changes else base


class RobustSmoother:
    """Offline Student-t smoother of a 3-D track with the :class:`zoo.smoothing.GPSmoother` interface.

    Args:
        preset: a name of :data:`ROBUST_PRESETS` (default ``robust``) or hyperparameters.
        lengthscale, outputscale, noise, dof: override the preset's values.
        fit: learn the hyperparameters of each track by variational EM first (from the positions only).
        calibrate: multiply the posterior std by the preset's offline ``std_scale`` factor.
        max_iterations: variational iterations of q(f), q(w) at most.
        horizon: seconds from the nearest observation beyond which a query is flagged.
        num_threads: torch intra-op threads while smoothing (None: leave torch's setting).
    """

    backend = "statespace-robust"

    def __init__(
        self,
        preset: str | RobustHyperparameters | None = "robust",
        *,
        lengthscale: float | Sequence[float] | None = None,
        outputscale: float | Sequence[float] | None = None,
        noise: float | Sequence[float] | None = None,
        dof: float | None = None,
        fit: bool = False,
        calibrate: bool = True,
        max_iterations: int = 30,
        horizon: float | None = None,
        num_threads: int | None = None,
    ):
        self.hyperparameters = resolve_preset(preset, dict(lengthscale=lengthscale, outputscale=outputscale,
                                                           noise=noise, dof=dof))
        if horizon is not None and not horizon > 0:
            raise ValueError(f"horizon must be positive seconds, got {horizon!r}")
        self.fit = fit
        self.calibrate = calibrate
        self.max_iterations = max_iterations
        self.horizon = horizon
        self.num_threads = num_threads
        #: the :class:`RobustFit` of the last call (weights, bound)
        self.last_fit: RobustFit | None = None

    def smooth(self, timestamps: np.ndarray, xyz: np.ndarray, query_times: np.ndarray | None = None) -> SmoothedTrack:
        """Smooth one track and predict at ``query_times`` (default: the observation times).

        Raises:
            ValueError: bad shapes or non-finite values.
        """
        t, y = prepare(timestamps, xyz)
        query = t if query_times is None else np.asarray(query_times, dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(query)):
            raise ValueError("query times must be finite")
        with torch_threads(self.num_threads):
            hp = self.hyperparameters
            if self.fit:
                hp = replace(fit_robust_hyperparameters([(t, y)], hp).hyperparameters, std_scale=hp.std_scale)
            order = np.argsort(t, kind="stable")
            origin = t[order[0]]
            ts, ys = t[order] - origin, y[order]
            centre = ys.mean(axis=0)
            same = query_times is None
            if same:
                times, observed, data = ts, np.ones(len(ts), dtype=bool), ys - centre
                where = np.empty(len(ts), dtype=np.int64)
                where[order] = np.arange(len(ts))
            else:
                merged = merge_queries(ts, query - origin)
                times, observed, data = merged.times, merged.observed, merged.scatter(ys - centre)
                where = merged.query_steps
            start = np.zeros(len(times), dtype=bool)
            start[0] = True
            fit = infer(Batch(times, data, observed, start), hp, max_iterations=self.max_iterations)
            self.last_fit = fit
            scale = hp.scale_for(OFFLINE) if self.calibrate else 1.0
            mean = fit.mean[where] + centre
            std = np.sqrt(np.maximum(fit.var[where], 0.0)) * scale
            horizon = self.horizon if self.horizon is not None else max(hp.lengthscale)
            beyond = distance_to_nearest(ts, query - origin) > horizon
        weights = fit.weights[where] if same else None
        return SmoothedTrack(query.copy(), mean, std, beyond, hp, self.backend, float(horizon), weights=weights)
