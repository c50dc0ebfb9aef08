"""Measure ``srp_phat`` on recordings: errors against ground truth, detections, speed.

Every recording given is a test flight: the DataModule builds its windows (at the 10 Hz label
times, the last ``window_seconds`` of audio each) and their phase features through the feature
cache, as ``aaute test`` does, and the net sees them in time order with their ``sequence``, ``time``
and ``mic_positions`` entries. Ground truth is used only for scoring. Printed: E (mean 3D error over
the windows with ground truth), the detected share, E where detected, E by range from the rig
(0-10, 10-20, 20-40 m) and by drone, the constant baseline (for each flight, the mean ground truth
of the other flights), the feature cache per window and the net's windows/s on the torch threads set.

Run: ``python -m benchmarks.studies.phase_bench --data DIR [DIR ...] [--net-kwargs '{"frames": ...}']``.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.studies.common import recordings_module
from datamodules.atomic import atomic_write
from datamodules.features import phase_recipe
from zoo.registry import get_model
from zoo.smoothing import make_smoother, smooth_detected

RANGE_BINS = ((0.0, 10.0), (10.0, 20.0), (20.0, 40.0))  #: m from the rig origin


def constant_errors(gt: np.ndarray, flight: np.ndarray) -> np.ndarray:
    """Per window: the error of predicting the mean ground truth of the other flights."""
    errors = np.empty(len(gt))
    for name in np.unique(flight):
        mine = flight == name
        others = gt[~mine] if (~mine).any() else gt[mine]
        errors[mine] = np.linalg.norm(gt[mine] - others.mean(axis=0), axis=1)
    return errors


def summarise(position: np.ndarray, gt: np.ndarray, detected: np.ndarray, drone: np.ndarray,
              flight: np.ndarray) -> dict[str, float]:
    """The table's numbers from per-window predictions and ground truth (windows with ground truth only)."""
    error = np.linalg.norm(position - gt, axis=1)
    distance = np.linalg.norm(gt, axis=1)
    result = {"windows": float(len(error)), "E": float(error.mean()), "detected": float(detected.mean()),
              "E_detected": float(error[detected].mean()) if detected.any() else float("nan"),
              "E_undetected": float(error[~detected].mean()) if (~detected).any() else float("nan"),
              "constant_E": float(constant_errors(gt, flight).mean())}
    for lo, hi in RANGE_BINS:
        inside = (distance >= lo) & (distance < hi)
        result[f"E_{lo:g}-{hi:g}m"] = float(error[inside].mean()) if inside.any() else float("nan")
        result[f"share_{lo:g}-{hi:g}m"] = float(inside.mean())
    for name in sorted(set(drone)):
        mine = drone == name
        result[f"E_{name}"] = float(error[mine].mean())
        result[f"detected_{name}"] = float(detected[mine].mean())
    return result


def smooth_flights(arrays: dict[str, np.ndarray], smoother: dict) -> np.ndarray:
    """Per flight, the smoother's track of its detected windows at every window, as ``aaute test``
    smooths a net that reports detections (:func:`zoo.smoothing.smooth_detected`)."""
    smoothed = arrays["position"].astype(np.float64)
    made = make_smoother(**smoother)
    for sequence in np.unique(arrays["sequence"]):
        rows = np.flatnonzero(arrays["sequence"] == sequence)  # the smoothers take rows in any time order
        smoothed[rows] = smooth_detected(made, arrays["time"][rows], smoothed[rows], arrays["detected"][rows])
    return smoothed


def run(data: list[Path], recipe: str, net_kwargs: dict, cache: Path | None, batch_size: int = 64,
        smoother: dict | None = None) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """Evaluate ``srp_phat`` on every recording under ``data``; the summary and the per-window arrays.
    With ``smoother`` (:func:`zoo.smoothing.make_smoother` arguments), ``E_smooth`` is the error of the
    detected windows' smoothed track."""
    start = time.perf_counter()
    module = recordings_module(data, recipe, cache, batch_size)
    feature_seconds = time.perf_counter() - start
    net = get_model("srp_phat", input_recipes={"audio_phase": recipe}, **net_kwargs)
    net.set_bounds(module.hparams.bev_bounds)
    ids = module.sequence_ids
    drones = {s.sequence_id: s.drone or "?" for s in module.sequences["test"]}
    keep: dict[str, list[np.ndarray]] = {name: [] for name in ("position", "gt", "valid", "detected", "score",
                                                                "time", "sequence")}
    net_seconds = 0.0
    for batch in module.test_dataloader()[0]:
        inputs = {name: batch[name] for name in ("audio_phase", "mic_positions", "time", "sequence")}
        if not net_seconds:
            net.prepare(inputs)  # the null threshold and coarse grid, once per geometry (not timed)
        tick = time.perf_counter()
        with torch.no_grad():
            out = net(inputs)
        net_seconds += time.perf_counter() - tick
        for name, value in (("position", out["position"]), ("gt", batch["gt"]), ("valid", batch["gt_valid"]),
                            ("detected", out["detected"]), ("score", out["detection_score"]),
                            ("time", batch["time"]), ("sequence", batch["sequence"])):
            keep[name].append(value.numpy())
    arrays = {name: np.concatenate(values) for name, values in keep.items()}
    arrays["flight"] = np.array([ids[i] for i in arrays["sequence"]])
    arrays["drone"] = np.array([drones[f] for f in arrays["flight"]])
    valid = arrays["valid"]
    result = summarise(arrays["position"][valid], arrays["gt"][valid], arrays["detected"][valid],
                       arrays["drone"][valid], arrays["flight"][valid])
    if smoother:
        arrays["smoothed"] = smooth_flights(arrays, smoother)
        result["E_smooth"] = float(np.linalg.norm(arrays["smoothed"][valid] - arrays["gt"][valid], axis=1).mean())
    windows = len(arrays["time"])
    shape = phase_recipe(recipe).output_shape(int(module.sequences["test"][0].mic_positions.shape[0]))
    result.update(net_windows_per_s=windows / net_seconds, feature_windows_per_s=windows / feature_seconds,
                  cache_kb_per_window=float(np.prod(shape)) * 2 / 1024, threads=float(torch.get_num_threads()))
    return result, arrays


def format_table(result: dict[str, float]) -> str:
    """The summary as aligned ``name value`` lines."""
    return "\n".join(f"{name:>22s} {value:10.3f}" for name, value in result.items())


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, nargs="+", required=True, help="folders or files of recordings")
    parser.add_argument("--recipe", default="gcc_phat", help="phase recipe the net reads")
    parser.add_argument("--net-kwargs", default="{}", help="srp_phat keyword arguments as JSON")
    parser.add_argument("--cache", type=Path, help="feature cache folder (default $AAUTE_CACHE)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--save", type=Path, help="write the per-window arrays to this .npz")
    parser.add_argument("--smoother", help="also score the smoothed track of the detected windows: "
                        "make_smoother arguments as JSON, e.g. '{\"preset\": \"robust\", \"horizon\": 3}'")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(args.threads)
    def json_option(text: str, flag: str, what: str) -> dict:
        try:
            return json.loads(text)
        except json.JSONDecodeError as error:
            parser.error(f"{flag} must be a JSON object of {what}: {error}")

    net_kwargs = json_option(args.net_kwargs, "--net-kwargs", "srp_phat arguments")
    smoother = None if args.smoother is None else json_option(args.smoother, "--smoother", "make_smoother arguments")
    result, arrays = run(args.data, args.recipe, net_kwargs, args.cache, smoother=smoother)
    print(format_table(result))
    if args.save is not None:
        with atomic_write(args.save) as tmp, open(tmp, "wb") as handle:
            np.savez(handle, **arrays)


if __name__ == "__main__":
    main()
