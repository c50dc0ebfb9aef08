"""The leaderboard: tables from results.csv alone, ranking marks, formats, plots and bad input.

The Markdown output of a small fixed results.csv is compared with ``golden/leaderboard.md``. After an
intended change of the layout, regenerate it with
``AAUTE_UPDATE_GOLDEN=1 .venv/bin/pytest tests/benchmarks/test_leaderboard.py -q`` and review the diff.
"""

from __future__ import annotations

import base64
import csv
import math
import os
import re
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from benchmarks import leaderboard, tables
from benchmarks.results import COLUMNS, append_rows

GOLDEN = Path(__file__).parent / "golden" / "leaderboard.md"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

PROVENANCE = {
    "suite": "demo", "status": "ok", "data": "simulated MMAUD-like, 10 flights", "data_kind": "simulated",
    "data_fingerprint": "fp-sim-0001", "drones": "avata,m300", "lights": "ideal,dark",
    "n_train_sequences": 6, "n_val_sequences": 2, "n_test_sequences": 2,
    "n_train_windows": 600, "n_val_windows": 200, "n_test_windows": 200,
    "git_commit": "0123456789abcdef0123", "git_dirty": True, "versions": "torch 2.9.1; lightning 2.6.0",
    "cpu": "Test CPU @ 2 GHz", "gpu": "", "threads": 2, "launcher": "local", "started_at": "2025-01-01T00:00:00",
}
BUDGET = {"max_epochs": 5, "limit_train_batches": 10, "epochs_run": 5, "best_epoch": 4, "batch_size": 16,
          "budget_note": "image 64x64 behind the reduced-size adapter (reference 256x256)"}
METHODS = {  # model -> (method, category, alpha)
    "student": ("Ours (student)", "self-supervised", 1.0),
    "audionet": ("AudioNet", "supervised", 0.0),
    "visualnet": ("VisualNet", "supervised", 0.0),
    "avfdti": ("AV-FDTI", "supervised", 0.0),
    "srp_phat": ("SRP_PHAT (grid 1 m, 100% of pairs)", "non-learned", None),
    "constant": ("Constant (mean train GT)", "reference", None),
}


def result(model: str, protocol: str, seed: int, e_ideal: float, e_dark: float, dx_ideal: float | None = None,
           **extra) -> dict:
    """A model or constant row: Dx/Dy/Dz derived from E unless given."""
    method, category, alpha = METHODS[model]
    row = {**PROVENANCE, "kind": "constant" if model == "constant" else "model",
           "job_id": f"{model}-{protocol}-s{seed}", "model": model, "method": method, "category": category,
           "alpha": alpha, "protocol": protocol, "seed": seed}
    if model != "constant":
        row.update(BUDGET)
    for light, error in (("ideal", e_ideal), ("dark", e_dark)):
        row.update({f"Dx_{light}": 0.5 * error, f"Dy_{light}": 0.6 * error, f"Dz_{light}": 0.3 * error,
                    f"E_{light}": error, f"RMSE_{light}": 1.2 * error})
    if dx_ideal is not None:
        row["Dx_ideal"] = dx_ideal
    row.update({"E_ideal_avata": e_ideal * 0.9, "E_ideal_m300": e_ideal * 1.1,
                "E_ideal_r0_10": e_ideal * 0.8, "E_ideal_r10_20": e_ideal * 1.2})
    row.update(extra)
    return row


def profile(model: str, gmacs: float, params: float, latency: float) -> dict:
    return {**PROVENANCE, "kind": "profile", "job_id": f"profile-{model}", "model": model,
            "method": METHODS[model][0], "category": METHODS[model][1], "params_total_M": params,
            "params_used_M": params, "gmacs": gmacs, "gflops": 2 * gmacs, "latency_ms_1t": latency,
            "profile_inputs": "audio_mel 4x64x64"}


def bound_row() -> dict:
    """The physical limit (CRLB) of the by_sequence windows, below every method."""
    row = {**PROVENANCE, "kind": "bound", "job_id": "bound-by_sequence-s0", "model": "crlb",
           "method": "Physical limit (CRLB)", "category": "reference", "protocol": "by_sequence", "seed": 0,
           "bound_median_m": 0.21, "snr_source": "simulator", "bound_band_hz": "full",
           "predictions_path": "pred/bound.csv"}
    for light in ("ideal", "dark"):
        row.update({f"E_{light}": 0.3, f"RMSE_{light}": 0.3})
    row.update({"E_ideal_avata": 0.25, "E_ideal_m300": 0.35, "E_ideal_r0_10": 0.2, "E_ideal_r10_20": 0.4})
    return row


def fixture_rows() -> list[dict]:
    """Two protocols, two seeds of the student, a constant per protocol, the CRLB, profiles and one failed job."""
    return [
        bound_row(),
        result("student", "by_sequence", 0, 1.0, 1.1, E_smooth_ideal=0.9, predictions_path="pred/student-s0.csv"),
        result("student", "by_sequence", 1, 1.5, 1.7, E_smooth_ideal=1.3, predictions_path="pred/student-s1.csv"),
        result("audionet", "by_sequence", 0, 2.0, 2.0, predictions_path="pred/audionet-s0.csv"),
        result("visualnet", "by_sequence", 0, 1.8, 6.0),
        result("srp_phat", "by_sequence", 0, 3.0, 3.0),  # no profile row: its GMACs stay empty
        result("constant", "by_sequence", 0, 5.0, 5.0, dx_ideal=0.1, predictions_path="pred/constant.csv"),
        {**PROVENANCE, "kind": "model", "job_id": "avfdti-by_sequence-s0", "status": "failed", "model": "avfdti",
         "method": "AV-FDTI", "category": "supervised", "protocol": "by_sequence", "seed": 0,
         "error": "RuntimeError: CUDA out of memory", "log_path": "logs/avfdti-by_sequence-s0.log"},
        result("student", "random_windows", 0, 0.5, 0.5),
        result("audionet", "random_windows", 0, 0.7, 0.7),
        result("constant", "random_windows", 0, 4.0, 4.0),
        profile("student", 0.25, 2.23, 1.5),
        profile("audionet", 0.08, 1.448, 0.9),
        profile("visualnet", 5.4, 31.18, 12.0),
    ]


def write_predictions(path: Path, offset: float, constant: bool = False, smooth: bool = False) -> None:
    """Per-window predictions of two flights (avata, m300) on circles; the estimate is GT + ``offset``."""
    frames = []
    for index, drone in enumerate(("avata", "m300")):
        t = np.arange(30) * 0.1
        gt = np.stack([5 + 3 * np.cos(t + index), 8 + 3 * np.sin(t + index), 2 + 0.2 * t], axis=1)
        estimate = np.tile(gt.mean(axis=0), (len(t), 1)) if constant else gt + offset
        frame = pd.DataFrame({"sequence_id": f"seq-{drone}", "recording_id": f"rec-{drone}", "drone": drone,
                              "light": "ideal", "timestamp": 100.0 + t, "x": estimate[:, 0], "y": estimate[:, 1],
                              "z": estimate[:, 2], "gt_x": gt[:, 0], "gt_y": gt[:, 1], "gt_z": gt[:, 2],
                              "gt_valid": 1})
        for axis, column in enumerate("xyz"):
            frame[f"smooth_{column}"] = gt[:, axis] + offset / 2 if smooth else np.nan
        frames.append(frame)
    path.parent.mkdir(parents=True, exist_ok=True)
    pd.concat(frames).to_csv(path, index=False)


def write_fixture(folder: Path) -> Path:
    path = folder / "results.csv"
    append_rows(path, fixture_rows())
    write_predictions(folder / "pred" / "student-s0.csv", 0.8, smooth=True)
    write_predictions(folder / "pred" / "constant.csv", 0.0, constant=True)
    write_predictions(folder / "pred" / "bound.csv", 0.0)
    bounds = pd.read_csv(folder / "pred" / "bound.csv")
    bounds["bound_m"] = np.linspace(0.1, 0.5, len(bounds))
    bounds[["x", "y", "z"]] = np.nan
    bounds.to_csv(folder / "pred" / "bound.csv", index=False)
    return path  # audionet-s0.csv and student-s1.csv are left missing on purpose


@pytest.fixture()
def results_csv(tmp_path) -> Path:
    """The fixed results.csv, for tests that change it."""
    return write_fixture(tmp_path / "run")


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> leaderboard.LeaderboardReport:
    """The fixed results.csv rendered once with plots (the tests below only read the outputs)."""
    folder = tmp_path_factory.mktemp("leaderboard")
    return leaderboard.render_leaderboard(write_fixture(folder / "run"), folder / "board")


def markdown_grid(markdown: str, title_start: str) -> dict[str, dict[str, str]]:
    """The grid of the Markdown table whose heading starts with ``title_start``: method -> header -> cell."""
    section = markdown.split(f"## {title_start}", 1)[1].split("\n## ", 1)[0]
    lines = [line for line in section.splitlines() if line.startswith("| ")]
    headers = [cell.strip() for cell in lines[0].strip("|").split(" | ")]
    grid = {}
    for line in lines[1:]:
        cells = [cell.strip() for cell in line.strip().strip("|").split(" | ")]
        grid[cells[0]] = dict(zip(headers, cells, strict=True))
    return grid


def test_markdown_matches_golden(report):
    if os.environ.get("AAUTE_UPDATE_GOLDEN") == "1":
        GOLDEN.parent.mkdir(parents=True, exist_ok=True)
        GOLDEN.write_text(report.markdown)
    assert GOLDEN.is_file(), f"no golden file; create it with AAUTE_UPDATE_GOLDEN=1 ({__doc__.splitlines()[3]})"
    assert report.markdown == GOLDEN.read_text(), (
        "Markdown differs from tests/benchmarks/golden/leaderboard.md; if the change is intended, regenerate "
        "it with AAUTE_UPDATE_GOLDEN=1 .venv/bin/pytest tests/benchmarks/test_leaderboard.py and review the diff")
    assert report.files["markdown"].read_text() == report.markdown


def test_best_bold_second_underlined_and_constant_not_ranked(report):
    grid = markdown_grid(report.markdown, "Table 1:")
    srp = "SRP_PHAT (grid 1 m, 100% of pairs)"
    assert list(grid) == ["VisualNet", "AudioNet", "Ours (student)", srp, "Physical limit (CRLB)",
                          "Constant (mean train GT)"]  # paper order, references last
    assert grid["Ours (student)"]["E ideal"] == "**1.25 ± 0.35**"
    assert grid["VisualNet"]["E ideal"] == "<u>1.80</u>"
    assert grid["AudioNet"]["E ideal"] == "2.00"
    assert grid["AudioNet"]["E dark"] == "<u>2.00</u>"  # VisualNet is worst in the dark
    assert grid["AudioNet"]["GMACs"] == "**0.0800**"
    assert grid["Ours (student)"]["GMACs"] == "<u>0.250</u>"
    # the constant has the lowest Dx but does not compete: the best model's Dx is bold, the constant's plain
    assert grid["Constant (mean train GT)"]["Dx ideal"] == "0.10"
    assert grid["Ours (student)"]["Dx ideal"].startswith("**")
    assert grid["Constant (mean train GT)"]["GMACs"] == tables.MISSING
    assert grid[srp]["GMACs"] == tables.MISSING and grid[srp]["E dark"] == "3.00"
    assert grid["Ours (student)"]["smoothed E ideal"] == "1.10 ± 0.28"  # the only smoothed row: nothing to rank
    assert grid["AudioNet"]["smoothed E ideal"] == tables.MISSING


def test_mean_and_std_over_seeds_are_right(report):
    board = pd.read_csv(report.files["csv"])
    student = board[(board["model"] == "student") & (board["protocol"] == "by_sequence")].iloc[0]
    assert student["n_seeds"] == 2
    assert student["E_ideal_mean"] == pytest.approx(1.25)
    assert student["E_ideal_std"] == pytest.approx(math.sqrt(((1.0 - 1.25) ** 2 + (1.5 - 1.25) ** 2) / 1), rel=1e-5)
    # mean E per seed: (1.0 + 1.1) / 2 = 1.05 and (1.5 + 1.7) / 2 = 1.6
    assert student["E_avg_mean"] == pytest.approx(1.325)
    assert student["E_avg_std"] == pytest.approx(0.55 / math.sqrt(2), rel=1e-5)
    assert student["gmacs"] == pytest.approx(0.25)
    assert len(board) == 6 + 3  # one row per method x protocol
    constant = board[board["kind"] == "constant"]
    assert set(constant["protocol"]) == {"by_sequence", "random_windows"}
    assert constant["gmacs"].isna().all()
    assert "(1 seed per method, except Ours (student) 2)" in report.markdown


def test_protocols_in_separate_tables_with_a_constant_row_each(report):
    markdown = report.markdown
    titles = re.findall(r"^## (Table \d+: .*)$", markdown, flags=re.MULTILINE)
    assert titles[0].startswith("Table 1: protocol by_sequence")
    leaky = [title for title in titles if "random_windows" in title and title.startswith("Table 2:")]
    assert leaky and "leaky: test windows overlap training windows" in leaky[0]
    first, second = markdown_grid(markdown, "Table 1:"), markdown_grid(markdown, "Table 2:")
    assert "Constant (mean train GT)" in first and "Constant (mean train GT)" in second
    assert "VisualNet" not in second  # no by_sequence row leaks into the random_windows table
    assert second["Ours (student)"]["E ideal"] == "**0.50**"
    table2 = markdown.split("## Table 2:", 1)[1].split("\n## ", 1)[0]
    assert "test windows overlap training windows" in table2.split("|", 1)[0]  # in the caption too
    assert "no constant baseline" not in markdown.lower()
    assert "CUDA out of memory" in markdown.split("## Table 1:", 1)[1].split("## Table 1a", 1)[0]  # failed job
    for table in ("Table 1a: E by drone", "Table 1b: E by range"):
        grid = markdown_grid(markdown, table)
        assert "Constant (mean train GT)" in grid and grid["Ours (student)"]


def test_caption_states_data_budget_seeds_machine_and_commit(report):
    caption = report.markdown.split("## Table 1:", 1)[1].split("| method", 1)[0]
    for fact in ("simulated", "6/2/2", "avata,m300", "ideal,dark", "max epochs 5", "batch size 16",
                 "reduced-size adapter", "reference input shapes", "Seeds 0, 1", "Test CPU @ 2 GHz", "threads 2",
                 "0123456789ab (dirty working tree)", "torch 2.9.1"):
        assert fact in caption, fact


def test_caption_names_the_smoother_of_each_method(tmp_path):
    rows = [result("student", "by_sequence", 0, 1.0, 1.1, E_smooth_ideal=0.9, smoother="robust"),
            result("srp_phat", "by_sequence", 0, 3.0, 3.0, E_smooth_ideal=2.9, smoother="tuned"),
            result("constant", "by_sequence", 0, 5.0, 5.0)]
    path = tmp_path / "results.csv"
    append_rows(path, rows)
    caption = leaderboard.render_leaderboard(path, tmp_path / "board", plots=False).markdown.split("| method")[0]
    assert ("Smoothed E: the robust Student-t state-space smoother (preset robust) for Ours (student); "
            "the tuned Matérn GP (preset tuned) for SRP_PHAT") in caption
    append_rows(path, [{**rows[1], "smoother": "robust"}])  # the newest row of a job counts
    caption = leaderboard.render_leaderboard(path, tmp_path / "board2", plots=False).markdown.split("| method")[0]
    assert "Smoothed E: the robust Student-t state-space smoother (preset robust)." in caption


def test_missing_constant_is_said_loudly(tmp_path):
    path = tmp_path / "results.csv"
    append_rows(path, [row for row in fixture_rows() if row["kind"] != "constant"])
    report = leaderboard.render_leaderboard(path, tmp_path / "board", plots=False)
    for table in ("Table 1:", "Table 2:"):
        section = report.markdown.split(f"## {table}", 1)[1].split("| method", 1)[0]
        assert "NO CONSTANT BASELINE" in section


def test_latex_is_booktabs_and_escaped(report):
    tex = report.files["latex"].read_text()
    assert "\\toprule" in tex and "\\midrule" in tex and "\\bottomrule" in tex
    assert "by\\_sequence" in tex and "random\\_windows" in tex
    for line in tex.splitlines():
        if not line.startswith("%"):
            for cell in line.removesuffix(" \\\\").split(" & "):
                assert not re.search(r"(?<!\\)[_%&#]", cell), f"unescaped character in LaTeX: {line}"
    assert "SRP\\_PHAT (grid 1 m, 100\\% of pairs)" in tex
    assert "\\textbf{1.25 $\\pm$ 0.35}" in tex and "\\underline{1.80}" in tex
    assert "\\multicolumn{4}{c}{ideal light}" in tex and "\\multicolumn{4}{c}{darkness}" in tex
    assert tables.latex_escape("50% a_b & #1 {x} $~^\\") == (
        "50\\% a\\_b \\& \\#1 \\{x\\} \\$\\textasciitilde{}\\textasciicircum{}\\textbackslash{}")


def test_html_is_self_contained_with_embedded_plots(report):
    page = report.html.read_text()
    assert 'src="http' not in page and "<script" not in page and "<link" not in page and "url(" not in page
    sources = re.findall(r'<img [^>]*src="([^"]+)"', page)
    assert len(sources) == len(report.plots) > 0
    assert all(source.startswith("data:image/png;base64,") for source in sources)
    assert base64.b64decode(sources[0].split(",", 1)[1])[:8] == PNG_MAGIC
    assert "<b>1.25&nbsp;±&nbsp;0.35</b>" in page and "<u>1.80</u>" in page
    assert page.count("<table>") == report.markdown.count("\n| method")


def test_plots_written_and_missing_predictions_warned(report):
    names = {path.name for path in report.plots}
    assert {"trajectory_avata.png", "trajectory_m300.png", "t1_error_cdf.png", "t1_error_vs_gmacs.png",
            "t1_error_by_range.png"} <= names
    for path in report.plots:
        assert path.parent.name == "plots" and path.read_bytes()[:8] == PNG_MAGIC
    assert any("error CDF (Table 1): left out" in warning and "audionet-s0.csv: predictions file not found"
               in warning for warning in report.warnings)
    assert any("error CDF (Table 2) skipped" in warning for warning in report.warnings)  # no files there


def test_trajectory_plots_draw_the_best_method_of_each_category(results_csv, tmp_path):
    frame = pd.read_csv(results_csv)
    frame.loc[frame["job_id"] == "srp_phat-by_sequence-s0", "predictions_path"] = "pred/srp_phat-s0.csv"
    frame.to_csv(results_csv, index=False)
    write_predictions(results_csv.parent / "pred" / "srp_phat-s0.csv", 2.0)
    report = leaderboard.render_leaderboard(results_csv, tmp_path / "board")
    caption = report.markdown.split("![Estimated and true trajectory of one test flight of the avata", 1)[1]
    caption = caption.split("](plots/", 1)[0]
    # the best self-supervised (student, seed 0) before the best non-learned; VisualNet, the best supervised
    # model, has no predictions and AudioNet's file is missing: both are left out with a warning
    assert "Ours (student) (seed 0), SRP_PHAT (grid 1 m, 100% of pairs) (seed 0)" in caption
    for name in ("VisualNet", "AudioNet"):
        assert any(f"trajectory plots (Table 1): {name} left out" in warning for warning in report.warnings)


def test_missing_prediction_files_skip_plots_not_tables(results_csv, tmp_path, caplog):
    for path in (results_csv.parent / "pred").glob("*.csv"):
        path.unlink()
    with caplog.at_level("WARNING", logger="benchmarks.leaderboard"):
        report = leaderboard.render_leaderboard(results_csv, tmp_path / "board")
    assert not any(path.name.startswith("trajectory") or "cdf" in path.name for path in report.plots)
    assert any("trajectory plots (Table 1) skipped" in record.getMessage() for record in caplog.records)
    assert all(path.is_file() for path in report.files.values())
    assert "**1.25 ± 0.35**" in report.markdown


def test_suite_filter_and_several_suites(results_csv, tmp_path):
    other = [{**row, "suite": "other", "job_id": row["job_id"] + "-o"} for row in fixture_rows()[:5]]
    append_rows(results_csv, other)
    both = leaderboard.render_leaderboard(results_csv, tmp_path / "both", plots=False)
    assert "suite other" in both.markdown and "suite demo" in both.markdown  # never merged as extra seeds
    only = leaderboard.render_leaderboard(results_csv, tmp_path / "only", suite="other", plots=False)
    assert len(re.findall(r"^## Table \d+:", only.markdown, flags=re.MULTILINE)) == 1


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = leaderboard.main([str(arg) for arg in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_cli_prints_tables_and_html_path(results_csv, tmp_path, capsys):
    code, out, _ = run_cli(capsys, results_csv, "--out", tmp_path / "cli", "--no-plots")
    assert code == 0
    assert "## Table 1: protocol by_sequence" in out
    assert str(tmp_path / "cli" / "leaderboard.html") in out


def rewrite(path: Path, change) -> None:
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    with open(path, "w", newline="") as handle:
        csv.writer(handle, lineterminator="\n").writerows(change(rows))


@pytest.mark.parametrize(("case", "message"), [
    ("schema", "schema version"), ("columns", "missing column"), ("empty", "empty file"),
    ("header", "no result rows"), ("failed", "no successful model or constant rows"), ("suite", "unknown suite"),
    ("inf", "line 2, column E_ideal: 'inf' is not a finite number >= 0"),
    ("negative", "line 2, column E_ideal: '-0.5' is not a finite number >= 0"),
    ("text", "line 2, column E_ideal: 'n/a' is not a finite number >= 0"),
])
def test_bad_input_is_one_line_and_exit_code_2(results_csv, tmp_path, capsys, case, message):
    argv = [results_csv, "--out", tmp_path / "bad", "--no-plots"]
    if case == "schema":
        rewrite(results_csv, lambda rows: [rows[0]] + [["99", *row[1:]] for row in rows[1:]])
    elif case == "columns":
        rewrite(results_csv, lambda rows: [row[: COLUMNS.index("E_ideal")] for row in rows])
    elif case == "empty":
        results_csv.write_text("")
    elif case == "header":
        rewrite(results_csv, lambda rows: rows[:1])
    elif case == "failed":
        status = COLUMNS.index("status")
        rewrite(results_csv, lambda rows: [rows[0]] + [[*row[:status], "failed", *row[status + 1:]]
                                                       for row in rows[1:]])
    elif case in ("inf", "negative", "text"):  # never shown as missing nor ranked as best
        cell = {"inf": "inf", "negative": "-0.5", "text": "n/a"}[case]
        at = COLUMNS.index("E_ideal")
        rewrite(results_csv, lambda rows: [rows[0], [*rows[1][:at], cell, *rows[1][at + 1:]], *rows[2:]])
    else:
        argv += ["--suite", "nope"]
    code, out, err = run_cli(capsys, *argv)
    assert code == 2 and out == ""
    assert err.startswith("error: ") and err.count("\n") == 1 and message in err
    assert not (tmp_path / "bad" / "leaderboard.md").exists()


def synthetic_results(path: Path, n_rows: int, seed: int = 0, predictions: bool = True) -> None:
    """A results.csv of about ``n_rows`` rows: 3 protocols x 9 methods x many seeds, profiles, failures."""
    rng = np.random.default_rng(seed)
    models = ["visualnet", "darknet", "audionet", "voranet", "asdnet", "avped", "avfdti", "student", "constant"]
    rows = [profile("audionet", 0.08 + i, 1.0 + i, 1.0 + i) | {"model": name, "job_id": f"profile-{name}"}
            for i, name in enumerate(models[:-1])]
    seeds = max(1, (n_rows - len(rows)) // (3 * len(models)))
    for protocol in ("by_sequence", "time_blocks", "random_windows"):
        for index, model in enumerate(models):
            method, category, alpha = METHODS.get(model, (model.title(), "supervised", 0.0))
            for s in range(seeds):
                error = 1.0 + index * 0.3 + rng.normal(0, 0.1)
                row = result("audionet", protocol, s, error, error * 1.2, E_smooth_ideal=error * 0.9)
                row.update(model=model, method=method, category=category, alpha=alpha,
                           kind="constant" if model == "constant" else "model", job_id=f"{model}-{protocol}-s{s}")
                if s == 0 and predictions:
                    row["predictions_path"] = f"pred/{model}-{protocol}.csv"
                    write_predictions(path.parent / row["predictions_path"], 0.1 * index, constant=model == "constant")
                if s == 1 and index == 0:
                    row.update(status="failed", error="killed")
                rows.append(row)
    append_rows(path, rows)


@pytest.mark.slow
def test_thousand_row_results_render(tmp_path, capsys):
    path = tmp_path / "results.csv"
    synthetic_results(path, 1000)
    assert 900 <= len(pd.read_csv(path)) <= 1100
    start = time.perf_counter()
    code, out, _ = run_cli(capsys, path, "--out", tmp_path / "board")
    seconds = time.perf_counter() - start
    assert code == 0 and out.count("## Table") >= 9
    print(f"\naaute leaderboard on a {len(pd.read_csv(path))}-row results.csv: {seconds:.2f} s")  # noqa: T201


def test_the_physical_limit_is_in_every_table_of_its_protocol_and_never_ranked(report):
    limit = "Physical limit (CRLB)"
    main = markdown_grid(report.markdown, "Table 1:")
    assert main[limit]["E ideal"] == "0.30" and main[limit]["Dx ideal"] == tables.MISSING
    assert main["Ours (student)"]["E ideal"] == "**1.25 ± 0.35**"  # the lower bound does not take the bold
    by_drone, by_range = markdown_grid(report.markdown, "Table 1a:"), markdown_grid(report.markdown, "Table 1b:")
    assert by_drone[limit]["avata ideal"] == "0.25" and by_range[limit]["0–10 m ideal"] == "0.20"
    assert "median 0.21 m" in report.markdown.split("## Table 1:", 1)[1].split("## Table 1a", 1)[0]
    assert limit not in markdown_grid(report.markdown, "Table 2:")  # its own protocol only
    assert "the black line is the per-window physical limit (CRLB)" in report.markdown  # figure captions
    assert "the black line is the physical limit (CRLB, RMS per band)" in report.markdown


def test_a_detecting_methods_detections_are_dots_on_its_trajectory(results_csv, tmp_path):
    from benchmarks.plots import read_predictions, trajectory_figure

    path = results_csv.parent / "pred" / "srp_phat-s0.csv"
    write_predictions(path, 2.0)
    table = pd.read_csv(path)
    table["detected"] = (np.arange(len(table)) % 3 == 0).astype(int)  # the others held or fallen back
    table.to_csv(path, index=False)
    flight = read_predictions(path).query("drone == 'avata'")
    figure = trajectory_figure([("SRP-PHAT", flight)], None, "one flight")
    lines = {line.get_label(): line for line in figure.axes[0].get_lines()}
    assert len(lines["SRP-PHAT"].get_xdata()) == len(flight)
    assert len(lines["SRP-PHAT, detected"].get_xdata()) == int(flight["detected"].sum()) < len(flight)
    frame = pd.read_csv(results_csv)
    frame.loc[frame["job_id"] == "srp_phat-by_sequence-s0", "predictions_path"] = "pred/srp_phat-s0.csv"
    frame.to_csv(results_csv, index=False)
    report = leaderboard.render_leaderboard(results_csv, tmp_path / "board")
    assert "Dots mark the windows SRP_PHAT (grid 1 m, 100% of pairs) detected the drone in" in report.markdown
