"""Learning curves from ``results.csv``: E against the number of training windows, one curve per model.

The rows of a learning suite (``configs/benchmark/learning.yaml``: every model at several ``train_flights``)
are model rows like any other; this module groups them by model and draws E (ideal light, mean over seeds)
against their training windows on a log axis, with the constant predictor (mean training ground truth) and the
physical limit (CRLB) as horizontal lines. A curve that falls with data is limited by data; one flat at the
constant, by what its inputs carry. ``aaute leaderboard ... --learning <this results.csv>`` states the curves of
a table's models in its caption (:func:`learning_evidence`).

    python -m benchmarks.learning demo_out/learning/results.csv --out demo_out/learning/learning_curves.png
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from benchmarks.plots import BOUND_STYLE, MARGINS, REFERENCE_STYLE, Plot, save_png
from benchmarks.results import ResultsError, latest, read_results

#: a curve is clearly below the constant where its E is lower by more than this share of it (a few seeds per size
#: give a rough spread at best, and one split alone none)
CLEAR_MARGIN = 0.05


def curve_points(frame: pd.DataFrame, light: str = "ideal") -> pd.DataFrame:
    """One row per model and data size: training flights and windows, E mean and std over seeds, seeds."""
    rows = frame[(frame["kind"] == "model") & (frame["status"] == "ok") & frame[f"E_{light}"].notna()]
    grouped = rows.groupby(["model", "n_train_sequences", "n_train_windows"], sort=True)[f"E_{light}"]
    points = grouped.agg(E="mean", std="std", seeds="size").reset_index()
    return points.rename(columns={"n_train_sequences": "flights", "n_train_windows": "windows"})


def reference_level(frame: pd.DataFrame, kind: str, light: str = "ideal", seeds: Sequence[int] | None = None
                    ) -> float | None:
    """E of the constant (mean training GT; ``kind`` 'constant') or of the physical limit ('bound'), mean over
    seeds (``seeds``: these only; a learning suite's seed is also its split's, so each has its own constant)."""
    rows = frame[(frame["kind"] == kind) & (frame["status"] == "ok")]
    if seeds is not None:
        rows = rows[rows["seed"].isin(list(seeds))]
    if kind == "constant":
        rows = rows[rows["method"].str.contains("GT", regex=False)]
    values = rows[f"E_{light}"].dropna()
    return float(values.mean()) if len(values) else None


def read_learning(path: Path) -> pd.DataFrame:
    """The newest rows of a learning suite's results.csv; a file without successful model rows is refused."""
    frame = latest(read_results(path))
    if not ((frame["kind"] == "model") & (frame["status"] == "ok")).any():
        raise ResultsError(f"{path}: no successful model rows: no learning curves to state")
    return frame


def _windows(value: float) -> str:
    return f"{value:.0f}"


def model_seeds(frame: pd.DataFrame) -> dict[str, tuple[int, ...]]:
    """The seeds each model's successful rows ran on."""
    rows = frame[(frame["kind"] == "model") & (frame["status"] == "ok")]
    return {str(model): tuple(sorted({int(seed) for seed in group["seed"]})) for model, group in rows.groupby("model")}


def _seed_words(seeds: Sequence[int]) -> str:
    return f"seed{'s' if len(seeds) > 1 else ''} {', '.join(str(seed) for seed in seeds)}"


def _model_clause(name: str, curve: pd.DataFrame, constant: float | None, constant_note: str = "") -> str:
    """One model's curve in words: E at the smallest and largest size, its best, and the sizes at which it is
    clearly below the constant (by more than :data:`CLEAR_MARGIN` of it)."""
    curve = curve.sort_values("windows")
    first, last = curve.iloc[0], curve.iloc[-1]
    best = curve.loc[curve["E"].idxmin()]
    text = f"{name} {first['E']:.2f} m at {_windows(first['windows'])} windows"
    if len(curve) > 1:
        text += f" to {last['E']:.2f} m at {_windows(last['windows'])}"
    if constant is None:
        return f"{text} (best {best['E']:.2f} m at {_windows(best['windows'])})"
    text += (f" (best {best['E']:.2f} m at {_windows(best['windows'])}, {best['E'] / constant:.2f} × the "
             f"constant{constant_note})")
    below = curve[curve["E"] < (1 - CLEAR_MARGIN) * constant]
    margin = f"more than {CLEAR_MARGIN * 100:.0f} % below the constant"
    if below.empty:
        return f"{text}: at no size {margin}"
    if len(below) == len(curve):
        return f"{text}: {margin} at every size"
    return f"{text}: {margin} at {', '.join(_windows(value) for value in below['windows'])} windows"


def _dark_clause(curve: pd.DataFrame, dark: pd.DataFrame) -> str:
    """A model's E in darkness at its largest data size against its ideal-light E there; '' for a model whose
    E is the same in both (it reads no image)."""
    both = curve.merge(dark, on=["flights", "windows"], suffixes=("", "_dark")).sort_values("windows")
    if both.empty or np.allclose(both["E"], both["E_dark"]):
        return ""
    last = both.iloc[-1]
    return (f", in darkness {last['E_dark']:.2f} m at {_windows(last['windows'])} windows "
            f"({last['E_dark'] / last['E']:.2f} × its E in ideal light)")


def _measured_by(frame: pd.DataFrame, source: str) -> str:
    """Where curves come from: the file (if named), the suite(s) and the commit(s) their model rows ran at."""
    trained = frame[frame["kind"] == "model"]
    suites = ", ".join(dict.fromkeys(trained["suite"].dropna().astype(str))) or "not recorded"
    commits = ", ".join(dict.fromkeys(trained["git_commit"].dropna().astype(str).str[:7]))
    return f"{f'{source}, ' if source else ''}suite {suites}{f' at commit {commits}' if commits else ''}"


def learning_evidence(frame: pd.DataFrame, protocol: str, methods: Mapping[str, str], light: str = "ideal",
                      source: str = "") -> str:
    """A caption's sentence on the learning curves of ``methods`` (model -> name in the table), '' if none.

    ``frame``: the rows of a learning suite's ``results.csv`` (newest per job), read from ``source`` (named in
    the sentence with the suite and the commit its rows ran at). Each model is stated by its E at the smallest
    and the largest data size, its best, and the sizes at which it is below the constant of the same data, so a
    reader sees whether a row fails for lack of data or whatever the data; a model that reads images also by its
    E in darkness (does it see the drone at all?).
    """
    rows = frame[frame["protocol"] == protocol]
    points = curve_points(rows, light)
    points = points[points["model"].isin(list(methods))]
    if points.empty:
        return ""
    constant = reference_level(rows, "constant", light)
    bound = reference_level(rows, "bound", light)
    trained = rows[rows["kind"] == "model"]
    data = "; ".join(dict.fromkeys(trained["data"].dropna().astype(str))) or "data not recorded"
    seeds = int(points["seeds"].max())
    references = [f"constant (mean train GT) {constant:.2f} m" if constant is not None else "no constant row"]
    if bound is not None:
        references.append(f"physical limit (CRLB, RMS) {bound:.2f} m")
    dark = curve_points(rows, "dark") if light == "ideal" else points.iloc[:0]
    own = model_seeds(rows)
    every = sorted({seed for seeds in own.values() for seed in seeds})
    # each seed its own split only where the constants differ (a split fixed apart from the seed gives one constant)
    own_splits = len({reference_level(rows, "constant", light, [seed]) for seed in every}) > 1
    spread = "one seed" if seeds == 1 else f"mean over up to {seeds} seeds{', each its own split,' * own_splits}"
    clauses = []
    for model, name in methods.items():
        if model not in set(points["model"]):
            continue
        # against the constant of the splits the model ran on (a learning suite's seed is its split's)
        fewer = list(own[model]) != every
        mine = reference_level(rows, "constant", light, own[model]) if fewer else constant
        note = f" of its {_seed_words(own[model])}, {mine:.2f} m" if fewer and mine is not None else ""
        clauses.append(_model_clause(name, points[points["model"] == model], mine, note)
                       + _dark_clause(points[points["model"] == model], dark[dark["model"] == model]))
    return (f"Learning curves ({_measured_by(rows, source)}: {data}; protocol {protocol}; E under {light} light, "
            f"{spread} per size; its own "
            f"{', '.join(references)}): {'; '.join(clauses)}.")


def learning_figure(points: pd.DataFrame, constants: Mapping[str, float], bound: float | None, title: str
                    ) -> Figure:
    """E against training windows (log axis), one line per model, the references as horizontal lines
    (``constants``: label -> E of each constant drawn)."""
    figure = Figure(figsize=(7, 4.5))
    figure.subplots_adjust(**MARGINS)
    ax = figure.subplots()
    for index, (model, curve) in enumerate(points.groupby("model", sort=True)):
        curve = curve.sort_values("windows")
        ax.errorbar(curve["windows"], curve["E"], yerr=curve["std"].fillna(0.0), marker="o", capsize=3,
                    color=f"C{index % 10}", label=str(model))
    for index, (label, constant) in enumerate(constants.items()):
        style = {**REFERENCE_STYLE, "linestyle": ("--", ":", "-.")[index % 3]}
        ax.axhline(constant, label=f"{label}: {constant:.2f} m", **style)
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


def _constants(frame: pd.DataFrame, light: str) -> dict[str, float]:
    """The constant's line of every set of seeds the models ran on (one line when they all ran on the same)."""
    sets = sorted(set(model_seeds(frame).values()), key=lambda seeds: (-len(seeds), seeds))
    lines = {}
    for seeds in sets:
        level = reference_level(frame, "constant", light, seeds)
        if level is not None:
            label = "constant (mean train GT)" + (f", {_seed_words(seeds)}" if len(sets) > 1 else "")
            lines[label] = level
    return lines


def _draw(frame: pd.DataFrame, source: Path, out: Path, light: str) -> tuple[pd.DataFrame, bytes]:
    """Draw the learning curves of a learning suite's rows (newest per job) into ``out`` (PNG): their points and
    the PNG bytes."""
    points = curve_points(frame, light)
    if points.empty:
        raise ResultsError(f"{source}: no successful model rows with E under {light} light to draw")
    figure = learning_figure(points, _constants(frame, light), reference_level(frame, "bound", light),
                             f"Learning curves ({', '.join(frame['suite'].dropna().unique())})")
    out.parent.mkdir(parents=True, exist_ok=True)
    return points, save_png(figure, out)


def learning_curves(results: Path, out: Path, light: str = "ideal") -> pd.DataFrame:
    """Draw the learning curves of ``results`` into ``out`` (PNG) and return their points."""
    return _draw(latest(read_results(results)), results, out, light)[0]


def learning_plot(frame: pd.DataFrame, source: Path, plot_dir: Path) -> Plot:
    """The leaderboard's figure of a learning suite's curves (rows of ``source``, newest per job), ideal light,
    as ``learning_curves.png`` in ``plot_dir``, with a caption naming where they were measured."""
    path = plot_dir / "learning_curves.png"
    _, png = _draw(frame, source, path, "ideal")
    caption = (f"Learning curves ({_measured_by(frame, str(source))}): E in ideal light against training windows "
               "(log scale), one line per model, with that data's constant (mean train GT) and physical limit "
               "(CRLB, RMS) as horizontal lines.")
    return Plot(path, caption, png)


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
