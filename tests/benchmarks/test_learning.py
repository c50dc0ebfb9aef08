"""Learning curves: the learning suite's shape (validated, not run) and the plot from a results.csv."""

from __future__ import annotations

import json

import pytest

from benchmarks.learning import curve_points, main
from benchmarks.results import append_rows, read_results
from benchmarks.suite import expand_jobs, load_suite
from tests.benchmarks.test_leaderboard import PROVENANCE, bound_row
from tests.helpers.suites import REPO


def test_the_learning_suite_trains_four_models_at_nested_data_sizes():
    jobs = [job for job in expand_jobs(load_suite(REPO / "configs" / "benchmark" / "learning.yaml"))
            if job.kind == "model"]
    sizes: dict[str, set[int]] = {}
    for job in jobs:
        args = job.cli_args
        split = json.loads([args[i + 1] for i, arg in enumerate(args) if arg == "--data.split"][-1])  # the last wins
        sizes.setdefault(job.model, set()).add(split["train_flights"])
        assert split["protocol"] == "by_sequence"
    assert set(sizes) == {"student", "phase_student", "audionet", "visualnet"}
    assert all(len(flights) >= 3 for flights in sizes.values())
    assert {job.kind for job in expand_jobs(load_suite(REPO / "configs" / "benchmark" / "learning.yaml"))} >= {
        "constant", "bound"}


def _model(model: str, flights: int, windows: int, error: float, seed: int = 0) -> dict:
    return {**PROVENANCE, "kind": "model", "job_id": f"{model}_f{flights}-by_sequence-s{seed}", "model": model,
            "method": f"{model}, {flights} flights", "category": "supervised", "protocol": "by_sequence",
            "seed": seed, "n_train_sequences": flights, "n_train_windows": windows, "E_ideal": error,
            "E_dark": error}


def test_curves_group_by_model_and_size_and_draw_the_references(tmp_path, capsys):
    rows = [_model("student", 2, 180, 9.0), _model("student", 2, 180, 8.0, seed=1), _model("student", 10, 900, 6.0),
            _model("audionet", 2, 180, 11.0), _model("audionet", 10, 900, 11.2),
            {**PROVENANCE, "kind": "constant", "job_id": "constant_gt-by_sequence-s0", "model": "constant",
             "method": "Constant (mean train GT)", "category": "reference", "protocol": "by_sequence", "seed": 0,
             "E_ideal": 11.5, "E_dark": 11.5}, bound_row()]
    results = tmp_path / "results.csv"
    append_rows(results, rows)
    points = curve_points(read_results(results))
    student = points[points["model"] == "student"].set_index("flights")
    assert student.loc[2, "E"] == pytest.approx(8.5) and student.loc[2, "seeds"] == 2
    assert student.loc[10, "windows"] == 900
    out = tmp_path / "plots" / "learning.png"
    assert main([str(results), "--out", str(out)]) == 0
    assert out.read_bytes().startswith(b"\x89PNG")
    printed = capsys.readouterr().out
    assert "student" in printed and "audionet" in printed


def test_no_model_rows_is_one_line_and_exit_2(tmp_path, capsys):
    results = tmp_path / "results.csv"
    append_rows(results, [bound_row()])
    assert main([str(results), "--out", str(tmp_path / "x.png")]) == 2
    assert capsys.readouterr().err.count("\n") == 1
