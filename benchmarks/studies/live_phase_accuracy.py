"""Accuracy of the live phase localiser: raw against smoothed, causal and fixed-lag, and the std's coverage.

``python -m benchmarks.studies.live_phase_accuracy --data DIR [--config configs/model/srp_phat.yaml]``
tracks every recording of ``DIR`` as ``aaute track`` does (batch 1, in stream order) and prints, per flight
and pooled, against the ground truth at each row's time: E (mean Euclidean error, m) of the raw localiser
output (what ``aaute predict`` gives), of the gated online smoother at lag 0 and at lag 1 s, the share of
rows detected / held / fallback, and the coverage of the smoother's std (per axis, the share of errors within
1 and 2 std, against 68.3 % and 95.4 % for a calibrated Gaussian) over the rows that have a std (measured and
held rows; fallback rows carry none). ``--smoother PRESET`` overrides the config's ``live_smoother`` preset.
``--rows DIR`` keeps each flight's raw rows there (``<flight>.npz``) and reuses them, so another smoother
preset is scored without tracking again (the raw rows do not depend on the smoother).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger(__name__)


def _smoothed(rows, preset: str, lag: float) -> tuple[np.ndarray, np.ndarray]:
    """The gated smoother's means and stds (N x 3) over the raw rows at ``lag``."""
    from zoo.deploy.live_phase import smooth_rows
    from zoo.smoothing import OnlineSmoother

    out = smooth_rows(np.array([r.timestamp for r in rows]), np.array([r.raw for r in rows]),
                      np.array([r.score for r in rows]), np.array([r.detected for r in rows]),
                      np.array([r.state for r in rows]), OnlineSmoother(preset, lag=lag))
    return np.array([r.mean for r in out]), np.array([r.std for r in out])


def _coverage(error: np.ndarray, std: np.ndarray, k: float) -> float:
    rows = np.isfinite(std).all(axis=1)
    return float((np.abs(error[rows]) <= k * std[rows]).mean()) if rows.any() else float("nan")


def flight(path: Path, config: Path, preset: str | None, store: Path | None = None) -> dict[str, float]:
    """One recording's figures (see the module docstring)."""
    from benchmarks.studies.common import live_rows
    from datamodules.formats import open_recording

    rows, configured = live_rows(path, config, store)
    preset = preset or configured
    gt = open_recording(path).ground_truth
    t = np.array([r.timestamp for r in rows])
    truth = np.stack([np.interp(t, gt.timestamps, gt.xyz[:, a]) for a in range(3)], axis=1)
    inside = (t >= gt.timestamps[0]) & (t <= gt.timestamps[-1])
    raw = np.array([r.raw for r in rows])
    result = {"rows": float(inside.sum()), "E_raw": float(np.linalg.norm(raw - truth, axis=1)[inside].mean())}
    for lag in (0.0, 1.0):
        mean, std = _smoothed(rows, preset, lag)
        error = (mean - truth)[inside]
        result[f"E_lag{lag:g}"] = float(np.linalg.norm(error, axis=1).mean())
        result[f"cover1_lag{lag:g}"] = _coverage(error, std[inside], 1.0)
        result[f"cover2_lag{lag:g}"] = _coverage(error, std[inside], 2.0)
    states = np.array([r.state for r in rows])[inside]
    for state in ("detected", "held", "fallback"):
        result[state] = float((states == state).mean())
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="a folder of recordings (MCAP) with ground truth")
    parser.add_argument("--config", type=Path, default=Path("configs/model/srp_phat.yaml"))
    parser.add_argument("--smoother", help="online smoother preset (default: the config's live_smoother, else robust)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rows", type=Path, help="keep (and reuse) each flight's raw rows in this folder")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(args.threads)
    paths = sorted(args.data.glob("*.mcap"))
    columns = ("rows", "E_raw", "E_lag0", "E_lag1", "cover1_lag0", "cover2_lag0", "cover1_lag1", "cover2_lag1",
               "detected", "held", "fallback")
    print("| flight | " + " | ".join(columns) + " |")
    print("|---" * (len(columns) + 1) + "|")
    results = []
    for path in paths:
        result = flight(path, args.config, args.smoother, args.rows)
        results.append(result)
        print(f"| {path.stem} | " + " | ".join(f"{result[c]:.3f}" for c in columns) + " |", flush=True)
    weights = np.array([r["rows"] for r in results])
    pooled = {c: float(np.average([r[c] for r in results], weights=weights)) for c in columns[1:]}
    print("| pooled | " + f"{weights.sum():.0f} | " + " | ".join(f"{pooled[c]:.3f}" for c in columns[1:]) + " |")


if __name__ == "__main__":
    main()
