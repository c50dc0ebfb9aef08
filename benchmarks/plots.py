"""The leaderboard's figures: trajectories, error CDFs, E against GMACs, E by range (matplotlib, no pyplot).

:class:`SectionPlotter` decides what to draw for one leaderboard table from its method statistics
(one row per method, as :func:`benchmarks.leaderboard.method_stats` builds them) and the per-window
prediction files the rows point to (:data:`benchmarks.results.PREDICTION_COLUMNS`); the numbers of the tables never
come from those files. A missing or unreadable file leaves its method out of a figure, or skips the
figure, with a warning. Figures are built on :class:`matplotlib.figure.Figure` directly, which needs
no GUI backend, and written as PNG atomically.
"""

from __future__ import annotations

import io
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from benchmarks.results import PREDICTION_COLUMNS
from datamodules.atomic import atomic_write
from datamodules.errors import AauteError

REFERENCE_STYLE = {"color": "0.45", "linestyle": "--"}  #: the constant-position predictor in every figure
BOUND_STYLE = {"color": "black", "linewidth": 2.0}  #: the physical limit (CRLB) in every figure
DPI = 100
#: Fixed margins (fractions of the figure) that fit the labels used here; a layout engine (constrained or
#: tight layout) would fit any label but doubles the drawing time, which dominates a leaderboard render.
MARGINS = {"left": 0.09, "right": 0.98, "bottom": 0.12, "top": 0.92}


class PredictionsError(AauteError, ValueError):
    """A predictions CSV that is missing or does not have the expected columns."""


def read_predictions(path: Path) -> pd.DataFrame:
    """Read a per-window predictions CSV; raises :class:`PredictionsError` naming the file and the problem."""
    if not path.is_file():
        raise PredictionsError(f"{path}: predictions file not found")
    try:
        frame = pd.read_csv(path, dtype={"sequence_id": str, "recording_id": str, "drone": str, "light": str})
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as error:
        raise PredictionsError(f"{path}: not a predictions CSV ({error})") from None
    missing = [column for column in PREDICTION_COLUMNS if column not in frame.columns]
    if missing:
        raise PredictionsError(f"{path}: predictions CSV lacks column(s) {missing}")
    if frame.empty:
        raise PredictionsError(f"{path}: predictions CSV has no windows")
    for column in PREDICTION_COLUMNS[4:]:
        try:
            frame[column] = pd.to_numeric(frame[column])  # empty cells (smoothing off) are NaN
        except (ValueError, TypeError):
            raise PredictionsError(f"{path}: column {column!r} is not numeric") from None
    return frame


def light_subset(frame: pd.DataFrame, light: str = "ideal") -> pd.DataFrame:
    """The windows of one light condition (all windows when the file has no such light)."""
    chosen = frame[frame["light"] == light]
    return chosen if len(chosen) else frame


def window_errors(frame: pd.DataFrame) -> np.ndarray:
    """Per-window Euclidean error (m) of the raw estimates, over windows with valid ground truth."""
    valid = frame[frame["gt_valid"].astype(float) > 0]
    diff = valid[["x", "y", "z"]].to_numpy(float) - valid[["gt_x", "gt_y", "gt_z"]].to_numpy(float)
    errors = np.linalg.norm(diff, axis=1)
    return errors[np.isfinite(errors)]


def bound_values(frame: pd.DataFrame) -> np.ndarray:
    """Per-window physical limit (m) of a bound job's ``bounds.csv``, over windows with valid ground truth."""
    if "bound_m" not in frame:
        return np.zeros(0)
    values = frame.loc[frame["gt_valid"].astype(float) > 0, "bound_m"].to_numpy(float)
    return values[np.isfinite(values)]


def save_png(figure: Figure, path: Path) -> bytes:
    """Write ``figure`` as a PNG at ``path`` (atomically) and return the PNG bytes (for embedding)."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=DPI)
    data = buffer.getvalue()
    with atomic_write(path) as tmp:
        tmp.write_bytes(data)
    return data


def trajectory_figure(methods: Sequence[tuple[str, pd.DataFrame]], constant: pd.DataFrame | None,
                      title: str) -> Figure:
    """x, y, z against time and a top view (x-y) of one flight: ground truth, each method's estimate (the first
    one's smoothed estimate too; a method whose windows say ``detected`` has its detections drawn as dots) and
    the constant.

    Args:
        methods: (legend name, prediction windows of one sequence and light condition), best first; the ground
            truth is read from the first.
        constant: the constant predictor's windows of the same sequence (None: not drawn).
        title: the figure title.
    """
    figure = Figure(figsize=(10, 6.5))
    figure.subplots_adjust(**{**MARGINS, "left": 0.07, "top": 0.91}, hspace=0.32, wspace=0.2)
    axes = figure.subplots(2, 2)
    methods = [(label, frame.sort_values("timestamp")) for label, frame in methods]
    first_label, first = methods[0]
    t0 = float(first["timestamp"].min())
    gt = first[first["gt_valid"].astype(float) > 0]
    series = [  # (label, windows, x/y/z columns, style against time, style in the top view)
        ("ground truth", gt, ("gt_x", "gt_y", "gt_z"), {"color": "black", "linewidth": 1.6}, None)]
    for index, (label, frame) in enumerate(methods):
        line = {"color": f"C{2 * index}", "linewidth": 0.8, "marker": ".", "markersize": 2.5}
        if "detected" not in frame.columns:
            series.append((label, frame, ("x", "y", "z"), line, None))
            continue
        # a detecting method: its line without markers (held and fallback windows too), its detections as dots
        series.append((label, frame, ("x", "y", "z"), {**line, "marker": None}, None))
        series.append((f"{label}, detected", frame[frame["detected"] == 1], ("x", "y", "z"),
                       {"color": line["color"], "linestyle": "none", "marker": "o", "markersize": 3.0}, None))
    if first["smooth_x"].notna().any():
        series.append((f"{first_label}, smoothed", first, ("smooth_x", "smooth_y", "smooth_z"),
                       {"color": "C1", "linewidth": 1.4}, None))
    if constant is not None and len(constant):
        point = {"color": REFERENCE_STYLE["color"], "linestyle": "none", "marker": "X", "markersize": 9}
        series.append(("constant (mean train target)", constant.sort_values("timestamp"), ("x", "y", "z"),
                       {**REFERENCE_STYLE, "linewidth": 1.2}, point))  # one point in the top view
    for ax, axis, index in zip(axes.flat[:3], "xyz", range(3), strict=True):
        for label, frame, columns, style, _ in series:
            ax.plot(frame["timestamp"] - t0, frame[columns[index]], label=label, **style)
        ax.set_xlabel("time in flight (s)")
        ax.set_ylabel(f"{axis} (m)")
        ax.grid(alpha=0.3)
    top = axes.flat[3]
    for label, frame, columns, style, top_style in series:
        top.plot(frame[columns[0]], frame[columns[1]], label=label, **(top_style or style))
    top.set_xlabel("x (m)")
    top.set_ylabel("y (m)")
    top.set_title("top view")
    top.set_aspect("equal", adjustable="datalim")
    top.grid(alpha=0.3)
    axes.flat[0].legend(fontsize=7, loc="best")
    figure.suptitle(title, fontsize=10)
    return figure


@dataclass(frozen=True)
class Curve:
    """One method's data in a comparison figure."""

    label: str
    reference: bool = False  #: the constant predictor: drawn grey and dashed
    bound: bool = False  #: the physical limit (CRLB): drawn as a black line


def error_cdf_figure(errors: Sequence[tuple[Curve, np.ndarray]], title: str) -> Figure:
    """Empirical CDF of the per-window Euclidean error, one curve per method."""
    figure = Figure(figsize=(7, 4.5))
    figure.subplots_adjust(**MARGINS)
    ax = figure.subplots()
    for index, (curve, values) in enumerate(errors):
        values = np.sort(values)
        fraction = np.arange(1, len(values) + 1) / len(values)
        style = BOUND_STYLE if curve.bound else REFERENCE_STYLE if curve.reference else {"color": f"C{index % 10}"}
        ax.step(values, fraction, where="post", label=f"{curve.label} (median {np.median(values):.2f} m)", **style)
    ax.set_xlabel("per-window Euclidean error (m), ideal light")
    ax.set_ylabel("fraction of test windows")
    ax.set_ylim(0, 1.02)
    ax.set_xlim(left=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title(title, fontsize=10)
    return figure


def error_vs_gmacs_figure(points: Sequence[tuple[Curve, float, float, float]], reference: float | None,
                          title: str) -> Figure:
    """E (with its std over seeds) against GMACs on a log axis, one labelled point per method.

    Args:
        points: (method, GMACs > 0, mean E, std of E or NaN) per method.
        reference: E of the constant predictor (a horizontal line) or None.
        title: the figure title.
    """
    figure = Figure(figsize=(7, 4.5))
    figure.subplots_adjust(**MARGINS)
    ax = figure.subplots()
    for index, (curve, gmacs, error, spread) in enumerate(points):
        ax.errorbar([gmacs], [error], yerr=None if np.isnan(spread) else [spread], fmt="o", capsize=3,
                    color=f"C{index % 10}")
        ax.annotate(curve.label, (gmacs, error), textcoords="offset points", xytext=(5, 4), fontsize=8)
    if reference is not None:
        ax.axhline(reference, label=f"constant (mean train target): {reference:.2f} m", **REFERENCE_STYLE)
        ax.legend(fontsize=8, loc="best")
    ax.set_xscale("log")
    gmacs = [point[1] for point in points]
    ax.set_xlim(min(gmacs) / 1.6, max(gmacs) * 3.0)  # room for the labels right of the points
    ax.set_xlabel("GMACs (batch 1, reference input shapes; log scale)")
    ax.set_ylabel("E, ideal light (m)")
    ax.grid(alpha=0.3, which="both")
    ax.set_title(title, fontsize=10)
    return figure


def error_by_range_figure(curves: Sequence[Curve], bands: Sequence[str], means: np.ndarray, stds: np.ndarray,
                          title: str) -> Figure:
    """Grouped bars of E per distance band, one bar per method (error bars: std over seeds).

    Args:
        curves: the methods (bars within a group).
        bands: the distance band labels (groups).
        means: methods x bands mean E (NaN: no windows in that band).
        stds: methods x bands std of E over seeds (NaN: one seed).
        title: the figure title.
    """
    figure = Figure(figsize=(8, 4.5))
    figure.subplots_adjust(**MARGINS)
    ax = figure.subplots()
    bars = [index for index, curve in enumerate(curves) if not curve.bound]
    width = 0.8 / max(len(bars), 1)
    positions = np.arange(len(bands))
    for index, curve in enumerate(curves):
        if curve.bound:  # a line across the groups, not a bar
            ax.plot(positions, means[index], marker="_", markersize=30, label=curve.label, **BOUND_STYLE)
            continue
        offset = positions - 0.4 + (bars.index(index) + 0.5) * width
        style = ({"color": "0.8", "edgecolor": "0.35", "hatch": "//"} if curve.reference
                 else {"color": f"C{index % 10}"})
        ax.bar(offset, means[index], width, yerr=stds[index], capsize=2, label=curve.label, **style)  # NaN: none
    ax.set_xticks(positions, bands)
    ax.set_xlabel("distance of the drone from the rig origin")
    ax.set_ylabel("E, ideal light (m)")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=8, loc="best")
    ax.set_title(title, fontsize=10)
    return figure


@dataclass
class Plot:
    """A written figure: its file, caption and PNG bytes (embedded in the HTML page)."""

    path: Path
    caption: str
    png: bytes


class SectionPlotter:
    """Draws the figures of one leaderboard table into ``plot_dir``.

    The statistics frame has one row per method with ``display``, ``kind``, ``reference``,
    ``predictions_path`` (relative to ``results_dir`` unless absolute; the lowest seed's file),
    ``predictions_seed``, ``gmacs`` and ``<metric>_mean`` / ``<metric>_std`` columns.
    """

    def __init__(self, results_dir: Path, plot_dir: Path, warn: Callable[[str], None]):
        self.results_dir = results_dir
        self.plot_dir = plot_dir
        self.warn = warn
        self.cache: dict[Path, pd.DataFrame | str] = {}

    def draw(self, stats: pd.DataFrame, number: int, protocol: str, bands: Mapping[str, str],
             trajectories: bool = False) -> list[Plot]:
        """Every figure of table ``number``; ``bands`` maps range column suffixes (``r0_10``) to labels."""
        plots = self.trajectories(stats, number, protocol) if trajectories else []
        return (plots + self.error_cdf(stats, number, protocol) + self.error_vs_gmacs(stats, number, protocol)
                + self.error_by_range(stats, number, protocol, bands))

    def predictions(self, stat: pd.Series) -> pd.DataFrame | str:
        """The method's prediction windows, or the reason there are none."""
        if not stat["predictions_path"]:
            return "no predictions_path in results.csv"
        path = Path(stat["predictions_path"])
        path = path if path.is_absolute() else self.results_dir / path
        if path not in self.cache:
            try:
                self.cache[path] = read_predictions(path)
            except PredictionsError as error:
                self.cache[path] = str(error)
        return self.cache[path]

    def save(self, figure: Figure, name: str, caption: str) -> Plot:
        path = self.plot_dir / name
        return Plot(path, caption, save_png(figure, path))

    def trajectories(self, stats: pd.DataFrame, number: int, protocol: str) -> list[Plot]:
        """One figure per drone: a test flight of the methods of interest (per category, the best, lowest ideal
        E, with predictions: the best published baseline, self-supervised and non-learned model) beside the
        constant."""
        what = f"trajectory plots (Table {number})"
        candidates = stats[(stats["kind"] == "model") & ~stats["reference"] & stats["E_ideal_mean"].notna()]
        if candidates.empty:
            self.warn(f"{what} skipped: no model with an ideal-light E")
            return []
        methods, categories = [], set()
        for _, stat in candidates.sort_values("E_ideal_mean").iterrows():  # best first
            if stat["category"] in categories:
                continue
            frame = self.predictions(stat)
            if isinstance(frame, str):
                self.warn(f"{what}: {stat['display']} left out: {frame}")
            else:
                methods.append((stat, frame))
                categories.add(stat["category"])
        if not methods:
            self.warn(f"{what} skipped: no method of interest has predictions")
            return []
        first = methods[0][1]
        light = "ideal" if (first["light"] == "ideal").any() else str(first["light"].iloc[0])
        methods = [(stat, frame[frame["light"] == light]) for stat, frame in methods]
        constants = stats[stats["kind"] == "constant"]
        constant = self.predictions(constants.iloc[0]) if len(constants) else "no constant row in the table"
        if isinstance(constant, str):
            self.warn(f"{what}: drawn without the constant predictor: {constant}")
            constant = None
        else:
            constant = constant[constant["light"] == light]
        names = ", ".join(f"{stat['display']} (seed {stat['predictions_seed']:g})" for stat, _ in methods)
        plots = []
        for drone, flights in methods[0][1].groupby("drone", sort=True):
            sequence = flights.groupby("sequence_id").size().sort_index().idxmax()  # the longest flight
            drawn = [(str(stat["display"]), frame[frame["sequence_id"] == sequence]) for stat, frame in methods]
            drawn = [(label, frame) for label, frame in drawn if len(frame)]
            reference = None if constant is None else constant[constant["sequence_id"] == sequence]
            title = f"{drone}, test flight {sequence} ({light} light), protocol {protocol}"
            figure = trajectory_figure(drawn, reference, title)
            detecting = [label for label, frame in drawn if "detected" in frame.columns]
            dots = (f" Dots mark the windows {', '.join(detecting)} detected the drone in; between them it holds "
                    f"its last detection or falls back." if detecting else "")
            caption = (f"Estimated and true trajectory of one test flight of the {drone} ({light} light) for the "
                       f"best method of each category of Table {number}, {names}, beside the constant predictor "
                       f"(the best one's smoothed estimate too): x, y, z against time and a top view.{dots}")
            plots.append(self.save(figure, f"trajectory_{re.sub(r'[^A-Za-z0-9_.-]+', '_', str(drone))}.png",
                                   caption))
        return plots

    def error_cdf(self, stats: pd.DataFrame, number: int, protocol: str) -> list[Plot]:
        """The CDF of per-window errors (ideal light), one curve per method with readable predictions."""
        what = f"error CDF (Table {number})"
        curves, left_out = [], []
        for _, stat in stats.iterrows():
            frame = self.predictions(stat)
            if isinstance(frame, str):
                left_out.append(f"{stat['display']} ({frame})")
                continue
            bound = stat["kind"] == "bound"
            windows = light_subset(frame, "ideal")
            errors = bound_values(windows) if bound else window_errors(windows)
            if errors.size:
                curves.append((Curve(stat["display"], bool(stat["reference"]), bound), errors))
            else:
                left_out.append(f"{stat['display']} (no window with valid ground truth)")
        if not curves:
            self.warn(f"{what} skipped: no readable predictions: {'; '.join(left_out)}")
            return []
        if left_out:
            self.warn(f"{what}: left out {'; '.join(left_out)}")
        figure = error_cdf_figure(curves, f"Per-window error, Table {number} ({protocol})")
        caption = (f"Distribution (CDF) of the per-window Euclidean error under ideal light, one curve per method "
                   f"of Table {number} (lowest seed of each method, raw estimates)")
        limit = any(curve.bound for curve, _ in curves)
        caption += "; the black line is the per-window physical limit (CRLB)." if limit else "."
        return [self.save(figure, f"t{number}_error_cdf.png", caption)]

    def error_vs_gmacs(self, stats: pd.DataFrame, number: int, protocol: str) -> list[Plot]:
        """E (ideal light) against GMACs, one point per method that has both."""
        points = [(Curve(stat["display"]), float(stat["gmacs"]), float(stat["E_ideal_mean"]),
                   float(stat["E_ideal_std"])) for _, stat in stats.iterrows()
                  if not stat["reference"] and stat["gmacs"] > 0 and np.isfinite(stat["E_ideal_mean"])]
        if not points:
            self.warn(f"E-vs-GMACs plot (Table {number}) skipped: no method has both GMACs and an ideal-light E")
            return []
        constant = stats.loc[stats["kind"] == "constant", "E_ideal_mean"].dropna()
        figure = error_vs_gmacs_figure(points, float(constant.iloc[0]) if len(constant) else None,
                                       f"E against compute, Table {number} ({protocol})")
        caption = (f"E (ideal light, mean ± std over seeds) against GMACs (log scale) for the methods of Table "
                   f"{number}; the dashed line is the constant predictor.")
        return [self.save(figure, f"t{number}_error_vs_gmacs.png", caption)]

    def error_by_range(self, stats: pd.DataFrame, number: int, protocol: str,
                       bands: Mapping[str, str]) -> list[Plot]:
        """E (ideal light) per distance band, grouped bars per method."""
        bands = {band: label for band, label in bands.items() if stats[f"E_ideal_{band}_mean"].notna().any()}
        means_columns = [f"E_ideal_{band}_mean" for band in bands]
        stats = stats[stats[means_columns].notna().any(axis=1)]
        if stats.empty:
            self.warn(f"E-by-range plot (Table {number}) skipped: no per-range E in results.csv")
            return []
        means = stats[means_columns].to_numpy(float)
        stds = stats[[f"E_ideal_{band}_std" for band in bands]].to_numpy(float)
        curves = [Curve(stat["display"], bool(stat["reference"]), stat["kind"] == "bound")
                  for _, stat in stats.iterrows()]
        figure = error_by_range_figure(curves, list(bands.values()), means, stds,
                                       f"E by range, Table {number} ({protocol})")
        caption = f"E (ideal light, mean ± std over seeds) per distance band, one bar per method of Table {number}"
        limit = any(curve.bound for curve in curves)
        caption += "; the black line is the physical limit (CRLB, RMS per band)." if limit else "."
        return [self.save(figure, f"t{number}_error_by_range.png", caption)]
