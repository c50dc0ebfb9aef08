"""``aaute smooth``: smooth a track CSV (offline, causal or fixed-lag) and add per-axis standard deviations.

A file of several tracks (a benchmark's ``predictions.csv``: flights x lights) is smoothed one
``(sequence_id, light)`` track at a time, and its output keeps those columns. A detecting localiser's
track (``srp_phat``'s ``aaute predict`` CSV: ``detection_score,detected,state``) is smoothed from its
detections alone, as ``aaute test`` (offline) and ``aaute track`` (``--lag``) smooth it: its held and
fallback rows are positions it remembers or falls back to, not measurements.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from datamodules.cli import check_output
from datamodules.errors import ConfigError

if TYPE_CHECKING:
    from zoo.smoothing import OnlineSmoother, SmoothedTrack, TrackPart

log = logging.getLogger("aaute")


def _cmd_smooth(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from zoo.smoothing import (
        ROBUST_PRESETS,
        OnlineSmoother,
        fit_robust_hyperparameters,
        make_smoother,
        read_tracks_csv,
        smooth_detected_track,
        smooth_online,
        write_smoothed_tracks,
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
    parts = read_tracks_csv(args.src)  # one per (sequence_id, light) of a benchmark's predictions.csv
    gated = [p for p in parts if p.detected is not None]
    if gated:
        detected = sum(int(p.detected.sum()) for p in gated)  # type: ignore[union-attr]
        log.info("%s: smoothing the %d detected of %d rows (the others are held or fallback positions)", args.src,
                 detected, sum(len(p.timestamps) for p in gated))
    if args.lag is not None:
        preset = ROBUST_PRESETS[args.preset]
        if args.fit:  # learned offline on these tracks' positions, then run online
            fitted = fit_robust_hyperparameters([_measured(p) for p in parts], preset).hyperparameters
            preset = replace(fitted, std_scale=preset.std_scale)
        tracks = [smooth_online(p.timestamps, p.xyz, preset, lag=args.lag) if p.detected is None
                  else _gated_online(p, OnlineSmoother(preset, lag=args.lag)) for p in parts]
    else:
        smoother = make_smoother(args.preset, **options)
        tracks = [smoother.smooth(p.timestamps, p.xyz) if p.detected is None
                  else smooth_detected_track(smoother, p.timestamps, p.xyz, p.detected) for p in parts]
    write_smoothed_tracks(args.dst, [(p.keys, track) for p, track in zip(parts, tracks, strict=True)])
    points = sum(len(track) for track in tracks)
    log.info("smoothed %d points of %s in %d track(s) (%s) -> %s", points, args.src, len(tracks), tracks[0].backend,
             args.dst)
    track = tracks[0]
    if track.weights is not None and not gated:
        hp = track.hyperparameters
        weights = np.concatenate([t.weights for t in tracks])
        mode = f"lag {args.lag:g} s" if args.lag is not None else "offline"
        sys.stdout.write(f"{args.preset} smoother ({mode}): "
                         f"degrees of freedom {hp.dof:.3g}{' (fitted)' if args.fit else ''}, "
                         f"{np.mean(weights < 0.5):.1%} of {points} frames down-weighted "
                         f"(weight < 0.5), median weight {np.median(weights):.2f}\n")
    beyond = sum(int(t.beyond_horizon.sum()) for t in tracks)
    if beyond:
        log.info("%d of %d points lie beyond the %g s horizon", beyond, points, track.horizon)
    return 0


def _measured(part: TrackPart) -> tuple[np.ndarray, np.ndarray]:
    """A track's measured rows (its detections, when it says which): what a smoother is fitted to."""
    from zoo.smoothing import measured_rows

    rows = measured_rows(part.detected, len(part.timestamps))
    return part.timestamps[rows], part.xyz[rows]


def _gated_online(part: TrackPart, smoother: OnlineSmoother) -> SmoothedTrack:
    """A detecting localiser's track smoothed causally or at a fixed lag, as ``aaute track`` does."""
    from zoo.deploy.live_phase import smooth_rows
    from zoo.smoothing import SmoothedTrack

    rows = smooth_rows(part.timestamps, part.xyz, part.scores, part.detected, part.states, smoother)
    return SmoothedTrack(np.array([r.timestamp for r in rows]), np.stack([r.mean for r in rows]),
                         np.stack([r.std for r in rows]), np.zeros(len(rows), dtype=bool), smoother.hyperparameters,
                         f"online-lag{smoother.lag:g}-detections", math.inf)


def add_command(sub: argparse._SubParsersAction) -> None:
    """Register ``aaute smooth`` on an argparse subparsers object."""
    smooth = sub.add_parser("smooth", help="smooth a track CSV (timestamp,x,y,z) and add per-axis std")
    smooth.add_argument("src", type=Path)
    smooth.add_argument("dst", type=Path)
    smooth.add_argument("--preset", choices=["robust", "srp_phat", "paper", "tuned"], default="robust",
                        help="robust: Student-t state-space smoother learned on real MMAUD predictions (default); "
                             "srp_phat: the robust smoother fitted to srp_phat's detections (aaute track's for it); "
                             "paper: the paper's RBF GP, lengthscale 300 x 10 ms, noise 2, outputscale 1; tuned: "
                             "Matern-5/2 GP learned on real MMAUD predictions")
    smooth.add_argument("--lag", type=float, help="robust only: causal (0) or fixed-lag (seconds) smoothing, "
                                                  "each output using data up to its time plus the lag")
    smooth.add_argument("--backend", default="auto", help="GP presets: auto | exact | statespace | local")
    smooth.add_argument("--fit", action="store_true", help="fit the hyperparameters to this track first")
    smooth.add_argument("--horizon", type=float, help="flag query times farther than this (s) from any data")
    smooth.add_argument("--overwrite", action="store_true", help="replace an existing DST (never SRC itself)")
    smooth.set_defaults(func=_cmd_smooth)
