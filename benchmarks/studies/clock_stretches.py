"""How well one stretch of audio calibrates the nodes' clocks: the estimates ``aaute track`` makes live.

Every recording on separate node clocks (``aaute simulate ... --clock-offset-range-ms 3
--clock-drift-range-ppm 20``) is cut into consecutive stretches of ``S`` seconds, stretch ``k`` from ``k S``
to ``(k + 1) S`` as the live tracker cuts its stream, and each stretch's clocks are estimated as the tracker
estimates them (:func:`zoo.deploy.live_clocks.estimate_stretch`). Each estimate's offsets at the stretch's
centre are compared with the truth there (the recording's ``clocks_truth``, read for evaluation only), node
by node relative to node 0, and its std (with the estimator's ``std_floor`` in quadrature, as the tracker's
line through the estimates takes it) with the error. Per ``S`` it prints the stretches calibrated and
refused (by the refusal's reason), the share of offsets more than 0.05 and 0.1 ms off, the median absolute
error, the share within 1 and 2 std and the median CPU per estimate (of the estimating thread; calibrated
and refused apart); then every offset more than 0.1 ms off.

Run: ``python -m benchmarks.studies.clock_stretches --data CLOCKS_DIR [CLOCKS_DIR ...] [--seconds 10 30]
[--workers 2] [--out CSV]``. One thread per worker (torch, BLAS and OpenMP).
"""

from __future__ import annotations

import argparse
import re
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from benchmarks.studies.common import true_clocks
from datamodules.features.clock_calibration import ClockCalibration, ClockCalibrationConfig, with_std_floor
from datamodules.formats import discover_recordings
from datamodules.formats.mcap_file import read_mcap
from datamodules.recording import RecordingError
from zoo.deploy.live_clocks import estimate_stretch, limit_to_one_thread

#: offsets off by more than these (ms) are counted
LIMITS_MS = (0.05, 0.1)


def stretch_errors(estimate: ClockCalibration, offsets: np.ndarray, drifts: np.ndarray, start: float,
                   seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """Per node, the error (s) of a stretch's estimate at its centre and the estimate's std with the floor.

    ``offsets`` (at the recording's first sample) and ``drifts`` (ppm) are the truth relative to node 0;
    the stretch starts ``start`` seconds into the recording and the estimate's times count from there."""
    truth = offsets + drifts * 1e-6 * (start + seconds / 2)
    std = with_std_floor(estimate.offsets_std_s, ClockCalibrationConfig().std_floor)
    return estimate.offsets_at(seconds / 2) - truth, std


def refusal_reason(error: Exception) -> str:
    """A refusal's kind: its message before the details, numbers left out."""
    return re.sub(r"[-+]?\d[\d.]*", "N", str(error).split(" (")[0].split(":")[0])


def recording_rows(path: Path, seconds: float) -> list[dict[str, Any]]:
    """One row per node of each calibrated stretch of ``path``, one per refused stretch."""
    limit_to_one_thread()  # as the tracker's worker runs
    recording = read_mcap(path)
    offsets, drifts = true_clocks(recording.meta)
    audio = recording.audio
    mics = np.asarray(audio.mic_positions, dtype=np.float64)
    rate = audio.sample_rate
    rows = []
    for k in range(int(audio.duration // seconds)):
        start = k * seconds
        result, _, cpu = estimate_stretch(audio.read(round(start * rate), round((start + seconds) * rate)), rate,
                                          mics)
        base = {"recording": path.stem, "drone": recording.drone, "seconds": seconds, "stretch": k, "cpu_s": cpu}
        if not isinstance(result, ClockCalibration):
            rows.append({**base, "status": "refused", "reason": refusal_reason(result)})
            continue
        error, std = stretch_errors(result, offsets, drifts, start, seconds)
        rows += [{**base, "status": "ok", "node": n, "error_ms": 1e3 * error[n], "std_ms": 1e3 * std[n],
                  "frames": result.frames} for n in range(1, offsets.size)]
    return rows


def summary(rows: pd.DataFrame) -> str:
    """Markdown: per stretch length, how many stretches were calibrated and how far their offsets are off."""
    lines = ["| S | stretches calibrated / refused | refused because | offsets > " +
             " / > ".join(f"{limit:g}" for limit in LIMITS_MS) + " ms off | median abs. error | within 1 / 2 std "
             "| CPU per estimate, median: calibrated / refused |", "|--:|--:|:--|--:|--:|--:|--:|"]
    for seconds, group in rows.groupby("seconds"):
        ok, refused = group[group.status == "ok"], group[group.status == "refused"]
        calibrated = ok[["recording", "stretch"]].drop_duplicates().shape[0]
        reasons = "; ".join(f"{reason}: {count}" for reason, count in refused.reason.value_counts().items()) or "-"
        error = ok.error_ms.abs()
        ratio = error / ok.std_ms
        cpu = group.drop_duplicates(["recording", "stretch"]).groupby("status").cpu_s.median()
        off = " / ".join(f"{(error > limit).mean():.1%}" for limit in LIMITS_MS) if len(ok) else "-"
        lines.append(f"| {seconds:g} s | {calibrated} / {len(refused)} | {reasons} | {off} | {error.median():.3f} ms | "
                     f"{(ratio <= 1).mean():.0%} / {(ratio <= 2).mean():.0%} | {cpu.get('ok', np.nan):.1f} / "
                     f"{cpu.get('refused', np.nan):.1f} s |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, nargs="+", required=True,
                        help="folders of recordings on separate node clocks (with clocks_truth)")
    parser.add_argument("--seconds", type=float, nargs="+", default=[10.0], help="stretch lengths S (s)")
    parser.add_argument("--workers", type=int, default=1, help="recordings estimated at once (one thread each)")
    parser.add_argument("--out", type=Path, help="write every row to this CSV")
    args = parser.parse_args(argv)
    try:
        paths = [path for folder in args.data for path in discover_recordings(folder)]
    except RecordingError as error:
        raise SystemExit(str(error)) from None
    jobs = [(path, seconds) for path in paths for seconds in args.seconds]
    with ProcessPoolExecutor(max_workers=max(args.workers, 1)) as pool:
        rows = pd.DataFrame([row for part in pool.map(recording_rows, *zip(*jobs, strict=True)) for row in part])
    if args.out is not None:
        rows.to_csv(args.out, index=False)
    print(summary(rows))
    off = rows[(rows.status == "ok") & (rows.error_ms.abs() > max(LIMITS_MS))] if "error_ms" in rows else rows.iloc[:0]
    if len(off):
        print(f"\nOffsets more than {max(LIMITS_MS):g} ms off:\n")
        off = off.astype({"node": int, "frames": int})[["recording", "drone", "seconds", "stretch", "node", "error_ms",
                                                         "std_ms", "frames"]]
        print(off.to_string(index=False, float_format=lambda v: f"{v:.3f}"))


if __name__ == "__main__":
    main()
