"""Learning curves from ``results.csv``: E against the number of training windows, one curve per model.

The rows of a learning suite (``configs/benchmark/learning.yaml``: every model at several ``train_flights``)
are model rows like any other; this module groups them by model and draws E (ideal light, mean over seeds)
against their training windows on a log axis, with the constant predictor (mean training ground truth) and the
physical limit (CRLB) as horizontal lines. A curve that falls with data is limited by data; one flat at the
constant, by what its inputs carry.

    python -m benchmarks.learning demo_out/learning/results.csv --out demo_out/learning/learning_curves.png
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import pandas as pd
from matplotlib.figure import Figure

from benchmarks.plots import BOUND_STYLE, MARGINS, REFERENCE_STYLE, save_png
from benchmarks.results import ResultsError, latest, read_results


def curve_points(frame: pd.DataFrame, light: str = "ideal") -> pd.DataFrame:
    """One row per model and data size: training flights and windows, E mean and std over seeds, seeds."""
    rows = frame[(frame["kind"] == "model") & (frame["status"] == "ok") & frame[f"E_{light}"].notna()]
    grouped = rows.groupby(["model", "n_train_sequences", "n_train_windows"], sort=True)[f"E_{light}"]
    points = grouped.agg(E="mean", std="std", seeds="size").reset_index()
    return points.rename(columns={"n_train_sequences": "flights", "n_train_windows": "windows"})


def reference_level(frame: pd.DataFrame, kind: str, light: str = "ideal") -> float | None:
    """E of the constant (mean training GT; ``kind`` 'constant') or of the physical limit ('bound'), over seeds."""
    rows = frame[(frame["kind"] == kind) & (frame["status"] == "ok")]
    if kind == "constant":
        rows = rows[rows["method"].str.contains("GT", regex=False)]
    values = rows[f"E_{light}"].dropna()
    return float(values.mean()) if len(values) else None


def learning_figure(points: pd.DataFrame, constant: float | None, bound: float | None, title: str) -> Figure:
    """E against training windows (log axis), one line per model, the references as horizontal lines."""
    figure = Figure(figsize=(7, 4.5))
    figure.subplots_adjust(**MARGINS)
    ax = figure.subplots()
    for index, (model, curve) in enumerate(points.groupby("model", sort=True)):
        curve = curve.sort_values("windows")
        ax.errorbar(curve["windows"], curve["E"], yerr=curve["std"].fillna(0.0), marker="o", capsize=3,
                    color=f"C{index % 10}", label=str(model))
    if constant is not None:
        ax.axhline(constant, label=f"constant (mean train GT): {constant:.2f} m", **REFERENCE_STYLE)
    if bound is not None:
        ax.axhline(bound, label=f"physical limit (CRLB, RMS): {bound:.2f} m", **BOUND_STYLE)
    ax.set_xscale("log")
    ax.set_xlabel("training windows (log scale)")
    ax.set_ylabel("E, ideal light (m)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="best")
    ax.set_title(title, fontsize=10)
    return figure


def learning_curves(results: Path, out: Path, light: str = "ideal") -> pd.DataFrame:
    """Draw the learning curves of ``results`` into ``out`` (PNG) and return their points."""
    frame = latest(read_results(results))
    points = curve_points(frame, light)
    if points.empty:
        raise ResultsError(f"{results}: no successful model rows with E under {light} light to draw")
    figure = learning_figure(points, reference_level(frame, "constant", light), reference_level(frame, "bound", light),
                             f"Learning curves ({', '.join(frame['suite'].dropna().unique())})")
    out.parent.mkdir(parents=True, exist_ok=True)
    save_png(figure, out)
    return points


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.learning", description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, help="results.csv of a learning suite")
    parser.add_argument("--out", type=Path, required=True, help="PNG file to write")
    parser.add_argument("--light", default="ideal", choices=("ideal", "dark"))
    args = parser.parse_args(argv)
    try:
        points = learning_curves(args.results, args.out, args.light)
    except ResultsError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    table = points.assign(E=points["E"].round(2), std=points["std"].round(2))
    print(table.to_string(index=False))
    print(f"figure: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
