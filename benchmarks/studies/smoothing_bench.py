"""Accuracy, calibration and speed of the trajectory smoothers: real MMAUD V1 tracks and long simulated ones.

``python -m benchmarks.studies.smoothing_bench --accuracy`` scores every smoother on the five MMAUD V1 TAME tracks
(``../shared/data/mmaud_v1_tame``): mean Euclidean error E per drone and pooled, for the raw predictions,
the ``paper`` and ``tuned`` GPs and the ``robust`` Student-t smoother offline, causal (lag 0) and at fixed
lags, with the 2-sigma coverage of the ground truth. The robust smoother's std calibration factor is
chosen leave-one-drone-out (on the other four drones' ground truth, same mode) for the coverage of each
drone; hyperparameters come from the predictions alone. ``--fit-preset`` re-learns the ``robust``
preset. ``--speed-robust`` times the robust smoother offline on a 1-hour track and the causal update.
``--choose-online`` scores the online smoother's (window, iterations) settings on every lag and picks
one leave-one-drone-out; ``--window`` / ``--iterations`` set them for ``--accuracy`` and ``--speed-robust``.

``python -m benchmarks.studies.smoothing_bench`` (no flag) measures the GP backends' speed and memory. Every case
(backend x track length) runs in a fresh subprocess so its peak resident memory (``ru_maxrss``) is its
own; the time is one call of ``GPSmoother.smooth`` (mean and std of x, y, z at every observation time)
after a warm-up, so imports and first-call set-up are excluded. The track is a simulated drone flight at
10 Hz with jittered stamps and 1 m noise per axis. Two references show what GPyTorch's own prediction machinery costs:
``gpytorch-exact`` is ``ExactGP`` prediction with exact (Cholesky) variances, and ``gpytorch-ski`` is
KISS-GP (``GridInterpolationKernel``, grid spacing lengthscale / 10, CG tolerance 1e-4) computing the
posterior **mean only**: its fast variances (LOVE) are not usable on long tracks.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: (name, GPSmoother preset, backend, largest track). The exact backends are cubic in time and
#: quadratic in memory; GPyTorch's own exact prediction is run at 1,000 points only.
CASES = (
    ("exact", "paper", "exact", 10_000),
    ("local", "paper", "local", None),
    ("exact", "tuned", "exact", 10_000),
    ("statespace", "tuned", "statespace", None),
    ("gpytorch-exact", "paper", "gpytorch-exact", 4_000),
    ("gpytorch-ski", "paper", "ski", None),
)


def make_track(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A simulated flight of ``n`` samples at 10 Hz: timestamps (absolute) and noisy xyz."""
    from datamodules.simulate.trajectory import generate_trajectory

    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1 + rng.normal(0.0, 0.005, n)
    xyz = generate_trajectory(n * 0.1 + 1.0, rng).position(np.clip(t, 0.0, None))
    return t + 1.69e9, xyz + rng.normal(0.0, 1.0, xyz.shape)


def _gpytorch_model(
    t: np.ndarray, xyz: np.ndarray, lengthscale: float, outputscale: float, noise: float, ski: bool
) -> np.ndarray:
    """Posterior mean (N x 3) by GPyTorch itself: KISS-GP without variances, or exact with them."""
    import gpytorch
    import torch

    class Model(gpytorch.models.ExactGP):
        def __init__(self, x, y, likelihood, kernel):
            super().__init__(x, y, likelihood)
            self.kernel = kernel

        def forward(self, x):
            zero = torch.zeros(x.shape[:-1], dtype=x.dtype)
            return gpytorch.distributions.MultivariateNormal(zero, self.kernel(x))

    rel = t - t.min()
    x = torch.as_tensor(rel, dtype=torch.float64)[:, None]
    centre = xyz.mean(axis=0)
    y = torch.as_tensor((xyz - centre).T, dtype=torch.float64)
    batch = torch.Size([3])
    base = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel(batch_shape=batch), batch_shape=batch)
    base = base.double()  # float64 before the values go in: GPyTorch's setters would round floats to float32
    base.base_kernel.lengthscale = torch.tensor(lengthscale, dtype=torch.float64)
    base.outputscale = torch.tensor(outputscale, dtype=torch.float64)
    kernel = base
    if ski:
        grid = int(np.ceil((rel.max() + 2 * lengthscale) / (lengthscale / 10))) + 1
        kernel = gpytorch.kernels.GridInterpolationKernel(
            base, grid_size=grid, num_dims=1, grid_bounds=[(-lengthscale, float(rel.max()) + lengthscale)]
        )
    likelihood = gpytorch.likelihoods.GaussianLikelihood(batch_shape=batch).double()
    likelihood.noise = torch.tensor(noise, dtype=torch.float64)
    model = Model(x, y, likelihood, kernel).double().eval()
    likelihood.double().eval()
    settings = gpytorch.settings
    if not ski:
        with torch.no_grad(), settings.max_cholesky_size(10**6), settings.fast_pred_var(False):
            posterior = model(x)
            posterior.variance  # noqa: B018  (computed, as a smoother must)
            return posterior.mean.numpy().T + centre
    with (torch.no_grad(), settings.skip_posterior_variances(True), settings.max_cholesky_size(0),
          settings.eval_cg_tolerance(1e-4), settings.max_cg_iterations(2000)):
        return model(x).mean.numpy().T + centre


def run_case(track: Path, preset: str, backend: str, threads: int) -> dict[str, float]:
    """Time one smoothing call in this process; called in a subprocess by :func:`main`."""
    import torch

    from zoo.smoothing import PRESETS, GPSmoother

    torch.set_num_threads(threads)
    data = np.load(track)
    t, xyz = data[:, 0], data[:, 1:]
    baseline = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    if backend in ("ski", "gpytorch-exact"):
        hp = PRESETS[preset]
        args = (hp.lengthscale[0], hp.outputscale[0], hp.noise[0], backend == "ski")
        _gpytorch_model(t[:200], xyz[:200], *args)
        start = time.perf_counter()
        mean = _gpytorch_model(t, xyz, *args)
    else:
        smoother = GPSmoother(preset, backend=backend)
        smoother.smooth(t[:200], xyz[:200])
        start = time.perf_counter()
        mean = smoother.smooth(t, xyz).mean
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    out = Path(str(track) + f".{preset}.{backend}.mean.npy")
    np.save(out, mean)
    return {"seconds": seconds, "peak_mb": peak / 1024, "baseline_mb": baseline / 1024}


DRONES_V1 = ("Mavic2", "Mavic3", "Phantom4", "Avata", "M300")
#: Fixed lags (s) scored by --accuracy besides offline.
LAGS = (0.0, 0.5, 1.0)


def _real_tracks(folder: Path) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    from zoo.smoothing import read_track_csv

    tracks = {}
    for drone in DRONES_V1:
        t, pred = read_track_csv(folder / f"{drone}_pred.csv")
        t_gt, gt = read_track_csv(folder / f"{drone}_gt.csv")
        if not np.array_equal(t, t_gt):
            raise ValueError(f"{folder}: {drone} prediction and ground-truth timestamps differ")
        tracks[drone] = (t, pred, gt)
    return tracks


def _smoothed(mode: str, t: np.ndarray, pred: np.ndarray, **online):
    """(mean, std, weights or None) of one smoother mode, uncalibrated; ``online``: OnlineSmoother options."""
    from zoo.smoothing import GPSmoother, RobustSmoother, smooth_online

    if mode in ("paper", "tuned"):
        track = GPSmoother(mode).smooth(t, pred)
    elif mode == "robust":
        track = RobustSmoother("robust", calibrate=False).smooth(t, pred)
    else:
        track = smooth_online(t, pred, "robust", lag=float(mode.split("=")[1]), calibrate=False, **online)
    return track.mean, track.std, track.weights


def accuracy(folder: Path, lags: tuple[float, ...] = LAGS, **online) -> str:
    """The Markdown table of E and coverage per mode (see the module docstring).

    ``online``: :class:`zoo.smoothing.OnlineSmoother` options of the lag modes (default: its own).
    """
    from zoo.smoothing import ROBUST_PRESETS, calibration_factor, coverage

    tracks = _real_tracks(folder)
    modes = ["raw", "paper", "tuned", "robust", *[f"lag={lag:g}" for lag in lags]]
    header = ["mode", *DRONES_V1, "pooled E", "2-sigma coverage (LODO-calibrated)", "coverage, preset factor",
              "uncalibrated", "down-weighted", "seconds"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    hp = ROBUST_PRESETS["robust"]
    for mode in modes:
        start = time.perf_counter()
        results = {}
        for drone, (t, pred, gt) in tracks.items():
            if mode == "raw":
                results[drone] = (pred, None, None, gt)
            else:
                results[drone] = (*_smoothed(mode, t, pred, **online), gt)
        seconds = time.perf_counter() - start
        errors = {d: np.linalg.norm(r[0] - r[3], axis=1) for d, r in results.items()}
        pooled = float(np.concatenate(list(errors.values())).mean())
        cells = [mode, *[f"{errors[d].mean():.3f}" for d in DRONES_V1], f"{pooled:.3f}"]
        if mode == "raw":
            cells += ["-", "-", "-", "-"]
        else:
            inside, preset_inside, raw_inside = [], [], []
            robust = mode == "robust" or mode.startswith("lag")
            lag = float(mode.split("=")[1]) if mode.startswith("lag") else float("inf")
            for drone, (mean, std, _, gt) in results.items():
                others = [results[o] for o in DRONES_V1 if o != drone]
                factor = calibration_factor(np.concatenate([o[0] for o in others]),
                                            np.concatenate([o[1] for o in others]),
                                            np.concatenate([o[3] for o in others]))
                n = mean.size
                inside.append(coverage(mean, factor * std, gt) * n)
                scale = hp.scale_for(lag) if robust else 1.0
                preset_inside.append(coverage(mean, scale * std, gt) * n)
                raw_inside.append(coverage(mean, std, gt) * n)
            total = sum(r[0].size for r in results.values())
            weights = [r[2] for r in results.values() if r[2] is not None]
            down = f"{np.mean(np.concatenate(weights) < 0.5):.1%}" if weights else "-"
            cells += [f"{sum(inside) / total:.1%}", f"{sum(preset_inside) / total:.1%}" if robust else "-",
                      f"{sum(raw_inside) / total:.1%}", down]
        cells.append(f"{seconds:.1f}")
        lines.append("| " + " | ".join(cells) + " |")
        print(lines[-1], file=sys.stderr, flush=True)
    return "\n".join(lines)


def choose_online(folder: Path, windows: tuple[float, ...] = (0.0, 3.0, 5.0, 8.0),
                  iterations: tuple[int, ...] = (2, 3), lags: tuple[float, ...] = LAGS) -> str:
    """Pooled E of the online smoother per (window, iterations) and lag, and a leave-one-drone-out choice.

    For each drone the setting is the one with the lowest pooled E over the other four drones (summed
    over the lags, since one default serves every lag); the drone is then scored with it. The table
    says which setting each drone's four others picked and what the picks score pooled.
    """
    from zoo.smoothing import smooth_online

    tracks = _real_tracks(folder)
    settings = [(w, i) for w in windows for i in iterations]
    # sums[setting][lag][drone] = (sum of E, frames)
    sums: dict = {}
    for window, its in settings:
        for lag in lags:
            for drone, (t, pred, gt) in tracks.items():
                track = smooth_online(t, pred, "robust", lag=lag, window=window, iterations=its, calibrate=False)
                error = np.linalg.norm(track.mean - gt, axis=1)
                sums.setdefault((window, its), {}).setdefault(lag, {})[drone] = (float(error.sum()), len(error))

    def pooled(setting, lag, drones) -> float:
        cells = [sums[setting][lag][d] for d in drones]
        return sum(c[0] for c in cells) / sum(c[1] for c in cells)

    header = ["window s", "iterations", *[f"lag {lag:g} s: pooled E" for lag in lags]]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for setting in settings:
        lines.append("| " + " | ".join([f"{setting[0]:g}", str(setting[1]),
                                        *[f"{pooled(setting, lag, DRONES_V1):.3f}" for lag in lags]]) + " |")
    picks = {}
    for drone in DRONES_V1:
        others = [d for d in DRONES_V1 if d != drone]
        picks[drone] = min(settings, key=lambda st: sum(pooled(st, lag, others) for lag in lags))
    lines.append("")
    lines.append("leave-one-drone-out picks (window s, iterations): "
                 + ", ".join(f"{d} {picks[d][0]:g}/{picks[d][1]}" for d in DRONES_V1))
    for lag in lags:
        total = sum(sums[picks[d]][lag][d][0] for d in DRONES_V1)
        frames = sum(sums[picks[d]][lag][d][1] for d in DRONES_V1)
        lines.append(f"lag {lag:g} s: pooled E of the left-out drones with their picks {total / frames:.3f}")
    return "\n".join(lines)


def fit_preset(folder: Path, rounds: int = 40) -> str:
    """Re-learn the ``robust`` preset from the five prediction tracks and its per-lag calibration factors.

    EM starts from the shipped preset (a check that it is a fixed point of the fit); from ``tuned`` with
    nu 3, ``fit_robust_hyperparameters(tracks, replace(tuned-as-robust, dof=3.0))``, it took 37 rounds.
    """
    from dataclasses import replace

    from zoo.smoothing import ROBUST_PRESETS, calibration_factor, fit_robust_hyperparameters

    tracks = _real_tracks(folder)
    report = fit_robust_hyperparameters([(t, pred) for t, pred, _ in tracks.values()], ROBUST_PRESETS["robust"],
                                        rounds=rounds, m_iterations=6, compare_gaussian=True)
    lines = [f"fitted (predictions only): {report.hyperparameters}",
             f"ELBO {report.elbo:.1f} nats; Gaussian model, fitted alike: {report.gaussian_log_likelihood:.1f}; "
             f"down-weighted {report.downweighted:.1%}; {report.rounds} rounds"]
    factors = []
    for lag in (*LAGS, float("inf")):
        mode = "robust" if lag == float("inf") else f"lag={lag:g}"
        parts = []
        for t, pred, gt in tracks.values():
            from zoo.smoothing import RobustSmoother, smooth_online

            hp = replace(report.hyperparameters, std_scale=())
            track = (RobustSmoother(hp).smooth(t, pred) if mode == "robust"
                     else smooth_online(t, pred, hp, lag=lag))
            parts.append((track.mean, track.std, gt))
        factors.append((lag, calibration_factor(*(np.concatenate([p[i] for p in parts]) for i in range(3)))))
    lines.append(f"std_scale (all five drones' ground truth): {tuple((lag, round(f, 3)) for lag, f in factors)}")
    return "\n".join(lines)


def speed_robust(threads: int = 1, points: int = 36_000, **options) -> str:
    """Seconds to smooth a ``points`` track offline and ms per online update (median over 2,000 frames).

    ``options``: :class:`zoo.smoothing.OnlineSmoother` settings (default: its own).
    """
    import torch

    from zoo.smoothing import OnlineSmoother, RobustSmoother

    torch.set_num_threads(threads)
    t, xyz = make_track(points)
    smoother = RobustSmoother("robust")
    smoother.smooth(t[:200], xyz[:200])
    start = time.perf_counter()
    smoother.smooth(t, xyz)
    offline = time.perf_counter() - start
    lines = [f"robust offline, {points} points: {offline:.2f} s ({smoother.last_fit.iterations} iterations, "
             f"{threads} torch thread(s))"]
    for lag in LAGS:
        online = OnlineSmoother("robust", lag=lag, **options)
        times = []
        for i in range(2000):
            start = time.perf_counter()
            online.update(t[i], xyz[i])
            times.append(time.perf_counter() - start)
        lines.append(f"online lag {lag:g} s (window {online.window:g} s, {online.iterations} iterations): median "
                     f"{np.median(times) * 1e3:.3f} ms, 95th percentile {np.quantile(times, 0.95) * 1e3:.3f} ms "
                     "per frame")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--accuracy", action="store_true", help="E and coverage of every smoother on MMAUD V1")
    parser.add_argument("--fit-preset", action="store_true", help="re-learn the robust preset (minutes)")
    parser.add_argument("--speed-robust", action="store_true", help="time the robust smoother (1-hour track)")
    parser.add_argument("--choose-online", action="store_true",
                        help="online smoother's E per (window, iterations), leave-one-drone-out pick (minutes)")
    parser.add_argument("--window", type=float, default=None, help="online smoother's window, s (default: its own)")
    parser.add_argument("--iterations", type=int, default=None,
                        help="online smoother's variational iterations per update (default: its own)")
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2].parent / "shared" / "data"
                        / "mmaud_v1_tame", help="folder of the MMAUD V1 TAME CSVs")
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 36000])
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads (2 cores here)")
    parser.add_argument("--exact-max", type=int, default=10000, help="largest track for the exact backends")
    parser.add_argument("--skip", nargs="*", default=[], help="case names to skip (e.g. gpytorch-ski)")
    parser.add_argument("--case", nargs=4, metavar=("TRACK", "PRESET", "BACKEND", "THREADS"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.accuracy or args.fit_preset or args.speed_robust or args.choose_online:
        import torch

        from zoo.smoothing import OnlineSmoother

        torch.set_num_threads(args.threads)
        online = {k: v for k, v in (("window", args.window), ("iterations", args.iterations)) if v is not None}
        if args.fit_preset:
            print(fit_preset(args.data))
        if args.choose_online:
            print(f"MMAUD V1 TAME tracks, online smoother settings, {args.threads} torch thread(s)\n")
            print(choose_online(args.data))
        if args.accuracy:
            used = OnlineSmoother("robust", **online)
            print(f"MMAUD V1 TAME tracks, {args.threads} torch thread(s); lag modes: window {used.window:g} s, "
                  f"{used.iterations} iterations per update\n")
            print(accuracy(args.data, **online))
        if args.speed_robust:
            print(speed_robust(args.threads, **online))
        return 0
    if args.case:
        track, preset, backend, threads = args.case
        print(json.dumps(run_case(Path(track), preset, backend, int(threads))))
        return 0

    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for n in args.sizes:
            t, xyz = make_track(n)
            track = Path(folder) / f"track{n}.npy"
            np.save(track, np.column_stack([t, xyz]))
            for name, preset, backend, largest in CASES:
                if name in args.skip or (largest is not None and n > min(largest, args.exact_max)):
                    continue
                command = [sys.executable, "-m", "benchmarks.studies.smoothing_bench", "--case", str(track), preset,
                           backend, str(args.threads)]
                done = subprocess.run(command, capture_output=True, text=True, check=False)
                if done.returncode != 0:
                    error = done.stderr.strip().splitlines()[-1]
                    rows.append((name, preset, n, f"failed: {error}", "", "", ""))
                    continue
                result = json.loads(done.stdout.strip().splitlines()[-1])
                mean = np.load(str(track) + f".{preset}.{backend}.mean.npy")
                reference = Path(str(track) + f".{preset}.exact.mean.npy")
                diff = f"{np.abs(mean - np.load(reference)).max():.1e}" if reference.exists() else "-"
                rows.append((name, preset, n, f"{result['seconds']:.2f}", f"{result['peak_mb']:.0f}",
                             f"{result['peak_mb'] - result['baseline_mb']:.0f}", diff))
                print(" | ".join(str(v) for v in rows[-1]), file=sys.stderr, flush=True)
    header = ("backend", "preset", "points", "seconds", "peak RSS MB", "added MB", "max |mean - exact| m")
    print(f"GP smoothing, 3 axes, mean + std ({args.threads} torch threads; gpytorch-ski: mean only)\n")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in rows:
        print("| " + " | ".join(str(v) for v in row) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
