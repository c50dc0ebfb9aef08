"""``aaute smooth``: smooth a track CSV (offline, causal or fixed-lag) and add per-axis standard deviations."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from datamodules.cli import check_output
from datamodules.errors import ConfigError

log = logging.getLogger("aaute")


def _cmd_smooth(args: argparse.Namespace) -> int:
    from dataclasses import replace

    import numpy as np

    from zoo.smoothing import (
        ROBUST_PRESETS,
        fit_robust_hyperparameters,
        make_smoother,
        read_track_csv,
        smooth_online,
        write_smoothed_csv,
    )

    check_output(args.src, args.dst, args.overwrite)
    robust = args.preset in ROBUST_PRESETS
    if args.lag is not None and not robust:
        raise ConfigError(f"--lag needs a robust preset ({', '.join(ROBUST_PRESETS)}), not {args.preset!r}")
    options: dict = {"fit": args.fit}
    if not robust:
        options["backend"] = args.backend
    if args.horizon is not None:
        options["horizon"] = args.horizon
    timestamps, xyz = read_track_csv(args.src)
    if args.lag is not None:
        preset = ROBUST_PRESETS[args.preset]
        if args.fit:  # learned offline on this track's positions, then run online
            fitted = fit_robust_hyperparameters([(timestamps, xyz)], preset).hyperparameters
            preset = replace(fitted, std_scale=preset.std_scale)
        track = smooth_online(timestamps, xyz, preset, lag=args.lag)
    else:
        track = make_smoother(args.preset, **options).smooth(timestamps, xyz)
    write_smoothed_csv(args.dst, track)
    log.info("smoothed %d points of %s (%s) -> %s", len(track), args.src, track.backend, args.dst)
    if track.weights is not None:
        hp = track.hyperparameters
        mode = f"lag {args.lag:g} s" if args.lag is not None else "offline"
        sys.stdout.write(f"{args.preset} smoother ({mode}): "
                         f"degrees of freedom {hp.dof:.3g}{' (fitted)' if args.fit else ''}, "
                         f"{np.mean(track.weights < 0.5):.1%} of {len(track)} frames down-weighted "
                         f"(weight < 0.5), median weight {np.median(track.weights):.2f}\n")
    beyond = int(track.beyond_horizon.sum())
    if beyond:
        log.info("%d of %d points lie beyond the %g s horizon", beyond, len(track), track.horizon)
    return 0


def add_command(sub: argparse._SubParsersAction) -> None:
    """Register ``aaute smooth`` on an argparse subparsers object."""
    smooth = sub.add_parser("smooth", help="smooth a track CSV (timestamp,x,y,z) and add per-axis std")
    smooth.add_argument("src", type=Path)
    smooth.add_argument("dst", type=Path)
    smooth.add_argument("--preset", choices=["robust", "paper", "tuned"], default="robust",
                        help="robust: Student-t state-space smoother learned on real MMAUD predictions (default); "
                             "paper: the paper's RBF GP, lengthscale 300 x 10 ms, noise 2, outputscale 1; tuned: "
                             "Matern-5/2 GP learned on real MMAUD predictions")
    smooth.add_argument("--lag", type=float, help="robust only: causal (0) or fixed-lag (seconds) smoothing, "
                                                  "each output using data up to its time plus the lag")
    smooth.add_argument("--backend", default="auto", help="GP presets: auto | exact | statespace | local")
    smooth.add_argument("--fit", action="store_true", help="fit the hyperparameters to this track first")
    smooth.add_argument("--horizon", type=float, help="flag query times farther than this (s) from any data")
    smooth.add_argument("--overwrite", action="store_true", help="replace an existing DST (never SRC itself)")
    smooth.set_defaults(func=_cmd_smooth)
