"""Speed and memory of the GP trajectory smoother's backends on long 10 Hz tracks.

Run ``python -m benchmarks.smoothing_bench``. Every case (backend x track length) runs in a fresh
subprocess so its peak resident memory (``ru_maxrss``) is its own; the time is one call of
``GPSmoother.smooth`` (mean and std of x, y, z at every observation time) after a warm-up, so imports
and first-call set-up are excluded. The track is a simulated drone flight at 10 Hz with jittered stamps
and 1 m noise per axis. Two references show what GPyTorch's own prediction machinery costs:
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 36000])
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads (2 cores here)")
    parser.add_argument("--exact-max", type=int, default=10000, help="largest track for the exact backends")
    parser.add_argument("--skip", nargs="*", default=[], help="case names to skip (e.g. gpytorch-ski)")
    parser.add_argument("--case", nargs=4, metavar=("TRACK", "PRESET", "BACKEND", "THREADS"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
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
                command = [sys.executable, "-m", "benchmarks.smoothing_bench", "--case", str(track), preset,
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
