"""Model profiler: parameters (total and used), GMACs / FLOPs, latency, throughput and front-end time.

``aaute profile [MODEL ...]`` (or ``python -m benchmarks.profiler``) prints one row per zoo model;
:func:`profile_model` returns the ``profile`` columns of the results schema (:data:`benchmarks.results.PROFILE`).

GMACs at batch 1, eval mode, each model's reference input shapes, and the used parameters come from
:mod:`benchmarks.flops` (the counting, its convention and its formulas).

Timing (:func:`profile_model`, ``torch.utils.benchmark.Timer.blocked_autorange``): median and
interquartile range of the per-call time over the measured blocks; the block-size estimation that
precedes them runs the call at least once, which is the warm-up. The IQR is reported only when at
least :data:`MIN_BLOCKS_FOR_IQR` blocks were measured: torch makes a block last tens of milliseconds
(10^4 times its timing overhead) or one call, so ``min_run_time`` 0.5 s gives an IQR for the light models,
a heavy model needs a ``min_run_time`` of several calls, and 0.05 s gives none (one block's IQR would
read 0). Latency is at batch 1 on 1 thread and on all cores; throughput (windows per second) at
``throughput_batch`` on the same two thread counts; the feature front-end and the end-to-end path (raw
window -> features -> position) per window on 1 thread. The front-end input is
a raw 2 s, 4-channel window at the simulator's 48 kHz for audio recipes and a raw camera frame of the
simulator's size (1280 x 720 RGB uint8) for image recipes. Each timed call runs at least twice (the
estimation and one measured block; more blocks until ``min_run_time`` is spent), so the cost is set by
the slowest call: AV-FDTI takes about 0.85 s per window on one core, about a minute per batch-64 call,
and about 6 GB of activations at batch 64 (its 512 x 512 heat-map decoder; 0.8 GB at batch 8). The defaults
(``min_run_time`` 0.5 s, batch 64) suit a careful run of light models; ``--min-run-time 0.05 --batch 4``
profiles all eight models in about a minute or two on 2 cores.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
from collections.abc import Callable, Mapping, Sequence
from functools import lru_cache
from typing import Any

import numpy as np
import pandas as pd
import torch
from torch import nn

from benchmarks.flops import forward_counts
from benchmarks.results import PROFILE
from datamodules.atomic import atomic_write
from datamodules.features import (
    image_features,
    image_recipe,
    mel_features,
    mel_recipe,
    phase_features,
    phase_recipe,
    scale_image,
)
from zoo.registry import get_model, list_models, model_class

log = logging.getLogger(__name__)

WINDOW_SECONDS = 2.0  #: raw audio per window for the front-end timing (MMAUDDataModule's default window)
MIN_BLOCKS_FOR_IQR = 4  #: fewer measured blocks give no meaningful interquartile range
TIMING_KEYS = ("latency_ms_1t", "latency_iqr_ms_1t", "latency_ms_all", "latency_iqr_ms_all", "threads_all",
               "throughput_batch", "throughput_1t", "throughput_all", "frontend_ms", "end_to_end_ms")


# ------------------------------------------------------------------------------------------ timing


def _measure(fn: Callable[[], Any], threads: int, min_run_time: float) -> tuple[float, float | None]:
    """Median and interquartile range (s) of ``fn()`` on ``threads`` threads (IQR None with few blocks)."""
    from torch.utils import benchmark  # imported here: its import is slow and only timing needs it

    timer = benchmark.Timer(stmt="fn()", globals={"fn": fn}, num_threads=threads)
    measurement = timer.blocked_autorange(min_run_time=min_run_time)  # its block-size estimate warms up
    iqr = measurement.iqr if len(measurement.times) >= MIN_BLOCKS_FOR_IQR else None
    return measurement.median, iqr


def _forward(net: nn.Module, inputs: dict[str, torch.Tensor]) -> Callable[[], Any]:
    def run() -> Any:
        with torch.no_grad():
            return net(inputs)

    return run


@lru_cache(maxsize=1)
def _simulator_defaults() -> tuple[float, tuple[int, int]]:
    """The simulator's audio sample rate (Hz) and camera frame size (height, width)."""
    from datamodules.simulate.acoustics import AudioConfig
    from datamodules.simulate.camera import CameraModel

    camera = CameraModel()
    return AudioConfig().sample_rate, (camera.height, camera.width)


def raw_inputs(net: nn.Module, seed: int = 0) -> dict[str, np.ndarray]:
    """Random raw inputs of one window: audio channels x samples (float32) and/or a camera frame H x W x 3 (uint8).

    Audio is a :data:`WINDOW_SECONDS` window at the simulator's sample rate with the net's channel
    count; the frame has the simulator's camera size.
    """
    sample_rate, (height, width) = _simulator_defaults()
    rng = np.random.default_rng(seed)
    raw: dict[str, np.ndarray] = {}
    for name in net.inputs:
        if name in ("audio_mel", "audio_phase"):
            samples = int(round(WINDOW_SECONDS * sample_rate))
            raw[name] = (0.1 * rng.standard_normal((net.in_channels, samples))).astype(np.float32)
        elif name == "image":
            raw[name] = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
        else:
            raise ValueError(f"{net.model_name}: no raw input is known for input {name!r} (recipe "
                             f"{net.inputs[name]!r}); expected 'audio_mel', 'audio_phase' or 'image'")
    return raw


def frontend(net: nn.Module, raw: Mapping[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """The net's feature recipes applied to raw inputs (audio at the simulator's rate): features without batch axis."""
    sample_rate = _simulator_defaults()[0]
    features: dict[str, torch.Tensor] = {}
    for name, recipe in net.inputs.items():
        if name == "audio_mel":
            features[name] = mel_features(raw[name], sample_rate, mel_recipe(recipe))
        elif name == "audio_phase":
            features[name] = phase_features(raw[name], sample_rate, phase_recipe(recipe))
        else:
            features[name] = scale_image(image_features(raw[name], image_recipe(recipe)))
    return features


def _end_to_end(net: nn.Module, raw: Mapping[str, np.ndarray]) -> Callable[[], torch.Tensor]:
    def run() -> torch.Tensor:
        with torch.no_grad():
            batch = {name: value[None] for name, value in frontend(net, raw).items()}
            return net(batch)["position"]

    return run


def _profile_inputs(net: nn.Module) -> str:
    return "; ".join(f"{name} {'x'.join(map(str, shape))}" for name, shape in net.input_shapes().items())


def _all_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def profile_model(name: str, *, min_run_time: float = 0.5, throughput_batch: int = 64,
                  all_threads: int | None = None, timing: bool = True) -> dict[str, Any]:
    """Profile one zoo model (random weights, eval mode): the ``profile`` columns of the results schema.

    Args:
        name: a registered model (:func:`zoo.registry.list_models`).
        min_run_time: seconds of measured calls per timing (after the warm-up estimate).
        throughput_batch: batch size of the throughput measurement (windows per second).
        all_threads: the "all cores" thread count (None: the cores this process may use).
        timing: False gives only the counts (fast); the timing columns are then None.

    Returns:
        A dict with exactly the keys of :data:`benchmarks.results.PROFILE`.
    """
    if min_run_time <= 0:
        raise ValueError(f"min_run_time must be positive seconds, got {min_run_time}")
    if throughput_batch < 1:
        raise ValueError(f"throughput_batch must be at least 1, got {throughput_batch}")
    if all_threads is not None and all_threads < 1:
        raise ValueError(f"all_threads must be at least 1, got {all_threads}")
    net = get_model(name).eval()
    inputs = net.example_inputs(1)
    macs, total, used = forward_counts(net, inputs)
    row: dict[str, Any] = {
        "params_total_M": total / 1e6, "params_used_M": used / 1e6, "gmacs": macs / 1e9, "gflops": 2 * macs / 1e9,
        "profile_inputs": _profile_inputs(net), **dict.fromkeys(TIMING_KEYS),
    }
    if not timing:
        return row
    threads_all = all_threads or _all_cores()
    previous = torch.get_num_threads()
    try:
        single, batch = _forward(net, inputs), _forward(net, net.example_inputs(throughput_batch))
        for suffix, threads in (("1t", 1), ("all", threads_all)):
            log.info("%s: latency and throughput on %d thread(s)", name, threads)
            median, iqr = _measure(single, threads, min_run_time)
            row[f"latency_ms_{suffix}"] = 1e3 * median
            row[f"latency_iqr_ms_{suffix}"] = None if iqr is None else 1e3 * iqr
            row[f"throughput_{suffix}"] = throughput_batch / _measure(batch, threads, min_run_time)[0]
        raw = raw_inputs(net)
        row["frontend_ms"] = 1e3 * _measure(lambda: frontend(net, raw), 1, min_run_time)[0]
        row["end_to_end_ms"] = 1e3 * _measure(_end_to_end(net, raw), 1, min_run_time)[0]
        row["threads_all"] = threads_all
        row["throughput_batch"] = throughput_batch
    finally:
        torch.set_num_threads(previous)
    return row


# ------------------------------------------------------------------------------------------ table


def _number(value: Any, digits: int) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value:.{digits}f}"


def _latency(row: Mapping[str, Any], suffix: str) -> str:
    median = row.get(f"latency_ms_{suffix}")
    if median is None:
        return "-"
    return f"{median:.2f} [{_number(row.get(f'latency_iqr_ms_{suffix}'), 2)}]"


def _shared(rows: Sequence[Mapping[str, Any]], key: str) -> Any:
    """The value of ``key`` if all rows that have one agree on it, else None."""
    values = {row.get(key) for row in rows if row.get(key) is not None}
    return values.pop() if len(values) == 1 else None


def format_profile_table(rows: list[dict]) -> str:
    """An aligned text table of profile rows (each a ``model`` key plus the PROFILE columns), with a legend.

    Thread count and throughput batch go into the header when all rows share them, else into each cell.
    """
    threads, batch = _shared(rows, "threads_all"), _shared(rows, "throughput_batch")
    all_cores = f"{threads} thread{'s' if threads != 1 else ''}" if threads else "all cores"
    per_batch = f"win/s, batch {batch}" if batch else "win/s"
    header = [("", "model"), ("params total", "(M)"), ("params used", "(M)"), ("", "GMACs"),
              ("FLOPs (G,", "= 2 x MACs)"), ("latency 1 thread", "ms median [IQR]"),
              (f"latency {all_cores}", "ms median [IQR]"), ("throughput 1 thread", per_batch),
              (f"throughput {all_cores}", per_batch), ("front-end", "ms (1 thread)"),
              ("end-to-end", "ms (1 thread)")]
    body = []
    for row in rows:
        all_latency, throughput_all = _latency(row, "all"), _number(row.get("throughput_all"), 1)
        throughput_1t = _number(row.get("throughput_1t"), 1)
        if row.get("threads_all") is not None and not threads:  # the header cannot name them
            all_latency += f" ({row['threads_all']}t)"
            throughput_all += f" ({row['threads_all']}t)"
        if row.get("throughput_batch") is not None and not batch:
            throughput_1t += f" (b{row['throughput_batch']})"
            throughput_all += f" (b{row['throughput_batch']})"
        body.append([str(row.get("model", "?")), _number(row.get("params_total_M"), 3),
                     _number(row.get("params_used_M"), 3), _number(row.get("gmacs"), 4),
                     _number(row.get("gflops"), 4), _latency(row, "1t"), all_latency, throughput_1t,
                     throughput_all, _number(row.get("frontend_ms"), 2), _number(row.get("end_to_end_ms"), 2)])
    lines = [[top for top, _ in header], [bottom for _, bottom in header], *body]
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]

    def render(cells: list[str]) -> str:
        return "  ".join(cell.ljust(width) if i == 0 else cell.rjust(width)
                         for i, (cell, width) in enumerate(zip(cells, widths, strict=True))).rstrip()

    text = [render(line) for line in lines]
    text.insert(2, "  ".join("-" * width for width in widths))
    text.append("GMACs: multiply-accumulates of one forward pass at batch 1 (the \"GFLOPs\" of the papers), counted "
                "on the executed graph; element-wise ops not counted; transposed convolutions by output size.")
    return "\n".join(text)


# ------------------------------------------------------------------------------------------ CLI


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``aaute profile``."""
    parser.add_argument("models", nargs="*", metavar="MODEL", help="zoo models to profile (default: all)")
    parser.add_argument("--min-run-time", type=float, default=0.5, metavar="S",
                        help="seconds of measured calls per timing (default 0.5; 0.05 for a quick look)")
    parser.add_argument("--batch", type=int, default=64, metavar="N",
                        help="batch size of the throughput measurement (default 64; heavy models take about "
                             "a minute per batch-64 call on one core)")
    parser.add_argument("--threads", type=int, default=None, metavar="N",
                        help="thread count of the 'all cores' timings (default: the cores this process may use)")
    parser.add_argument("--no-timing", action="store_true", help="parameters and GMACs only (fast)")
    parser.add_argument("--csv", default=None, metavar="FILE", help="also write the rows to this CSV file")


def run(args: argparse.Namespace) -> int:
    """``aaute profile``: profile the models, print the table, optionally write the CSV."""
    names = list(args.models) or list_models()
    for name in names:
        model_class(name)  # unknown names fail here, before any work, with the known ones listed
    if args.min_run_time <= 0:
        raise ValueError(f"--min-run-time must be positive seconds, got {args.min_run_time}")
    if args.batch < 1:
        raise ValueError(f"--batch must be at least 1, got {args.batch}")
    if args.threads is not None and args.threads < 1:
        raise ValueError(f"--threads must be at least 1, got {args.threads}")
    rows = []
    for name in names:
        log.info("profiling %s", name)
        rows.append({"model": name, **profile_model(name, min_run_time=args.min_run_time,
                                                    throughput_batch=args.batch, all_threads=args.threads,
                                                    timing=not args.no_timing)})
    sys.stdout.write(format_profile_table(rows) + "\n")
    if args.csv:
        with atomic_write(args.csv) as tmp:
            pd.DataFrame(rows, columns=["model", *PROFILE]).to_csv(tmp, index=False)
        log.info("%d profile row(s) written to %s", len(rows), args.csv)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m benchmarks.profiler [MODEL ...] [options]``."""
    parser = argparse.ArgumentParser(prog="aaute profile", description=__doc__.splitlines()[0])
    add_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        return run(args)
    except ValueError as error:
        sys.stderr.write(f"aaute profile: {error}\n")
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
