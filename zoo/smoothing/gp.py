"""Gaussian-process smoothing of per-window trajectory estimates, with predictive uncertainty.

The AAUTE paper smooths the student's 10 Hz position estimates with a GP on time: an RBF kernel with
lengthscale 300, noise variance 2.0 and signal variance 1.0. :class:`GPSmoother` does this per axis
(three independent GPs, batch-independent hyperparameters) and returns the posterior mean and the
predictive standard deviation at any query times; :func:`zoo.smoothing.smooth_track_file` does it for a
CSV track and :func:`zoo.smoothing.smooth_predictions` per sequence of a batch of predictions.

Conventions, decided here with measurements on the real MMAUD V1 tracks with TAME's audio predictions
(``../shared/data/mmaud_v1_tame``, five drones; mean Euclidean error E of the raw predictions, averaged
over the drones: 0.887 m):

* **Time** is float64 seconds since the first observation. Absolute ROS/Unix stamps (~1.7e9 s) would
  ruin the kernel's squared distances, and float32 loses metres even on relative times of long tracks.
* **Outputs** are centred per axis (the prior mean is the track's own mean) and *not* divided by their
  standard deviation, so noise and signal variances are in m^2 and the std is in metres. Scaling would
  not change the posterior mean (it depends only on the noise/signal ratio and the lengthscale), only
  the reported std. In metres the paper's noise variance 2.0 m^2 (std 1.4 m) is close to the TAME
  residual variance on y and z (0.9-3.1 m^2 for every drone but Avata); in standardised units it would
  be a noise std of 1.4 track spreads (8 m on y). A zero mean without centring pulls the track to the
  origin.
* **The paper's lengthscale 300** is read in units of 10 ms: 3.0 s. The paper gives no unit, and with
  its noise and signal variances every natural reading makes all five drones worse than no smoothing:
  300 ms (E 2.03 m: with noise/signal 2 and ~7 points per lengthscale the mean shrinks towards the
  track mean), 300 samples at 10 Hz = 30 s (2.30 m), 300 s (6.43 m). Only 2-6 s smooth usefully with
  those variances (3 s: 0.742 m; the best, 4.5 s: 0.736 m), as the paper reports GP smoothing to do.
  This is a choice, not a fact from the paper; the literal-ms reading is
  ``GPSmoother(lengthscale=0.3)``.
* **The ``tuned`` preset** is Matern-5/2 with per-axis hyperparameters learned by maximising the
  marginal likelihood pooled over the five tracks (ground truth not used); see :data:`PRESETS`. Its
  pooled log-likelihood beats the RBF's, each fitted the same way, by 536 nats, on every axis of every
  track; it has an exact state-space form (one hour at 10 Hz in ~1 s) and it gives E 0.579 m against
  the RBF-ML fit's 0.596 m and the paper's 0.742 m.

Backends (``backend=``):

* ``exact``: dense Cholesky, O(N^3) time, O(N^2) memory, any kernel.
* ``statespace``: Kalman filter and Rauch-Tung-Striebel smoother of the 3-state SDE that *is* the
  Matern-5/2 GP (the blocked engine of :mod:`zoo.smoothing.kalman`): O(N), equal to ``exact`` to 1e-8 m.
* ``local`` (RBF): exact GPs on overlapping windows whose margins follow from the decay of the GP's
  equivalent kernel, keeping truncation errors near 1e-7 of the data scale (2e-7 m measured at 10k).

``auto`` runs Matern-5/2 in state-space form at every size, and RBF exactly up to ``exact_max_points``
observations and locally above. GPyTorch supplies the kernels, the likelihood, the marginal likelihood
for fitting and the kernel matrices of the exact and local backends, but not the predictions: its
ExactGP prediction factorises twice and solves against the whole cross-covariance (4,000 points,
3 axes, mean and variance: 19.9 s and +3.0 GB, against 3.1 s and +0.45 GB for ``exact`` here and
0.6 s for ``local``), and its scalable path (SKI/KISS-GP with LOVE variances) gives grossly inflated
variances on long tracks. ``python -m benchmarks.studies.smoothing_bench`` measures all of this.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from typing import Literal

import gpytorch
import numpy as np
import torch

from zoo.smoothing.kalman import Batch, blocked_posterior, blocked_prior
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

KERNELS = ("rbf", "matern52")
BACKENDS = ("auto", "exact", "statespace", "local")

#: Seconds per unit of the paper's lengthscale "300" (see the module docstring).
PAPER_TIME_UNIT = 0.01
#: Relative truncation error aimed at by the ``local`` backend's window margins.
LOCAL_TOLERANCE = 1e-7


# ------------------------------------------------------------------------------------ hyperparameters


@dataclass(frozen=True)
class GPHyperparameters:
    """Per-axis (x, y, z) GP hyperparameters in physical units; one value is taken for all three axes.

    Attributes:
        kernel: ``"rbf"`` or ``"matern52"``.
        lengthscale: seconds.
        outputscale: signal variance, m^2 (prior variance of a centred axis).
        noise: observation noise variance, m^2.
    """

    kernel: str
    lengthscale: tuple[float, float, float]
    outputscale: tuple[float, float, float]
    noise: tuple[float, float, float]

    def __post_init__(self) -> None:
        if self.kernel not in KERNELS:
            raise ValueError(f"unknown kernel {self.kernel!r}; expected one of {KERNELS}")
        for name in ("lengthscale", "outputscale", "noise"):
            object.__setattr__(self, name, per_axis(getattr(self, name), name))

    @property
    def shared(self) -> bool:
        """True when all three axes have the same values (then one factorisation serves all)."""
        return all(len(set(getattr(self, n))) == 1 for n in ("lengthscale", "outputscale", "noise"))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Lengthscale, outputscale and noise as float64 arrays of shape (3,)."""
        return (np.array(self.lengthscale), np.array(self.outputscale), np.array(self.noise))


#: Named hyperparameter sets.
#:
#: ``paper``: the AAUTE paper's RBF kernel, lengthscale 300 x 10 ms = 3.0 s, noise 2.0 m^2, signal 1.0 m^2.
#:
#: ``tuned``: Matern-5/2, per axis (x, y, z), learned by maximising the marginal likelihood pooled over the
#: five MMAUD V1 TAME prediction tracks (``fit_hyperparameters(tracks, "paper", kernel="matern52",
#: max_points=20_000, tolerance=1e-7)``: all 11,063 points in blocks of 500; ground truth not used),
#: rounded to two digits. Leave-one-drone-out fits give errors within 1 cm of these on the left-out
#: drone, so the values are not fitted to one flight. The y/z outputscales are loosely determined
#: (25-35 m^2 across those fits), with little effect on the mean.
PRESETS: dict[str, GPHyperparameters] = {
    "paper": GPHyperparameters("rbf", 300 * PAPER_TIME_UNIT, 1.0, 2.0),
    "tuned": GPHyperparameters("matern52", (5.0, 8.2, 13.0), (2.5, 26.0, 23.0), (0.074, 0.69, 0.95)),
}


def _make_kernel(kernel: str, batch: int) -> gpytorch.kernels.ScaleKernel:
    shape = torch.Size([batch]) if batch > 1 else torch.Size([])
    if kernel == "rbf":
        base = gpytorch.kernels.RBFKernel(batch_shape=shape)
    else:
        base = gpytorch.kernels.MaternKernel(nu=2.5, batch_shape=shape)
    return gpytorch.kernels.ScaleKernel(base, batch_shape=shape).to(DTYPE)


def axis_kernel(hp: GPHyperparameters, axis: int) -> gpytorch.kernels.ScaleKernel:
    """An unbatched GPyTorch kernel with the hyperparameters of ``axis``."""
    kernel = _make_kernel(hp.kernel, 1)
    # tensors in float64: GPyTorch's setters turn a Python float into a float32 tensor first
    kernel.base_kernel.lengthscale = torch.tensor(hp.lengthscale[axis], dtype=DTYPE)
    kernel.outputscale = torch.tensor(hp.outputscale[axis], dtype=DTYPE)
    return kernel


# ------------------------------------------------------------------------------------------ backends


def _exact_posterior(
    hp: GPHyperparameters, t: np.ndarray, y: np.ndarray, tq: np.ndarray, chunk: int = 2048
) -> tuple[np.ndarray, np.ndarray]:
    """Exact GP posterior mean and latent variance at ``tq`` from centred data ``y`` (N x 3).

    Kernel matrices come from GPyTorch; the solve is one float64 Cholesky factorisation L and one
    triangular solve per chunk of queries against the cross-covariance k*, giving the variance
    k** - |L^-1 k*|^2 and the mean (L^-1 k*)^T L^-1 y: O(N^3 + N^2 M) time, O(N^2 + N chunk) memory.
    """
    mean = np.zeros((tq.shape[0], 3))
    var = np.empty((tq.shape[0], 3))
    groups = [[0, 1, 2]] if hp.shared else [[0], [1], [2]]
    _, outputscale, noise = hp.arrays()
    if t.shape[0] == 0:
        var[:] = outputscale
        return mean, var
    x = torch.as_tensor(t, dtype=DTYPE)[:, None]
    xq = torch.as_tensor(tq, dtype=DTYPE)[:, None]
    with torch.no_grad():
        for axes in groups:
            kernel = axis_kernel(hp, axes[0])
            K = kernel(x).to_dense()
            K.diagonal().add_(float(noise[axes[0]]))
            L, info = torch.linalg.cholesky_ex(K)
            if int(info) != 0:  # only with near-duplicate times and tiny noise: add relative jitter
                K.diagonal().add_(1e-10 * float(outputscale[axes[0]]))
                L = torch.linalg.cholesky(K)
            del K
            # mean = (L^-1 k*)^T (L^-1 y): the data ride along with the first chunk's triangular solve
            # (a one-column solve on its own stalled for 0.7 s on 2 busy cores)
            targets = torch.as_tensor(y[:, axes], dtype=DTYPE)
            whitened = None
            for start in range(0, tq.shape[0], chunk):
                cross_t = kernel(xq[start:start + chunk], x).to_dense().T
                if whitened is None:
                    v = torch.linalg.solve_triangular(L, torch.cat([targets, cross_t], dim=1), upper=False)
                    whitened, v = v[:, :len(axes)], v[:, len(axes):]
                else:
                    v = torch.linalg.solve_triangular(L, cross_t, upper=False)
                mean[start:start + chunk, axes] = (v.T @ whitened).numpy()
                latent = outputscale[axes[0]] - v.square_().sum(0).numpy()
                var[start:start + chunk, axes] = latent[:, None]
    return mean, np.maximum(var, 0.0)


def _rbf_margin(hp: GPHyperparameters, density: float, tolerance: float = LOCAL_TOLERANCE) -> float:
    """Window margin (s) beyond which data change the RBF posterior by less than ``tolerance``.

    For dense data the posterior mean is the data convolved with the equivalent kernel, whose Fourier
    transform is S / (S + noise / density) with the RBF spectral density S(w) = s2 sqrt(2 pi) l
    exp(-w^2 l^2 / 2). Its nearest complex poles give an exponential decay length
    l sqrt(2 ln(1/c)) / pi with c = noise / (density s2 sqrt(2 pi) l); the margin is that length times
    ln(1/tolerance), and never less than 5 lengthscales. The variance decays at least as fast.
    """
    lengthscale, outputscale, noise = hp.arrays()
    c = noise / (density * outputscale * math.sqrt(2 * math.pi) * lengthscale)
    decay = lengthscale * np.sqrt(2.0 * np.maximum(np.log(1.0 / c), 1.0)) / math.pi
    return float(np.max(np.maximum(decay * math.log(1.0 / tolerance), 5.0 * lengthscale)))


def _density(t: np.ndarray, lengthscale: float) -> float:
    """Observations per second, not counting gaps longer than one lengthscale."""
    covered = float(np.minimum(np.diff(t), lengthscale).sum()) if t.shape[0] > 1 else 0.0
    return t.shape[0] / max(covered, lengthscale)


def _local_posterior(
    hp: GPHyperparameters, t: np.ndarray, y: np.ndarray, tq: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Exact RBF posterior per block of queries from the data within a margin of the block.

    Blocks of queries span one margin; each is solved exactly with the data from one margin before
    its first to one margin after its last query, so the cost is O(N (density margin)^2).
    """
    margin = _rbf_margin(hp, _density(t, max(hp.lengthscale)))
    mean = np.empty((tq.shape[0], 3))
    var = np.empty((tq.shape[0], 3))
    if tq.shape[0] == 0:
        return mean, var
    order = np.argsort(tq, kind="stable")
    sorted_q = tq[order]
    block = np.floor((sorted_q - sorted_q[0]) / margin).astype(np.int64)
    bounds = np.flatnonzero(np.diff(block)) + 1
    for idx in np.split(np.arange(sorted_q.shape[0]), bounds):
        q = sorted_q[idx]
        i0 = int(np.searchsorted(t, q[0] - margin, side="left"))
        i1 = int(np.searchsorted(t, q[-1] + margin, side="right"))
        origin = q[0]
        m, v = _exact_posterior(hp, t[i0:i1] - origin, y[i0:i1], q - origin)
        mean[order[idx]] = m
        var[order[idx]] = v
    log.debug("local backend: margin %.1f s, %d blocks", margin, len(bounds) + 1)
    return mean, var


def statespace_posterior(
    hp: GPHyperparameters, t: np.ndarray, y: np.ndarray, tq: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Exact Matern-5/2 posterior by Kalman filtering and RTS smoothing, O(N + M).

    The blocked engine of :mod:`zoo.smoothing.kalman` with the Gaussian noise of every observation (the
    robust smoother's engine at unit weights). Queries that are not observation times are merged into
    the time axis as steps without an update.
    """
    if hp.kernel != "matern52":
        raise ValueError(f"the statespace backend needs the matern52 kernel, not {hp.kernel!r}")
    lengthscale, outputscale, noise = hp.arrays()
    if tq.shape == t.shape and np.array_equal(tq, t):
        times, observed, data, steps = t, np.ones(t.shape[0], dtype=bool), y, np.arange(t.shape[0])
    else:
        merged = merge_queries(t, tq)
        times, observed, data, steps = merged.times, merged.observed, merged.scatter(y), merged.query_steps
    start = np.zeros(times.shape[0], dtype=bool)
    start[0] = True
    prior = blocked_prior(Batch(times, data, observed, start), lengthscale, outputscale)
    mean, var, _ = blocked_posterior(prior, np.broadcast_to(noise, (times.shape[0], 3)))
    return mean[steps], np.maximum(var[steps], 0.0)


_POSTERIORS = {"exact": _exact_posterior, "statespace": statespace_posterior, "local": _local_posterior}


# ------------------------------------------------------------------------------------------- fitting


def _fit_blocks(
    tracks: Iterable[tuple[np.ndarray, np.ndarray]], block_points: int, max_points: int
) -> tuple[list[tuple[torch.Tensor, torch.Tensor]], np.ndarray, int]:
    """Centred tracks cut into contiguous blocks, batched by block length.

    Returns ``[(times (nb, 1, n, 1), targets (nb, 3, n)), ...]``, the pooled per-axis variance and
    the number of points used.
    """
    blocks: list[tuple[np.ndarray, np.ndarray]] = []
    sum_sq, count = np.zeros(3), 0
    for timestamps, xyz in tracks:
        t, y = prepare(timestamps, xyz)
        order = np.argsort(t, kind="stable")
        t, y = t[order] - t[order[0]], y[order] - y.mean(axis=0)
        sum_sq += (y**2).sum(axis=0)
        count += len(t)
        for idx in np.array_split(np.arange(len(t)), max(1, round(len(t) / block_points))):
            blocks.append((t[idx] - t[idx[0]], y[idx].T))
    if count < 10:
        raise ValueError(f"fitting GP hyperparameters needs at least 10 observations, got {count}")
    keep = max(1, max_points // block_points)
    if len(blocks) > keep:
        blocks = [blocks[i] for i in np.linspace(0, len(blocks) - 1, keep).round().astype(int)]
    groups = []
    for n in sorted({len(b[0]) for b in blocks}):
        same = [b for b in blocks if len(b[0]) == n]
        x = torch.as_tensor(np.stack([b[0] for b in same]), dtype=DTYPE)[:, None, :, None]
        groups.append((x, torch.as_tensor(np.stack([b[1] for b in same]), dtype=DTYPE)))
    used = sum(int(x.shape[0] * x.shape[2]) for x, _ in groups)
    return groups, np.maximum(sum_sq / count, 1e-6), used


def _block_log_likelihood(
    groups: list[tuple[torch.Tensor, torch.Tensor]],
    kernel: gpytorch.kernels.Kernel,
    likelihood: gpytorch.likelihoods.GaussianLikelihood,
) -> torch.Tensor:
    """Sum over blocks and axes of the exact GP marginal log-likelihood (GPyTorch, batched)."""
    total = torch.zeros((), dtype=DTYPE)
    for x, targets in groups:
        prior = gpytorch.distributions.MultivariateNormal(torch.zeros_like(targets), kernel(x))
        total = total + likelihood(prior).log_prob(targets).sum()
    return total


def fit_hyperparameters(
    tracks: Iterable[tuple[np.ndarray, np.ndarray]],
    init: GPHyperparameters | str = "paper",
    *,
    kernel: str | None = None,
    block_points: int = 500,
    max_points: int = 3000,
    iterations: int = 50,
    tolerance: float = 1e-6,
) -> GPHyperparameters:
    """Per-axis hyperparameters maximising the GP marginal likelihood of one or more tracks.

    Each track (timestamps (N,), xyz (N, 3)) is centred per axis and cut into contiguous blocks of
    ``block_points``; the objective is the sum of the blocks' exact marginal log-likelihoods (GPyTorch,
    float64 Cholesky), which ignores the correlation across block boundaries (500 points are 50 s at
    10 Hz, several lengthscales; 1,000-point blocks gave lengthscales and noises within 2% of these on
    TAME tracks) and keeps the cost linear in N. At most ``max_points`` points, as evenly spaced
    blocks, enter the objective. L-BFGS runs from ``init`` (a preset name or values), with the
    outputscale started at the data variance. About 5 s per 2,000-point track on 2 idle cores.

    Raises:
        ValueError: fewer than 10 observations in all.
    """
    start = PRESETS[init] if isinstance(init, str) else init
    kernel = kernel or start.kernel
    groups, axis_var, total = _fit_blocks(tracks, block_points, max_points)
    kernel_module = _make_kernel(kernel, 3)
    likelihood = gpytorch.likelihoods.GaussianLikelihood(batch_shape=torch.Size([3])).to(DTYPE)
    kernel_module.base_kernel.lengthscale = torch.tensor(start.lengthscale, dtype=DTYPE).reshape(3, 1, 1)
    kernel_module.outputscale = torch.tensor(axis_var, dtype=DTYPE)
    likelihood.noise = torch.tensor(np.minimum(start.noise, 0.5 * axis_var), dtype=DTYPE).reshape(3, 1)
    params = [*kernel_module.parameters(), *likelihood.parameters()]
    optimizer = torch.optim.LBFGS(
        params, lr=1.0, max_iter=iterations, tolerance_grad=1e-5, tolerance_change=tolerance,
        line_search_fn="strong_wolfe",
    )

    def closure() -> torch.Tensor:
        optimizer.zero_grad()
        loss = -_block_log_likelihood(groups, kernel_module, likelihood) / total
        loss.backward()
        return loss

    with gpytorch.settings.max_cholesky_size(10**7), gpytorch.settings.cholesky_jitter(double_value=1e-10):
        optimizer.step(closure)
    fitted = GPHyperparameters(
        kernel,
        kernel_module.base_kernel.lengthscale.detach().reshape(3).tolist(),
        kernel_module.outputscale.detach().reshape(3).tolist(),
        likelihood.noise.detach().reshape(3).tolist(),
    )
    log.info("fitted %s", fitted)
    return fitted


# ---------------------------------------------------------------------------------------- the smoother


class GPSmoother:
    """Per-axis GP smoother of a 3-D track; see the module docstring for the conventions.

    Args:
        preset: ``"paper"`` (default, the paper's RBF) or ``"tuned"`` (Matern-5/2 learned on real data);
            explicit ``kernel``/``lengthscale``/``outputscale``/``noise`` override its values.
        kernel: ``"rbf"`` or ``"matern52"``.
        lengthscale: seconds, one value or one per axis.
        outputscale: signal variance in m^2, one value or one per axis.
        noise: observation noise variance in m^2, one value or one per axis.
        backend: ``"auto"``, ``"exact"``, ``"statespace"`` (Matern-5/2 only) or ``"local"`` (RBF only).
        fit: learn the hyperparameters of each track by marginal likelihood, starting from the preset.
        horizon: seconds from the nearest observation beyond which a query is flagged as unsupported
            (default: the largest lengthscale, where the prior correlation has dropped to 0.61 or less).
        on_beyond_horizon: ``"warn"`` (log a warning, keep the values), ``"nan"`` (NaN mean and std
            there) or ``"raise"`` (ValueError).
        exact_max_points: for the RBF kernel, ``auto`` uses the exact backend up to this many
            observations and the local one above (Matern-5/2 always runs in state-space form).
        num_threads: torch intra-op threads while smoothing (None: leave torch's setting).
    """

    def __init__(
        self,
        preset: str | None = "paper",
        *,
        kernel: str | None = None,
        lengthscale: float | Sequence[float] | None = None,
        outputscale: float | Sequence[float] | None = None,
        noise: float | Sequence[float] | None = None,
        backend: str = "auto",
        fit: bool = False,
        horizon: float | None = None,
        on_beyond_horizon: Literal["warn", "nan", "raise"] = "warn",
        exact_max_points: int = 2000,
        num_threads: int | None = None,
    ):
        if preset is not None and preset not in PRESETS:
            raise ValueError(f"unknown preset {preset!r}; expected one of {sorted(PRESETS)}")
        if preset is None and any(v is None for v in (kernel, lengthscale, outputscale, noise)):
            raise ValueError("without a preset, give kernel, lengthscale, outputscale and noise")
        base = PRESETS[preset] if preset is not None else None
        changes = {k: v for k, v in dict(kernel=kernel, lengthscale=lengthscale, outputscale=outputscale,
                                         noise=noise).items() if v is not None}
        self.hyperparameters = replace(base, **changes) if base is not None else GPHyperparameters(**changes)
        if backend not in BACKENDS:
            raise ValueError(f"unknown backend {backend!r}; expected one of {BACKENDS}")
        if on_beyond_horizon not in ("warn", "nan", "raise"):
            raise ValueError(f"on_beyond_horizon must be 'warn', 'nan' or 'raise', not {on_beyond_horizon!r}")
        if horizon is not None and not horizon > 0:
            raise ValueError(f"horizon must be positive seconds, got {horizon!r}")
        self.backend = backend
        self.fit = fit
        self.horizon = horizon
        self.on_beyond_horizon = on_beyond_horizon
        self.exact_max_points = exact_max_points
        self.num_threads = num_threads
        if (backend, self.hyperparameters.kernel) in (("statespace", "rbf"), ("local", "matern52")):
            raise ValueError(f"backend {backend!r} does not support the {self.hyperparameters.kernel!r} "
                             "kernel; statespace is for matern52, local for rbf")

    def choose_backend(self, n: int, kernel: str | None = None) -> str:
        """The backend that runs for ``n`` observations."""
        kernel = kernel or self.hyperparameters.kernel
        if self.backend != "auto":
            return self.backend
        if kernel == "matern52":
            return "statespace"  # exact and O(N) at every size
        return "exact" if n <= self.exact_max_points else "local"

    def smooth(
        self, timestamps: np.ndarray, xyz: np.ndarray, query_times: np.ndarray | None = None
    ) -> SmoothedTrack:
        """Smooth one track and predict at ``query_times`` (default: the observation times).

        Args:
            timestamps: (N,) seconds, any origin (absolute ROS time is fine), any order, duplicates allowed.
            xyz: (N, 3) positions in metres.
            query_times: (M,) seconds on the same clock as ``timestamps``.

        Raises:
            ValueError: bad shapes, non-finite values, or queries beyond the horizon with
                ``on_beyond_horizon="raise"``.
        """
        t, y = prepare(timestamps, xyz)
        query = t if query_times is None else np.asarray(query_times, dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(query)):
            raise ValueError("query times must be finite")
        with torch_threads(self.num_threads):
            hp = fit_hyperparameters([(t, y)], self.hyperparameters) if self.fit else self.hyperparameters
            order = np.argsort(t, kind="stable")
            origin = t[order[0]]
            ts, ys, tq = t[order] - origin, y[order], query - origin
            horizon = self.horizon if self.horizon is not None else max(hp.lengthscale)
            distance = distance_to_nearest(ts, tq)
            beyond = distance > horizon
            if beyond.any():
                message = (f"{int(beyond.sum())} of {len(query)} query times lie more than {horizon:.3g} s "
                           f"from any observation (up to {distance.max():.3g} s): the smoothed track there "
                           "falls back towards the track mean and its std towards the prior std")
                if self.on_beyond_horizon == "raise":
                    raise ValueError(message)
                if self.on_beyond_horizon == "warn":
                    log.warning(message)
            centre = ys.mean(axis=0)
            backend = self.choose_backend(len(ts), hp.kernel)
            mean, var = _POSTERIORS[backend](hp, ts, ys - centre, tq)
        mean += centre
        std = np.sqrt(var)
        if self.on_beyond_horizon == "nan":
            mean[beyond] = np.nan
            std[beyond] = np.nan
        return SmoothedTrack(query.copy(), mean, std, beyond, hp, backend, float(horizon))
