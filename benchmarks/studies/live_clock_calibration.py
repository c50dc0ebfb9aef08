"""Live self-calibration of the nodes' clocks (``aaute track --clock-seconds S``): its offset error, the E after
it, and what the estimate costs the stream.

Each condition is a pair of folders holding the same flights, one on a shared clock and one with separate node
clocks (as for :mod:`benchmarks.studies.clock_calibration`; the truth, ``clocks_truth``, is read for evaluation
only). Every flight is tracked live with ``srp_phat`` (``configs/model/srp_phat.yaml``, batch 1, in stream
order, as ``aaute track`` does): on the shared clock, on separate clocks without calibration, and on separate
clocks calibrated from the first ``S`` seconds of the stream for each ``--clock-seconds S``. These runs wait for
the estimate (:class:`~zoo.deploy.live_clocks.CalibratingPhase` without ``background``), so the correction starts
exactly at ``S`` whatever the machine's load. Per flight and ``S`` it reports the offsets' error against the
truth over the rest of the flight (node by node against node 0: at ``S`` and the largest after it) with the
estimate's std, and the E (mean 3D error, m) of the raw localiser output and of the causal smoother on the rows
after the correction began, on each clock setting over the same rows, and of the raw output from 10 s after it
(``srp_phat`` holds a detection for up to 10 s: none from before the first correction, whose rows are
``uncorrected``, but a later estimate's correction still shows detections made with the earlier ones), and the
share of those rows in which ``srp_phat`` detected the drone (a clock error of a few hundredths of a millisecond
already lowers its steered response; rows without a detection hold the last one or fall back).

The cost: the estimate's CPU seconds, and what a stream paced at real time would see around it.
A replay gives each update's compute (block arrival to row); queueing those updates behind blocks that arrive
every 0.1 s gives the latency of each row from its block's arrival when the estimate holds up the stream.
``--paced`` also runs the calibrated flights of the first condition paced at real time with the estimate in the
background (a worker process, the default of ``aaute track``), and reports the latency from each block's due
time to its row and how many seconds of stream pass before the correction starts.

Run: ``python -m benchmarks.studies.live_clock_calibration --condition default SHARED_DIR CLOCKS_DIR
[--condition quiet SHARED_DIR CLOCKS_DIR] [--clock-seconds 10 30] [--paced] [--out PREFIX]``. One torch thread.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from benchmarks.studies.common import SRP_PHAT_CONFIG, true_clocks
from datamodules.atomic import atomic_write
from datamodules.formats import discover_recordings, open_recording
from datamodules.streams import RecordingSource

log = logging.getLogger(__name__)

HOP = 0.1  #: seconds between rows (``aaute track``'s block)
STALLED = 0.5  #: a row this many seconds after its block's arrival counts as held up
SETTLE = 10.0  #: seconds after the first correction from which E is also given (``srp_phat``'s hold: 10 s)


@dataclass
class LiveRun:
    """One live run: rows (time, raw xyz, smoothed xyz), each update's latency (s), the calibration if any, and
    which rows ``srp_phat`` detected the drone in (the others hold its last detection or fall back)."""

    times: np.ndarray
    raw: np.ndarray
    smooth: np.ndarray
    latencies: np.ndarray
    lateness: np.ndarray = field(default_factory=lambda: np.zeros(0))  #: paced: each block's delivery after its due
    front: Any = None
    detected: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))


class _Rows:
    def __init__(self):
        self.rows: list = []

    def write(self, row) -> None:
        self.rows.append(row)


class _PacedSource(RecordingSource):
    """A recording delivered at real time that also notes how late after its due time each block was handed on."""

    def blocks(self, size: int):
        self.lateness: list[float] = []
        start_wall = time.perf_counter()
        for start in range(0, self.audio.num_samples - size + 1, size):
            due = start_wall + (start + size) / self.sample_rate
            if due > time.perf_counter():
                time.sleep(due - time.perf_counter())
            self.lateness.append(time.perf_counter() - due)
            yield self.audio.read(start, start + size)
        self.leftover = self.audio.num_samples % size


def track(path: Path, clock_seconds: float, background: bool = False, paced: bool = False,
          config: Path = SRP_PHAT_CONFIG, follow: bool = True) -> LiveRun:
    """Track ``path`` live (see the module docstring)."""
    from zoo.deploy.live_phase import CalibratingPhase, PhaseTracker, load_phase_model

    source = _PacedSource(path) if paced else RecordingSource(path)
    model = load_phase_model(config=config, source=source)
    keep = _Rows()
    tracker = PhaseTracker(model, source, [keep], preset=model.live_smoother.get("preset", "robust"),
                           clock_seconds=clock_seconds, clock_follow=follow)
    if isinstance(tracker.front, CalibratingPhase):
        tracker.front.background = background
    report = tracker.run()
    rows = sorted(keep.rows, key=lambda r: r.timestamp)
    if len(rows) != len(report.latencies):
        raise RuntimeError(f"{path}: {len(rows)} rows but {len(report.latencies)} updates (a skipped window?)")
    lateness = np.asarray(getattr(source, "lateness", []), dtype=np.float64)
    return LiveRun(np.array([r.timestamp for r in rows]), np.array([r.raw for r in rows]),
                   np.array([r.mean for r in rows]), np.asarray(report.latencies), lateness, tracker.front,
                   np.array([r.detected for r in rows], dtype=bool))


def queued_latency(compute: np.ndarray, hop: float = HOP) -> np.ndarray:
    """Latency (s) of each update from its block's arrival when blocks arrive every ``hop`` seconds and each
    update takes ``compute`` seconds, one at a time in order (a late update delays those behind it)."""
    finish, out = -np.inf, np.empty(compute.size)
    for k, c in enumerate(compute):
        arrival = k * hop
        finish = max(finish, arrival) + c
        out[k] = finish - arrival
    return out


def errors(run: LiveRun, truth_times: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row: whether ground truth covers it, the raw and smoothed 3D errors (m)."""
    inside = (run.times >= truth_times[0]) & (run.times <= truth_times[-1])
    gt = np.stack([np.interp(run.times, truth_times, truth[:, a]) for a in range(3)], axis=1)
    return inside, np.linalg.norm(run.raw - gt, axis=1), np.linalg.norm(run.smooth - gt, axis=1)


def corrected_offsets(front: Any, times: np.ndarray) -> np.ndarray:
    """The offsets (times x nodes) ``front`` corrected the frames by at each of ``times`` (stream seconds from
    its first correction on): each correction of its ``history`` from the second it started."""
    starts = np.array([start for start, _ in front.history])
    index = np.clip(np.searchsorted(starts, times, side="right") - 1, 0, None)
    return np.stack([front.history[i][1].offsets_at(t) for i, t in zip(index, times, strict=True)])


def offset_rows(front: Any, offsets: np.ndarray, drifts: np.ndarray, start: float, duration: float,
                once: Any = None) -> list[dict[str, Any]]:
    """Per node (1 ..): the first estimate's error against the truth at ``start`` s of the stream and its std,
    the largest absolute error of the corrections in effect from there to ``duration`` (ms), and the same
    for ``once`` (a run that estimated only from the first stretch) when given."""
    first = front.history[0][1]
    grid = np.linspace(start, duration, 61)
    truth = offsets + drifts * 1e-6 * grid[:, None]
    error = corrected_offsets(front, grid) - truth
    once_error = corrected_offsets(once, grid) - truth if once is not None and once.history else None
    return [{"node": n, "error_ms": 1e3 * error[0, n], "max_error_ms": 1e3 * np.abs(error[:, n]).max(),
             "max_error_once_ms": 1e3 * np.abs(once_error[:, n]).max() if once_error is not None else np.nan,
             "std_ms": 1e3 * first.offsets_std_s[n], "drift_error_ppm": front.calibration.drifts_ppm[n] - drifts[n],
             "estimates": len(front.estimates)}
            for n in range(1, offsets.size)]


def flight(name: str, shared: Path, clocks: Path, seconds: list[float]) -> tuple[list[dict], list[dict]]:
    """One flight's rows of the E table (one per ``S``) and of the offset table (one per ``S`` and node)."""
    recording = open_recording(clocks)
    offsets, drifts = true_clocks(recording.meta)
    gt, t0 = recording.ground_truth, float(recording.audio.t0)
    base = {"condition": name, "recording": clocks.stem, "drone": recording.drone}
    runs = {"shared": track(shared, 0.0), "uncalibrated": track(clocks, 0.0)}
    e_rows, o_rows = [], []
    for s in seconds:
        live, once = track(clocks, s), track(clocks, s, follow=False)
        front = live.front
        row: dict[str, Any] = {**base, "clock_seconds": s, "estimate_cpu_s": front.estimate_cpu_seconds,
                               "estimate_wall_s": front.estimate_seconds}
        compute = live.latencies
        queued = queued_latency(compute)
        around = np.abs(live.times - t0 - s) <= 0.05 + 1e-9
        row.update(compute_median_ms=1e3 * float(np.median(compute)), worst_queued_s=float(queued.max()),
                   stalled_s=HOP * float((queued > STALLED).sum()), update_at_s_ms=1e3 * float(compute[around].max()))
        stream = errors(live, gt.timestamps, gt.xyz)[0] & (live.times - t0 >= s)  # every row from S on
        for column, other in (("calibrated", live), ("once", once), *runs.items()):
            row[f"E_stream_{column}"] = float(errors(other, gt.timestamps, gt.xyz)[1][stream].mean())
        row["stream_rows"] = int(stream.sum())
        if front.calibration is None:
            row["status"] = "refused"
            e_rows.append(row)
            log.warning("%s %s S=%g: calibration refused", name, clocks.stem, s)
            continue
        row["status"], row["once_calibrated"] = "ok", once.front.calibration is not None
        o_rows += [{**base, "clock_seconds": s, **r}
                   for r in offset_rows(front, offsets, drifts, front.calibrated_at, recording.audio.duration,
                                        once.front)]
        after = live.times - t0 >= front.calibrated_at
        for column, other in (("calibrated", live), ("once", once), *runs.items()):
            if not np.array_equal(other.times, live.times):
                raise RuntimeError(f"{clocks.stem}: the runs' rows are at different times")
            inside, raw, smooth = errors(other, gt.timestamps, gt.xyz)
            keep = inside & after
            settled = keep & (live.times - t0 >= front.calibrated_at + SETTLE)
            for key, values, rows in (("E_raw", raw, keep), ("E_smooth", smooth, keep), ("E_settled", raw, settled),
                                      ("detected", other.detected, keep)):  # none after a correction at the end
                row[f"{key}_{column}"] = float(values[rows].mean()) if rows.any() else float("nan")
        row["rows"] = int((after & errors(live, gt.timestamps, gt.xyz)[0]).sum())
        e_rows.append(row)
        log.warning("%s %s S=%g: E raw shared %.2f / uncalibrated %.2f / calibrated %.2f m; estimate %.1f s CPU",
                    name, clocks.stem, s, row["E_raw_shared"], row["E_raw_uncalibrated"], row["E_raw_calibrated"],
                    row["estimate_cpu_s"])
    return e_rows, o_rows


def paced(name: str, clocks: Path, seconds: float) -> dict[str, Any]:
    """One flight tracked at real time with the estimate in the background: latency from each block's due time
    to its row around the estimate, and when the correction started."""
    live = track(clocks, seconds, background=True, paced=True)
    front, times = live.front, live.times - float(open_recording(clocks).audio.t0)
    late = live.lateness[-live.latencies.size:] if live.lateness.size >= live.latencies.size else 0.0
    latency = live.latencies + late  # from the due time: waiting to be read, then the update
    during = (times >= seconds) & (times <= seconds + (front.estimate_seconds or 0.0))
    outside = ~during & (times >= seconds - 10)
    return {"condition": name, "recording": clocks.stem, "clock_seconds": seconds,
            "estimate_wall_s": front.estimate_seconds, "estimate_cpu_s": front.estimate_cpu_seconds,
            "corrected_from_s": front.calibrated_at, "status": "ok" if front.calibration is not None else "refused",
            "latency_during_median_ms": 1e3 * float(np.median(latency[during])) if during.any() else np.nan,
            "latency_during_max_ms": 1e3 * float(latency[during].max()) if during.any() else np.nan,
            "latency_other_median_ms": 1e3 * float(np.median(latency[outside])),
            "latency_max_ms": 1e3 * float(latency.max())}


def markdown(frame: pd.DataFrame, columns: dict[str, str]) -> str:
    """A Markdown table of ``frame``'s ``columns`` (name: format)."""
    lines = ["| " + " | ".join(columns) + " |", "|" + "--:|" * len(columns)]
    for row in frame.itertuples():
        cells = []
        for column, fmt in columns.items():
            value = getattr(row, column, np.nan)
            cells.append(format(value, fmt) if isinstance(value, int | float) and fmt else str(value))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def summary(e_frame: pd.DataFrame, o_frame: pd.DataFrame) -> str:
    """Pooled per condition and ``S``: flights calibrated, E (raw) on the rows after it on each clock setting
    (over the calibrated flights) and the share of those rows ``srp_phat`` detected the drone in, offset errors and
    their std, E (raw) over every row from ``S`` on of every flight, calibrated or not (what a stricter or looser
    refusal trades), estimate CPU and the queued stall."""
    lines = ["| condition | S | calibrated: once / followed | E shared / uncalibrated / once / followed (raw, m) | "
             "smoothed (m) | raw, from S + 10 s (m) | rows detected: shared / once / followed | "
             "offset error at S: median / max (ms) | largest after S: once / followed (ms) | within 1 / 2 std | "
             "every flight from S: shared / uncalibrated / once / followed (raw, m) | "
             "estimate CPU (s) | worst queued latency (s) |", "|:--|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|"]
    for (condition, s), group in e_frame.groupby(["condition", "clock_seconds"], sort=False):
        ok = group[group.status == "ok"]
        nodes = o_frame[(o_frame.condition == condition) & (o_frame.clock_seconds == s)] if len(o_frame) else o_frame
        w = ok.rows.to_numpy(dtype=float) if len(ok) else np.zeros(0)

        def pooled(column: str, ok: pd.DataFrame = ok, w: np.ndarray = w) -> float:
            values = ok[column].to_numpy(dtype=float)
            keep = (w > 0) & np.isfinite(values)  # a flight calibrated at its very end has no rows after it
            return float(np.average(values[keep], weights=w[keep])) if keep.any() else float("nan")

        every = group.stream_rows.to_numpy(dtype=float)
        stream = " / ".join(f"{np.average(group[f'E_stream_{c}'].to_numpy(dtype=float), weights=every):.2f}"
                            for c in ("shared", "uncalibrated", "once", "calibrated"))
        if len(nodes):
            z = (nodes.error_ms / nodes.std_ms).abs()
            offsets = (f"{nodes.error_ms.abs().median():.3f} / {nodes.error_ms.abs().max():.3f} | "
                       f"{nodes.max_error_once_ms.max():.3f} / {nodes.max_error_ms.max():.3f} | "
                       f"{(z <= 1).mean():.0%} / {(z <= 2).mean():.0%}")
        else:
            offsets = "- | - | -"
        once = int(ok.once_calibrated.sum()) if len(ok) else 0
        lines.append(f"| {condition} | {s:g} | {once} / {len(ok)} of {len(group)} | {pooled('E_raw_shared'):.2f} / "
                     f"{pooled('E_raw_uncalibrated'):.2f} / {pooled('E_raw_once'):.2f} / "
                     f"{pooled('E_raw_calibrated'):.2f} | "
                     f"{pooled('E_smooth_shared'):.2f} / {pooled('E_smooth_uncalibrated'):.2f} / "
                     f"{pooled('E_smooth_once'):.2f} / {pooled('E_smooth_calibrated'):.2f} | "
                     f"{pooled('E_settled_shared'):.2f} / {pooled('E_settled_uncalibrated'):.2f} / "
                     f"{pooled('E_settled_once'):.2f} / {pooled('E_settled_calibrated'):.2f} | "
                     f"{pooled('detected_shared'):.0%} / {pooled('detected_once'):.0%} / "
                     f"{pooled('detected_calibrated'):.0%} | {offsets} | {stream} | "
                     f"{group.estimate_cpu_s.median():.1f} ({group.estimate_cpu_s.min():.1f}-"
                     f"{group.estimate_cpu_s.max():.1f}) | {group.worst_queued_s.max():.1f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--condition", nargs=3, action="append", required=True,
                        metavar=("NAME", "SHARED_DIR", "CLOCKS_DIR"),
                        help="a condition: the flights on one shared clock and the same flights on separate clocks")
    parser.add_argument("--clock-seconds", type=float, nargs="+", default=[10.0, 30.0])
    parser.add_argument("--paced", type=float, nargs="*", default=[], metavar="S",
                        help="also track the first condition's flights paced at real time, estimating in the "
                             "background from the first S seconds")
    parser.add_argument("--no-replay", action="store_true", help="only the paced runs")
    parser.add_argument("--out", type=Path, help="write PREFIX_live_E.csv, PREFIX_live_offsets.csv (and _paced)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    for notices in ("zoo.deploy.live_phase", "zoo.deploy.live_clocks"):  # the per-run notices; the tables say it
        logging.getLogger(notices).setLevel(logging.ERROR)
    logging.getLogger("datamodules.formats.node_audio").setLevel(logging.ERROR)
    torch.set_num_threads(1)
    begin = time.perf_counter()
    e_rows, o_rows, paced_rows = [], [], []
    for name, shared, clocks in [] if args.no_replay else args.condition:
        for path in discover_recordings(Path(clocks)):
            e, o = flight(name, Path(shared) / path.name, path, args.clock_seconds)
            e_rows += e
            o_rows += o
    e_frame, o_frame = pd.DataFrame(e_rows), pd.DataFrame(o_rows)
    if len(e_frame):
        print(summary(e_frame, o_frame), "", sep="\n")
        print(markdown(e_frame, {"condition": "", "recording": "", "drone": "", "clock_seconds": "g", "status": "",
                             "E_raw_shared": ".2f", "E_raw_uncalibrated": ".2f", "E_raw_once": ".2f",
                             "E_raw_calibrated": ".2f",
                             "E_smooth_shared": ".2f", "E_smooth_calibrated": ".2f", "E_settled_shared": ".2f",
                             "E_settled_calibrated": ".2f", "detected_once": ".2f", "detected_calibrated": ".2f",
                             "estimate_cpu_s": ".1f",
                             "compute_median_ms": ".1f", "update_at_s_ms": ".0f", "worst_queued_s": ".1f",
                             "stalled_s": ".1f"}), "", sep="\n")
    if len(o_frame):
        print(markdown(o_frame, {"condition": "", "recording": "", "clock_seconds": "g", "node": "d",
                                 "error_ms": "+.3f", "std_ms": ".3f", "max_error_once_ms": ".3f",
                                 "max_error_ms": ".3f", "estimates": "d",
                                 "drift_error_ppm": "+.1f"}), "", sep="\n")
    if args.paced:
        name, _, clocks = args.condition[0]
        paced_rows = [paced(name, path, s) for s in args.paced for path in discover_recordings(Path(clocks))]
        print(markdown(pd.DataFrame(paced_rows), {
            "condition": "", "recording": "", "clock_seconds": "g", "status": "", "estimate_wall_s": ".1f",
            "estimate_cpu_s": ".1f", "corrected_from_s": ".1f", "latency_during_median_ms": ".1f",
            "latency_during_max_ms": ".1f", "latency_other_median_ms": ".1f", "latency_max_ms": ".1f"}), "", sep="\n")
    print(f"1 torch thread, load average {os.getloadavg()[0]:.2f} at the end, "
          f"{(time.perf_counter() - begin) / 60:.1f} min")
    if args.out is not None:
        for suffix, frame in (("live_E", e_frame), ("live_offsets", o_frame), ("live_paced", pd.DataFrame(paced_rows))):
            if len(frame):
                with atomic_write(args.out.with_name(f"{args.out.name}_{suffix}.csv")) as path:
                    frame.to_csv(path, index=False)


if __name__ == "__main__":
    main()
