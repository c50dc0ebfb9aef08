"""Fit the ``srp_phat`` preset of the online robust smoother on development flights.

``python -m benchmarks.studies.live_phase_calibration --data DIR [DIR ...] [--rows DIR]`` tracks every
recording of the folders live (``configs/model/srp_phat.yaml``, as ``aaute track`` does; ``--rows`` keeps
and reuses the raw rows) and fits, from the detections alone, the robust smoother's hyperparameters by
variational EM (:func:`zoo.smoothing.fit_robust_hyperparameters`, started from ``robust``): srp_phat's
errors are metres with heavy tails, not MMAUD V1's centimetres, so the ``robust`` preset's noise makes its
std far too small. Then, with ground truth, the factor per lag (0, 0.5, 1 s and offline) that makes the 2-std
band cover 95 % of the errors of the rows that carry a std (detected and held;
:func:`zoo.smoothing.calibration_factor`). It prints the preset to paste into
:data:`zoo.smoothing.ROBUST_PRESETS`. Use development flights only (seed 202): the held-out flights
(seed 101) score it (:mod:`benchmarks.studies.live_phase_accuracy`).
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

#: lags (s) the preset calibrates; between them the factor is interpolated linearly
LAGS = (0.0, 0.5, 1.0)


def main(argv: list[str] | None = None) -> None:
    from benchmarks.studies.common import live_rows
    from datamodules.formats import open_recording
    from zoo.deploy.live_phase import GatedSmoothing, PhaseRow
    from zoo.smoothing import (
        ROBUST_PRESETS,
        OnlineSmoother,
        RobustSmoother,
        calibration_factor,
        fit_robust_hyperparameters,
    )

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, nargs="+", required=True, help="folders of development recordings")
    parser.add_argument("--config", type=Path, default=Path("configs/model/srp_phat.yaml"))
    parser.add_argument("--rows", type=Path, help="keep (and reuse) each flight's raw rows in this folder")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(1)
    flights = []
    for folder in args.data:
        for path in sorted(folder.glob("*.mcap")):
            store = None if args.rows is None else args.rows / folder.name
            rows, _ = live_rows(path, args.config, store)
            gt = open_recording(path).ground_truth
            t = np.array([r.timestamp for r in rows])
            truth = np.stack([np.interp(t, gt.timestamps, gt.xyz[:, a]) for a in range(3)], axis=1)
            flights.append((rows, truth))
            print(f"{folder.name}/{path.stem}: {len(rows)} rows, {np.mean([r.state == 'detected' for r in rows]):.0%} "
                  f"detected", flush=True)
    tracks = []
    for rows, _ in flights:
        measured = [r for r in rows if r.state == "detected"]
        if len(measured) >= 2:
            tracks.append((np.array([r.timestamp for r in measured]), np.array([r.raw for r in measured])))
    start = replace(ROBUST_PRESETS["robust"], std_scale=())
    report = fit_robust_hyperparameters(tracks, start, rounds=40, m_iterations=6)
    hp = replace(report.hyperparameters, std_scale=())
    print(f"fitted from {sum(len(t) for t, _ in tracks)} detections ({report.rounds} rounds, ELBO {report.elbo:.1f}): "
          f"{hp}")
    factors = []
    for lag in LAGS:
        parts = []
        for rows, truth in flights:
            gated = GatedSmoothing(OnlineSmoother(hp, lag=lag, calibrate=False))
            out = []
            for row in rows:
                out += gated.add(PhaseRow(row.timestamp, row.raw, row.score, row.detected, row.state))
            out += gated.flush()
            parts.append((np.array([r.mean for r in out]), np.array([r.std for r in out]), truth))
        factor = calibration_factor(*(np.concatenate([p[i] for p in parts]) for i in range(3)))
        factors.append((lag, round(factor, 3)))
        print(f"lag {lag:g} s: std factor {factor:.3f}", flush=True)
    parts = []  # offline: each flight's detections smoothed alone, scored at the detections
    for rows, truth in flights:
        measured = np.array([r.state == "detected" for r in rows])
        if measured.sum() < 2:
            continue
        t = np.array([r.timestamp for r in rows])[measured]
        track = RobustSmoother(hp, calibrate=False).smooth(t, np.array([r.raw for r in rows])[measured])
        parts.append((np.asarray(track.mean), np.asarray(track.std), truth[measured]))
    offline = calibration_factor(*(np.concatenate([p[i] for p in parts]) for i in range(3)))
    factors.append((float("inf"), round(offline, 3)))
    print(f"offline: std factor {offline:.3f}")
    ls, os_, noise = (tuple(round(float(v), 4) for v in a) for a in hp.arrays())
    print(f'"srp_phat": RobustHyperparameters(\n    lengthscale={ls}, outputscale={os_}, noise={noise}, '
          f"dof={hp.dof:.3g},\n    std_scale={tuple(factors)},\n),".replace("inf", "OFFLINE"))


if __name__ == "__main__":
    main()
