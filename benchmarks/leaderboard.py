"""``aaute leaderboard``: render ``results.csv`` as the paper's comparison table, breakdowns and plots.

Every number in the tables comes from ``results.csv`` (read by :func:`benchmarks.results.read_results`,
the newest row of each job); plots may also read the per-window prediction files the rows point to.
Layout (like Table I of the AAUTE paper): one row per method with its category, Dx Dy Dz E under
ideal light and under darkness, mean E, GMACs, parameters, latency and, where smoothing ran, the
smoothed E (the caption names each method's smoother); mean ± sample standard deviation over seeds;
best value per column in bold, second underlined (lower is better everywhere; the constant-position row
is shown but never ranked).
One table per suite x protocol x data fingerprint, never mixed; the ``random_windows`` protocol is
labelled leaky. Outputs: ``leaderboard.md``, ``leaderboard.csv``, ``leaderboard.tex`` (booktabs),
one self-contained ``leaderboard.html`` and the PNG plots in ``plots/``. This module computes the
statistics and assembles the pages; :mod:`benchmarks.tables` holds the table model and renders it,
:mod:`benchmarks.captions` writes each table's caption.
"""

from __future__ import annotations

import argparse
import base64
import html
import logging
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from benchmarks.captions import distinct_values, learning_sentence, plain_text, table_caption
from benchmarks.results import (
    BREAKDOWN,
    CATEGORIES,
    DRONES,
    LIGHTS,
    METRICS,
    PROTOCOLS,
    RANGES,
    ResultsError,
    latest,
    range_name,
    read_results,
)
from benchmarks.tables import (
    CSS,
    Cell,
    Column,
    Row,
    Table,
    html_table,
    latex_table,
    markdown_escape,
    markdown_table,
)
from datamodules.atomic import atomic_write
from datamodules.errors import AauteError

if TYPE_CHECKING:
    from benchmarks.plots import Plot

log = logging.getLogger(__name__)

#: Row order within a category: the paper's Table I (supervised visual, audio, audio-visual models, then the
#: student); models not listed follow the listed ones of their category, by method name.
PAPER_ORDER = ("visualnet", "darknet", "audionet", "voranet", "asdnet", "avped", "avfdti", "student", "srp_phat")
LEAKY_TITLE = "leaky: test windows overlap training windows"
RANGE_LABELS = {range_name(*band): f"{band[0]:g}–{band[1]:g} m" if band[1] is not None else f"{band[0]:g}+ m"
                for band in RANGES}
LIGHT_TITLES = {"ideal": "ideal light", "dark": "darkness"}  #: group headers above the per-light columns
VALUE_KEYS = [*METRICS, "E_avg", *BREAKDOWN]  #: aggregated over seeds: <key>_mean and <key>_std
PROFILE_KEYS = ["params_total_M", "params_used_M", "gmacs", "gflops", "latency_ms_1t", "latency_iqr_ms_1t",
                "throughput_1t", "profile_inputs"]



class LeaderboardError(AauteError, ValueError):
    """``results.csv`` can be read but holds nothing to render (the message says why)."""


@dataclass
class Section:
    """The tables of one suite x protocol x data fingerprint, the statistics behind them and their plots."""

    number: int
    suite: str
    protocol: str
    fingerprint: str
    rows: pd.DataFrame
    stats: pd.DataFrame
    tables: list[Table]
    plots: list[Plot] = field(default_factory=list)  # filled by render_leaderboard


@dataclass
class LeaderboardReport:
    """What :func:`render_leaderboard` wrote: the files, the plots, the Markdown text and the warnings."""

    markdown: str
    files: dict[str, Path]
    plots: list[Path]
    warnings: list[str]

    @property
    def html(self) -> Path:
        return self.files["html"]

    @property
    def paths(self) -> list[Path]:
        """Every file written."""
        return [*self.files.values(), *self.plots]


# ----------------------------------------------------------------------------------------------- statistics


def _method_key(row: pd.Series) -> str:
    return "|".join((row["kind"], row["model"], row["method"], plain_text(row["alpha"])))


def _sort_key(row: pd.Series) -> tuple:
    category = row["category"]
    rank = CATEGORIES.index(category) if category in CATEGORIES else 2.5  # unknown: before reference
    order = PAPER_ORDER.index(row["model"]) if row["model"] in PAPER_ORDER else len(PAPER_ORDER)
    return rank, row["kind"] == "constant", order, row["display"]


def method_stats(rows: pd.DataFrame, profiles: pd.DataFrame) -> pd.DataFrame:
    """One row per method (kind x model x method x alpha): mean and std over seeds, profile values, order.

    ``rows`` are the ok model and constant rows of one table; ``profiles`` the ok profile rows (the
    last one of each model is used). Std is the sample standard deviation (ddof 1), NaN for one seed.
    The result is sorted in the paper's order, constant last.
    """
    rows = rows.assign(E_avg=(rows["E_ideal"] + rows["E_dark"]) / 2, _key=rows.apply(_method_key, axis=1))
    grouped = rows.groupby("_key", sort=False)
    stats = grouped[["kind", "model", "method", "category", "alpha"]].first()
    stats["n_seeds"] = grouped.size()
    stats["seeds"] = grouped["seed"].agg(lambda s: ", ".join(plain_text(v) for v in sorted(s.dropna().unique())))
    stats = stats.join(grouped[VALUE_KEYS].mean().add_suffix("_mean"))
    stats = stats.join(grouped[VALUE_KEYS].std(ddof=1).add_suffix("_std"))
    first_prediction = (rows[rows["predictions_path"] != ""].sort_values("seed", kind="stable")
                        .groupby("_key", sort=False)[["predictions_path", "seed"]].first())
    stats = stats.join(first_prediction.rename(columns={"seed": "predictions_seed"}))
    stats["predictions_path"] = stats["predictions_path"].fillna("")
    profile = profiles.drop_duplicates("model", keep="last").set_index("model")[PROFILE_KEYS]
    stats = stats.join(profile, on="model")
    stats.loc[stats["kind"] == "constant", PROFILE_KEYS] = np.nan
    stats["reference"] = (stats["kind"] == "constant") | (stats["category"] == "reference")
    stats["display"] = [method or model for method, model in zip(stats["method"], stats["model"], strict=True)]
    repeated = stats["display"].duplicated(keep=False)
    stats.loc[repeated, "display"] = [f"{name} ({model}, α={plain_text(alpha) or '-'})" for name, model, alpha
                                      in stats.loc[repeated, ["display", "model", "alpha"]].itertuples(index=False)]
    order = sorted(stats.index, key=lambda key: _sort_key(stats.loc[key]))
    return stats.loc[order].reset_index(drop=True)


def _build_rows(stats: pd.DataFrame, columns: Sequence[Column], labels: Callable[[pd.Series], list[str]]) -> list[Row]:
    """Rows with their cells, marked: per column the best value bold, the second underlined.

    Ranking uses the values as displayed (so ties look tied), lower is better, among the rows that are
    not the reference; a column is marked when at least two rows compete, the second when three do.
    """
    rows = []
    for _, stat in stats.iterrows():
        cells = {}
        for column in columns:
            mean = stat[f"{column.key}_mean"] if column.aggregated else stat[column.key]
            std = stat[f"{column.key}_std"] if column.aggregated else np.nan
            cells[column.key] = Cell(float(mean), float(std), column.digits)
        rows.append(Row(labels(stat), cells, bool(stat["reference"])))
    for column in columns:
        ranked = [(float(parts[0]), row.cells[column.key]) for row in rows if not row.reference
                  and (parts := row.cells[column.key].parts()) is not None]
        if len(ranked) < 2:
            continue
        distinct = sorted({value for value, _ in ranked})
        for value, cell in ranked:
            if value == distinct[0]:
                cell.mark = "best"
            elif len(ranked) >= 3 and len(distinct) > 1 and value == distinct[1]:
                cell.mark = "second"
    return rows


# ----------------------------------------------------------------------------------------------- tables


def _main_columns(stats: pd.DataFrame) -> list[Column]:
    columns = [Column(f"{name}_{light}", name, LIGHT_TITLES[light], flat=f"{name} {light}")
               for light in LIGHTS for name in ("Dx", "Dy", "Dz", "E")]
    columns += [Column("E_avg", "mean E"), Column("gmacs", "GMACs", digits=None, aggregated=False),
                Column("params_total_M", "params (M)", digits=None, aggregated=False),
                Column("latency_ms_1t", "latency (ms)", digits=None, aggregated=False)]
    smoothed = [Column(f"E_smooth_{light}", LIGHT_TITLES[light], "smoothed E", flat=f"smoothed E {light}")
                for light in LIGHTS]
    return columns + _present(stats, smoothed)  # only where smoothing ran


def _present(stats: pd.DataFrame, columns: list[Column]) -> list[Column]:
    return [column for column in columns if stats[f"{column.key}_mean"].notna().any()]


def _failed_note(row: pd.Series) -> str:
    who = row["method"] or row["model"] or row["kind"]
    seed = f", seed {plain_text(row['seed'])}" if plain_text(row["seed"]) else ""
    error = row["error"] or "no error recorded"
    where = f" (log: {row['log_path']})" if row["log_path"] else ""
    return f"{row['job_id']} ({row['status'] or 'no status'}) {who}{seed}: {error}{where}"


def _section_tables(number: int, title: str, rows: pd.DataFrame, stats: pd.DataFrame, protocol: str,
                    failed: pd.DataFrame, learning: str = "") -> list[Table]:
    leaky = f"; {LEAKY_TITLE}" if protocol == "random_windows" else ""
    has_constant = (stats["kind"] == "constant").any()
    alert = "" if has_constant else ("NO CONSTANT BASELINE: this table has no constant-position row, so it cannot "
                                     "show whether the models learned anything (run the suite's constant jobs).")
    main = Table(str(number), title, table_caption(rows, stats, protocol, learning), ["method", "category"],
                 _main_columns(stats), [], alert, [_failed_note(row) for _, row in failed.iterrows()])
    main.rows = _build_rows(stats, main.columns, lambda stat: [stat["display"], stat["category"]])
    tables = [main]
    breakdowns = (
        ("a", "E by drone", "per drone type",
         [Column(f"E_{light}_{drone}", drone, LIGHT_TITLES[light], flat=f"{drone} {light}")
          for light in LIGHTS for drone in DRONES]),
        ("b", "E by range", "per distance band of the drone from the rig origin",
         [Column(f"E_{light}_{band}", label, LIGHT_TITLES[light], flat=f"{label} {light}")
          for light in LIGHTS for band, label in RANGE_LABELS.items()]),
    )
    for letter, name, what, candidates in breakdowns:
        columns = _present(stats, candidates)
        if not columns:
            continue
        caption = (f"E (m; mean ± std over seeds) {what}, same runs as Table {number} (protocol {protocol}"
                   f"{leaky}). Best per column in bold, second underlined; the constant row does not compete.")
        table = Table(f"{number}{letter}", f"Table {number}{letter}: {name}, protocol {protocol}"
                      f"{f' ({LEAKY_TITLE})' if leaky else ''}", caption,
                      ["method"], columns, [], main.alert)
        table.rows = _build_rows(stats, columns, lambda stat: [stat["display"]])
        tables.append(table)
    return tables


def _section_order(key: tuple[str, str, str], first_seen: dict) -> tuple:
    suite, protocol, _ = key
    protocol_rank = PROTOCOLS.index(protocol) if protocol in PROTOCOLS else len(PROTOCOLS)
    return first_seen[("suite", suite)], protocol_rank, protocol, first_seen[key]


def build_sections(frame: pd.DataFrame, learning: pd.DataFrame | None = None, learning_source: str = ""
                   ) -> tuple[list[Section], pd.DataFrame]:
    """The sections (one per suite x protocol x data fingerprint) and the failed rows no section claims.

    ``learning``: a learning suite's rows (newest per job) read from ``learning_source``, stated in the captions.
    """
    ok = frame[frame["status"] == "ok"]
    entries = ok[ok["kind"].isin(["model", "constant", "bound"])]
    profiles = ok[ok["kind"] == "profile"]
    failed = frame[frame["status"] != "ok"]
    keys = list(zip(entries["suite"], entries["protocol"], entries["data_fingerprint"], strict=True))
    first_seen: dict = {}
    for index, (suite, protocol, fingerprint) in enumerate(keys):
        first_seen.setdefault(("suite", suite), index)
        first_seen.setdefault((suite, protocol, fingerprint), index)
    ordered = sorted(set(keys), key=lambda key: _section_order(key, first_seen))
    several_suites = len({suite for suite, _, _ in ordered}) > 1
    claimed = pd.Series(False, index=failed.index)
    sections = []
    for number, (suite, protocol, fingerprint) in enumerate(ordered, start=1):
        mask = ((entries["suite"] == suite) & (entries["protocol"] == protocol)
                & (entries["data_fingerprint"] == fingerprint))
        rows = entries[mask]
        same_protocol = [key for key in ordered if key[:2] == (suite, protocol)]
        mine = (failed["suite"] == suite) & (failed["protocol"] == protocol) & ~claimed
        if len(same_protocol) > 1:
            mine &= failed["data_fingerprint"] == fingerprint
        claimed |= mine
        same_suite = profiles["suite"] == suite  # a model's profile from this suite wins over other suites'
        stats = method_stats(rows, pd.concat([profiles[~same_suite], profiles[same_suite]]))
        title = f"Table {number}: protocol {protocol}"
        if protocol == "random_windows":
            title += f" ({LEAKY_TITLE})"
        title += f", {'/'.join(distinct_values(rows, 'data_kind')) or 'unknown'} data"
        if len(same_protocol) > 1:
            title += f" {fingerprint[:10] or '(no fingerprint)'}"
        if several_suites:
            title += f", suite {suite or '(none)'}"
        tables = _section_tables(number, title, rows, stats, protocol, failed[mine],
                                 learning_sentence(learning, stats, protocol, learning_source))
        sections.append(Section(number, suite, protocol, fingerprint, rows, stats, tables))
    return sections, failed[~claimed]


# ----------------------------------------------------------------------------------------------- documents


def _main_section(sections: Sequence[Section]) -> Section:
    return next((section for section in sections if section.protocol == "by_sequence"), sections[0])


def _csv_frame(sections: Sequence[Section]) -> pd.DataFrame:
    leading = ["table", "suite", "protocol", "data_fingerprint", "data_kind", "method", "model", "kind",
               "category", "alpha", "n_seeds", "seeds"]
    values = [f"{key}_{part}" for key in VALUE_KEYS for part in ("mean", "std")]
    frames = []
    for section in sections:
        stats = section.stats.assign(table=section.number, suite=section.suite, protocol=section.protocol,
                                     data_fingerprint=section.fingerprint,
                                     data_kind="/".join(distinct_values(section.rows, "data_kind")),
                                     method=section.stats["display"])
        frames.append(stats[leading + values + PROFILE_KEYS])
    return pd.concat(frames, ignore_index=True)


def _intro(source: str, frame: pd.DataFrame, sections: Sequence[Section], suite: str | None) -> str:
    ok = int((frame["status"] == "ok").sum())
    scope = f" (suite {suite})" if suite else ""
    return (f"Rendered from {source}{scope} alone: {len(frame)} jobs ({ok} ok, {len(frame) - ok} not ok), "
            f"{len(sections)} comparison table(s), one per protocol and data set; tables of different protocols "
            "are never mixed. Errors in metres, mean ± sample standard deviation over seeds; per numeric column "
            "the best value is bold and the second underlined (lower is better; the constant-position row is "
            "shown in every table and does not compete).")


def _markdown(intro: str, sections: Sequence[Section], orphans: Sequence[str], out: Path) -> str:
    parts = ["# Leaderboard", "", markdown_escape(intro), ""]
    for section in sections:
        for table in section.tables:
            parts += [markdown_table(table)]
        if section.plots:
            parts += [f"Plots of Table {section.number}:", ""]
            parts += [f"![{markdown_escape(plot.caption)}]({plot.path.relative_to(out).as_posix()})\n"
                      for plot in section.plots]
    if orphans:
        parts += ["## Failed jobs outside the tables", ""] + [f"- {markdown_escape(note)}" for note in orphans] + [""]
    return "\n".join(parts).rstrip("\n") + "\n"


def _latex(intro: str, sections: Sequence[Section], orphans: Sequence[str]) -> str:
    parts = ["% Leaderboard rendered from results.csv by 'aaute leaderboard'; needs \\usepackage{booktabs}.",
             f"% {intro}", ""]
    for section in sections:
        parts += [latex_table(table) for table in section.tables]
    if orphans:
        parts.append("% Failed jobs outside the tables: " + "; ".join(note.replace("\n", " ") for note in orphans))
    return "\n".join(parts)


def _html(intro: str, sections: Sequence[Section], orphans: Sequence[str], warnings: Sequence[str]) -> str:
    esc = html.escape
    body = ["<h1>Leaderboard</h1>", f"<p>{esc(intro)}</p>"]
    for section in sections:
        body += [html_table(table) for table in section.tables]
        for plot in section.plots:
            data = base64.b64encode(plot.png).decode("ascii")
            body.append(f'<figure><img alt="{esc(plot.caption)}" src="data:image/png;base64,{data}">'
                        f"<figcaption>{esc(plot.caption)}</figcaption></figure>")
    if orphans:
        body.append("<h2>Failed jobs outside the tables</h2><ul class=\"failed\">"
                    + "".join(f"<li>{esc(note)}</li>" for note in orphans) + "</ul>")
    if warnings:
        body.append('<h2>Skipped plots</h2><ul class="warnings">'
                    + "".join(f"<li>{esc(warning)}</li>" for warning in warnings) + "</ul>")
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n"
            f"<title>Leaderboard</title>\n<style>{CSS}</style>\n</head>\n<body>\n"
            + "\n".join(body) + "\n</body>\n</html>\n")


def _select(frame: pd.DataFrame, path: Path, suite: str | None) -> pd.DataFrame:
    if frame.empty:
        raise LeaderboardError(f"{path}: no result rows yet (run 'aaute benchmark' first)")
    if suite is not None:
        known = list(dict.fromkeys(frame["suite"]))
        if suite not in known:
            raise LeaderboardError(f"{path}: unknown suite {suite!r}; suites in this file: "
                                   f"{', '.join(repr(name) for name in known)}")
        frame = frame[frame["suite"] == suite]
    usable = frame[(frame["status"] == "ok") & frame["kind"].isin(["model", "constant"])]
    if usable.empty:
        failed = int((frame["status"] != "ok").sum())
        raise LeaderboardError(f"{path}: no successful model or constant rows to tabulate ({failed} job(s) not ok; "
                               "their rows name the error and the log)")
    return frame


def render_leaderboard(results: Path, out: Path, suite: str | None = None, plots: bool = True,
                       learning: Path | None = None) -> LeaderboardReport:
    """Render ``results`` (a results.csv) into ``out``: Markdown, CSV, LaTeX, one HTML page and PNG plots.

    Args:
        results: the results.csv written by ``aaute benchmark``.
        out: the output folder (created).
        suite: only this suite's rows (default: all, one table per suite x protocol x data fingerprint).
        plots: draw the figures (prediction files that are missing skip their plot with a warning).
        learning: a learning suite's results.csv (``configs/benchmark/learning.yaml``): each caption states
            the learning curves of its table's models (E at each data size against that data's constant), and
            the first table's plots end with their figure.

    Raises:
        ResultsError: the file is not a results.csv of this schema (missing columns, other version).
        LeaderboardError: nothing to render (no rows, no successful rows, unknown suite).
    """
    results, out = Path(results), Path(out)
    frame = _select(latest(read_results(results)), results, suite)
    curves = None
    if learning is not None:
        from benchmarks.learning import learning_plot, read_learning

        curves = read_learning(Path(learning))
    sections, orphans = build_sections(frame, curves, str(learning) if learning is not None else "")
    warnings: list[str] = []

    def warn(message: str) -> None:
        warnings.append(message)
        log.warning("%s", message)

    if plots:
        from benchmarks.plots import SectionPlotter  # matplotlib is imported only when plots are drawn

        plotter = SectionPlotter(results.parent, out / "plots", warn)
        main = _main_section(sections)
        for section in sections:
            section.plots = plotter.draw(section.stats, section.number, section.protocol, RANGE_LABELS,
                                         trajectories=section is main)
        if curves is not None:
            main.plots.append(learning_plot(curves, Path(learning), out / "plots"))
    orphan_notes = [_failed_note(row) for _, row in orphans.iterrows()]
    intro = _intro(results.name, frame, sections, suite)
    markdown = _markdown(intro, sections, orphan_notes, out)
    files = {"markdown": out / "leaderboard.md", "csv": out / "leaderboard.csv", "latex": out / "leaderboard.tex",
             "html": out / "leaderboard.html"}
    texts = {"markdown": markdown, "latex": _latex(intro, sections, orphan_notes),
             "csv": _csv_frame(sections).to_csv(index=False, float_format="%.6g", lineterminator="\n"),
             "html": _html(intro, sections, orphan_notes, warnings)}
    for name, path in files.items():
        with atomic_write(path) as tmp:
            tmp.write_text(texts[name], encoding="utf-8")
    plot_paths = [plot.path for section in sections for plot in section.plots]
    return LeaderboardReport(markdown, files, plot_paths, warnings)


# ----------------------------------------------------------------------------------------------- command line


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``aaute leaderboard``."""
    parser.add_argument("results", type=Path, help="results.csv written by 'aaute benchmark'")
    parser.add_argument("--out", type=Path, help="output folder (default: 'leaderboard' beside RESULTS)")
    parser.add_argument("--suite", help="only this suite's rows (default: every suite, each in its own tables)")
    parser.add_argument("--no-plots", action="store_true", help="write the tables only")
    parser.add_argument("--learning", type=Path, help="results.csv of a learning suite: each caption states its "
                        "models' learning curves (E per data size against that data's constant)")


def run(args: argparse.Namespace) -> int:
    """Render, print the Markdown tables and the HTML page's path; a bad input is one line and exit code 2."""
    out = args.out if args.out is not None else Path(args.results).parent / "leaderboard"
    try:
        report = render_leaderboard(args.results, out, suite=args.suite, plots=not args.no_plots,
                                    learning=args.learning)
    except (ResultsError, LeaderboardError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    sys.stdout.write(report.markdown)
    print(f"\nHTML page: {report.html}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="aaute leaderboard", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
