"""Does self-calibration of the nodes' clocks work on held-out flights: offset error, uncertainty, ``srp_phat`` E.

Each condition is a pair of folders holding the same flights (same simulator seed and settings): one
recorded on one shared clock, one with separate node clocks (``aaute simulate ... --clock-offset-range-ms 3
--clock-drift-range-ppm 20``: the nodes' clocks are the only difference, the truth is in each recording's
``clocks_truth``, read here for evaluation only). For every recording on separate clocks the offsets are
estimated from its audio (:func:`~datamodules.features.clock_calibration.estimate_clock_offsets` with the
settings the DataModule uses) and compared with the truth, node by node relative to node 0: the error at
the first sample and the largest error over the recording (offset and drift together); the estimate's
uncertainty is set against the actual error. Then ``srp_phat`` (``configs/model/srp_phat.yaml``, recipe
``gcc_phat_2s_static``, the path of ``aaute test``) gives its E on the shared clock, on the separate clocks
uncalibrated (``clock_calibration: off``) and self-calibrated (``auto``: what a recording that says
``nodes_share_clock: false`` gets by default).

Run: ``python -m benchmarks.studies.clock_calibration --condition default SHARED_DIR CLOCKS_DIR
[--condition quiet SHARED_DIR CLOCKS_DIR] [--out PREFIX]``; prints Markdown tables, writes ``PREFIX_E.csv``
and ``PREFIX_offsets.csv``. One torch thread.
"""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from benchmarks.studies.common import recordings_module, srp_phat_errors, true_clocks
from datamodules.atomic import atomic_write
from datamodules.features.clock_calibration import (
    ClockCalibration,
    ClockCalibrationConfig,
    ClockCalibrationError,
    estimate_clock_offsets,
)
from datamodules.formats import discover_recordings
from datamodules.formats.mcap_file import read_mcap

log = logging.getLogger(__name__)

RECIPE = "gcc_phat_2s_static"
TARGET_S = 5e-5  #: the target: offsets within 0.05 ms of the truth
GRID = 121  #: times over the recording at which the offset error is taken


def offset_errors(estimate: ClockCalibration, offsets: np.ndarray, drifts: np.ndarray,
                  duration: float) -> tuple[np.ndarray, np.ndarray]:
    """Per node, the estimate's error (s) at the first sample and its largest absolute error over the recording."""
    times = np.linspace(0.0, duration, GRID)
    error = estimate.offsets_at(times) - (offsets + drifts * 1e-6 * times[:, None])
    return error[0], np.abs(error).max(axis=0)


def calibrate(folder: Path) -> list[dict[str, Any]]:
    """One row per recording and node (1 ..) in ``folder``: truth, estimate, uncertainty, errors, time."""
    rows = []
    for path in discover_recordings(folder):
        recording = read_mcap(path)
        offsets, drifts = true_clocks(recording.meta)
        base = {"recording": path.stem, "drone": recording.drone}
        start = time.perf_counter()
        try:
            estimate = estimate_clock_offsets(recording.audio, ClockCalibrationConfig())
        except ClockCalibrationError as error:
            seconds = time.perf_counter() - start
            log.warning("%s: %s", path, error)
            rows += [{**base, "node": n, "true_ms": 1e3 * offsets[n], "status": f"failed: {error}",
                      "seconds": seconds} for n in range(1, offsets.size)]
            continue
        seconds = time.perf_counter() - start
        log.warning("%s (%s, %.1f s): %s", path.stem, recording.drone, seconds, estimate.summary())
        first, worst = offset_errors(estimate, offsets, drifts, recording.audio.duration)
        rows += [{**base, "node": n, "true_ms": 1e3 * offsets[n], "estimate_ms": 1e3 * estimate.offsets_s[n],
                  "std_ms": 1e3 * estimate.offsets_std_s[n], "true_drift_ppm": drifts[n],
                  "drift_ppm": estimate.drifts_ppm[n], "error0_ms": 1e3 * first[n], "max_error_ms": 1e3 * worst[n],
                  "frames": estimate.frames, "status": "ok", "seconds": seconds} for n in range(1, offsets.size)]
    return rows


def error_table(offsets: pd.DataFrame) -> str:
    """Markdown: per condition, the distribution of the offset errors and the uncertainty against them."""
    lines = ["| condition | nodes x flights | calibrated | abs. error at start: median / 90 % / max | "
             "largest error over the flight: median / max | within 0.05 ms | abs. error / std: median | "
             "within 1 / 2 std |", "|:--|--:|--:|--:|--:|--:|--:|--:|"]
    for condition, group in offsets.groupby("condition", sort=False):
        ok = group[group.status == "ok"]
        first, worst = ok.error0_ms.abs(), ok.max_error_ms
        ratio = first / ok.std_ms
        lines.append(f"| {condition} | {len(group)} | {len(ok)} | {first.median():.3f} / {first.quantile(0.9):.3f} / "
                     f"{first.max():.3f} ms | {worst.median():.3f} / {worst.max():.3f} ms | "
                     f"{(worst <= 1e3 * TARGET_S).sum()} of {len(group)} | {ratio.median():.2f} | "
                     f"{(ratio <= 1).mean():.0%} / {(ratio <= 2).mean():.0%} |")
    return "\n".join(lines)


def flight_table(offsets: pd.DataFrame) -> str:
    """Markdown: per condition and flight, each node's error at the start +- its std, or why it failed."""
    lines = ["| condition | flight | drone | error at start +- std, nodes 1 / 2 / 3 (ms) | largest error (ms) | s |",
             "|:--|:--|:--|:--|--:|--:|"]
    for (condition, recording), group in offsets.groupby(["condition", "recording"], sort=False):
        drone, seconds = group.drone.iloc[0], group.seconds.iloc[0]
        if (group.status != "ok").any():
            lines.append(f"| {condition} | {recording} | {drone} | {group.status.iloc[0]} | - | {seconds:.1f} |")
            continue
        cells = " / ".join(f"{e:+.3f} +- {s:.3f}" for e, s in zip(group.error0_ms, group.std_ms, strict=True))
        lines.append(f"| {condition} | {recording} | {drone} | {cells} | {group.max_error_ms.max():.3f} | "
                     f"{seconds:.1f} |")
    return "\n".join(lines)


def e_table(errors: pd.DataFrame) -> str:
    """Markdown: srp_phat E per condition: shared clock, uncalibrated, self-calibrated, their ratio, and the same
    on the flights the calibration corrected."""
    lines = ["| condition | E shared clock | E separate clocks, uncalibrated | E separate clocks, self-calibrated | "
             "calibrated vs shared | flights corrected | on those: E shared / calibrated |",
             "|:--|--:|--:|--:|--:|--:|--:|"]
    for condition, row in errors.iterrows():
        lines.append(f"| {condition} | {row.shared:.2f} m | {row.uncalibrated:.2f} m | {row.calibrated:.2f} m | "
                     f"{row.calibrated / row.shared - 1:+.0%} | {row.corrected:.0f} of {row.recordings:.0f} | "
                     f"{row.shared_corrected:.2f} / {row.calibrated_corrected:.2f} m "
                     f"({row.calibrated_corrected / row.shared_corrected - 1:+.0%}) |")
    return "\n".join(lines)


def flight_e_table(flights: pd.DataFrame) -> str:
    """Markdown: srp_phat E per flight on each clock setting, and whether the calibration corrected it."""
    lines = ["| condition | flight | drone | E shared | E uncalibrated | E self-calibrated | corrected |",
             "|:--|:--|:--|--:|--:|--:|:--|"]
    lines += [f"| {r.condition} | {r.recording} | {r.drone} | {r.shared:.2f} m | {r.uncalibrated:.2f} m | "
              f"{r.calibrated:.2f} m | {'yes' if r.corrected else 'no'} |" for r in flights.itertuples()]
    return "\n".join(lines)


def condition_errors(name: str, shared: Path, clocks: Path, cache: Path, template: torch.nn.Module | None
                     ) -> tuple[dict[str, Any], list[dict[str, Any]], torch.nn.Module]:
    """srp_phat's E of one condition (overall and on the corrected flights), per flight, and the prepared net."""
    per, corrected = {}, set()
    for column, folder, mode in (("shared", shared, "off"), ("uncalibrated", clocks, "off"),
                                 ("calibrated", clocks, "auto")):
        module = recordings_module([folder], RECIPE, cache, clock_calibration=mode)
        per[column], template = srp_phat_errors(module, template)
        log.warning("%s, %s: E %.2f m", name, column, np.concatenate(list(per[column].values())).mean())
        if mode == "auto":  # what the DataModule did: corrected, or left as it was (and why)
            corrected = {Path(p).stem for p, v in module.clock_estimates.items() if isinstance(v, ClockCalibration)}
            drones = {sequence.path.stem: sequence.drone for sequence in module.sequences["test"]}
    row: dict[str, Any] = {"condition": name, "corrected": len(corrected), "recordings": len(per["calibrated"])}
    for column, errors in per.items():
        row[column] = float(np.concatenate(list(errors.values())).mean())
        row[f"{column}_corrected"] = float(np.concatenate([errors[s] for s in sorted(corrected)]).mean()) \
            if corrected else float("nan")
    flights = [{"condition": name, "recording": stem, "drone": drones.get(stem, "-"),
                **{column: float(per[column][stem].mean()) for column in per}, "corrected": stem in corrected}
               for stem in sorted(per["calibrated"])]
    return row, flights, template


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--condition", nargs=3, action="append", required=True,
                        metavar=("NAME", "SHARED_DIR", "CLOCKS_DIR"),
                        help="a condition: the flights on one shared clock and the same flights on separate clocks")
    parser.add_argument("--out", type=Path, help="write PREFIX_E.csv and PREFIX_offsets.csv")
    parser.add_argument("--cache", type=Path, help="feature cache (default: a temporary folder)")
    parser.add_argument("--no-srp", action="store_true", help="only the offsets, no srp_phat E")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(1)
    begin = time.perf_counter()
    offsets, errors, flights, template = [], [], [], None
    with tempfile.TemporaryDirectory() as tmp:
        cache = args.cache or Path(tmp) / "cache"
        for name, shared, clocks in args.condition:
            offsets += [{"condition": name, **row} for row in calibrate(Path(clocks))]
            if args.no_srp:
                continue
            row, per_flight, template = condition_errors(name, Path(shared), Path(clocks), cache, template)
            errors.append(row)
            flights += per_flight
    offsets_frame = pd.DataFrame(offsets)
    print(error_table(offsets_frame), flight_table(offsets_frame), sep="\n\n")
    if errors:
        print("\n" + e_table(pd.DataFrame(errors).set_index("condition")), flight_e_table(pd.DataFrame(flights)),
              sep="\n\n")
    print(f"\n1 torch thread, load average {os.getloadavg()[0]:.2f} at the end, "
          f"{(time.perf_counter() - begin) / 60:.1f} min")
    if args.out is not None:
        with atomic_write(args.out.with_name(args.out.name + "_offsets.csv")) as path:
            offsets_frame.to_csv(path, index=False)
        if errors:
            with atomic_write(args.out.with_name(args.out.name + "_E.csv")) as path:
                pd.DataFrame(errors).to_csv(path, index=False)
            with atomic_write(args.out.with_name(args.out.name + "_flights.csv")) as path:
                pd.DataFrame(flights).to_csv(path, index=False)


if __name__ == "__main__":
    main()
