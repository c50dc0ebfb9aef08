"""Learning curves: the learning suite's shape (validated, not run) and the plot from a results.csv."""

from __future__ import annotations

import json

import pandas as pd
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


def learning_rows() -> list[dict]:
    """A learning suite's rows: the student never below the constant, AudioNet clearly below it at one size and
    just below it (by less than the margin) at another."""
    curve = {"student": (14.7, 13.5, 12.8), "audionet": (12.3, 10.8, 11.2), "phase_student": (10.2, 8.8, 7.8)}
    rows = [_model(model, flights, flights * 90, error) for model, errors in curve.items()
            for flights, error in zip((2, 5, 20), errors, strict=True)]
    rows += [{**_model("visualnet", flights, flights * 20, error), "E_dark": error * 0.99}  # it never sees the drone
             for flights, error in ((2, 18.2), (5, 12.0))]
    rows.append({**PROVENANCE, "kind": "constant", "job_id": "constant_gt-by_sequence-s0", "model": "constant",
                 "method": "Constant (mean train GT)", "category": "reference", "protocol": "by_sequence",
                 "seed": 0, "E_ideal": 11.5, "E_dark": 11.5})
    return [{**row, "suite": "learning", "data": "30 flights"} for row in [*rows, bound_row()]]


def test_the_table_caption_states_the_learning_curves_of_its_models(tmp_path, capsys):
    from benchmarks.leaderboard import main as leaderboard_main
    from tests.benchmarks.test_leaderboard import write_fixture

    learning = tmp_path / "learning" / "results.csv"
    append_rows(learning, learning_rows())
    results = write_fixture(tmp_path / "run")
    assert leaderboard_main([str(results), "--out", str(tmp_path / "board"), "--no-plots",
                             "--learning", str(learning)]) == 0
    markdown = (tmp_path / "board" / "leaderboard.md").read_text()
    first, second = markdown.split("## Table 2", 1)
    caption = first.split("## Table 1:", 1)[1].split("\n| ", 1)[0]
    assert f"Learning curves ({learning}, suite learning at commit 0123456: 30 flights; protocol by_sequence" in caption
    assert "constant (mean train GT) 11.50 m, physical limit (CRLB, RMS) 0.30 m" in caption
    assert ("Ours (student) 14.70 m at 180 windows to 12.80 m at 1800 (best 12.80 m at 1800, 1.11 × the constant): "
            "at no size more than 5 % below the constant") in caption
    assert ("AudioNet 12.30 m at 180 windows to 11.20 m at 1800 (best 10.80 m at 450, 0.94 × the constant): more "
            "than 5 % below the constant at 450 windows;") in caption
    assert ("VisualNet 18.20 m at 40 windows to 12.00 m at 100 (best 12.00 m at 100, 1.04 × the constant): at no "
            "size more than 5 % below the constant, in darkness 11.88 m at 100 windows (0.99 × its E in ideal light)"
            ) in caption
    assert "AudioNet" in caption and "in darkness" not in caption.split("AudioNet", 1)[1].split(";")[0]
    assert "phase_student" not in caption  # not a row of this table
    assert "Learning curves" not in second  # the learning suite's protocol is by_sequence alone
    plain = tmp_path / "plain"
    assert leaderboard_main([str(results), "--out", str(plain), "--no-plots"]) == 0
    assert "Learning curves" not in (plain / "leaderboard.md").read_text()
    capsys.readouterr()


def test_a_learning_file_without_model_rows_is_one_line_and_exit_2(tmp_path, capsys):
    from benchmarks.leaderboard import main as leaderboard_main
    from tests.benchmarks.test_leaderboard import write_fixture

    learning = tmp_path / "learning.csv"
    append_rows(learning, [bound_row()])
    code = leaderboard_main([str(write_fixture(tmp_path / "run")), "--out", str(tmp_path / "b"), "--no-plots",
                             "--learning", str(learning)])
    error = capsys.readouterr().err
    assert code == 2 and error.count("\n") == 1 and "no successful model rows" in error


def test_the_first_table_plots_end_with_the_learning_curves_named_by_their_file(tmp_path):
    from benchmarks.leaderboard import render_leaderboard
    from tests.benchmarks.test_leaderboard import write_fixture

    learning = tmp_path / "learning" / "results.csv"
    append_rows(learning, learning_rows())
    report = render_leaderboard(write_fixture(tmp_path / "run"), tmp_path / "board", learning=learning)
    figure = tmp_path / "board" / "plots" / "learning_curves.png"
    assert figure in report.plots and figure.read_bytes().startswith(b"\x89PNG")
    table_1_plots = report.markdown.split("Plots of Table 1:", 1)[1].split("## Table 2", 1)[0]
    assert table_1_plots.rstrip().endswith("(plots/learning_curves.png)")
    assert f"Learning curves ({learning}, suite learning at commit 0123456)" in table_1_plots
    plain = render_leaderboard(write_fixture(tmp_path / "run2"), tmp_path / "plain")
    assert not any(path.name == "learning_curves.png" for path in plain.plots)


@pytest.mark.parametrize("own_run", [False, True])
def test_make_demo_states_this_machines_learning_curves_else_the_kept_ones(tmp_path, own_run):
    import subprocess

    out = tmp_path / "demo_out"
    if own_run:
        append_rows(out / "learning" / "results.csv", learning_rows())
    dry_run = subprocess.run(["make", "-n", "demo", f"DEMO_OUT={out}"], cwd=REPO, capture_output=True, text=True,
                             check=True).stdout
    leaderboard = next(line for line in dry_run.splitlines() if "aaute leaderboard" in line)
    expected = out / "learning" / "results.csv" if own_run else "results/learning.csv"
    assert leaderboard.endswith(f"--learning {expected}")


def test_the_kept_learning_run_is_a_clean_run_of_the_suite_and_the_readme_quotes_it():
    """results/learning.csv (what make demo states without a run of its own): every model at three or more
    sizes, the constant and the bound, one clean commit; the README's table gives its figures."""
    import re

    from benchmarks.learning import read_learning, reference_level

    frame = read_learning(REPO / "results" / "learning.csv")
    assert set(frame["suite"]) == {"learning"} and (frame["status"] == "ok").all()
    assert frame["git_commit"].nunique() == 1 and not frame["git_dirty"].astype(str).eq("True").any()
    points = curve_points(frame)
    sizes = points.groupby("model")["flights"].nunique()
    assert set(sizes.index) == {"student", "phase_student", "audionet", "visualnet"} and (sizes >= 3).all()
    readme = (REPO / "README.md").read_text()
    table = readme[readme.index("| E ideal (m) | 2 flights"):]
    labels = {"student": "| student (mel", "audionet": "| AudioNet (mel", "phase_student": "| phase student",
              "visualnet": "| VisualNet (256 px"}
    for model, label in labels.items():
        row = table[table.index(label):].splitlines()[0]
        # each size's "E ± std" (several seeds) or "E" (one), ideal light first where darkness follows
        quoted = [(float(mean), float(std) if std else None)
                  for mean, std in re.findall(r"\| (\d+\.\d\d)(?: ± (\d+\.\d\d))?(?= [|/])", row)]
        curve = points[points["model"] == model].sort_values("flights")
        expected = [(round(mean, 2), round(std, 2) if seeds > 1 else None)
                    for mean, std, seeds in zip(curve["E"], curve["std"], curve["seeds"], strict=True)]
        assert quoted == expected, (model, row)
    for kind, label in (("constant", "| constant (mean train GT"), ("bound", "| physical limit (CRLB, RMS")):
        row = table[table.index(label):].splitlines()[0]
        assert float(row.split("|")[2].split("±")[0]) == round(reference_level(frame, kind), 2)


def test_a_model_run_on_fewer_seeds_is_held_against_the_constant_of_its_own_splits(tmp_path):
    """Each seed of a learning suite is its own split, with its own constant: a model run on seed 0 alone is
    compared with seed 0's constant, in the caption and as its own line in the figure."""
    from benchmarks.learning import _constants, learning_evidence

    constant = {"kind": "constant", "model": "constant", "method": "Constant (mean train GT)", "category": "reference",
                "protocol": "by_sequence", "suite": "learning", "data": "30 flights"}
    rows = [_model("audionet", 5, 450, error, seed=seed) for seed, error in ((0, 10.0), (1, 8.0))]
    rows += [{**_model("visualnet", 5, 90, 12.0), "E_dark": 11.9}]
    rows += [{**PROVENANCE, **constant, "job_id": f"constant_gt-by_sequence-s{seed}", "seed": seed, "E_ideal": level,
              "E_dark": level} for seed, level in ((0, 12.0), (1, 8.0))]
    frame = pd.DataFrame([{**PROVENANCE, "suite": "learning", "data": "30 flights", **row} for row in rows])
    caption = learning_evidence(frame, "by_sequence", {"audionet": "AudioNet", "visualnet": "VisualNet"})
    assert "mean over up to 2 seeds, each its own split, per size; its own constant (mean train GT) 10.00 m" in caption
    assert "AudioNet 9.00 m at 450 windows (best 9.00 m at 450, 0.90 × the constant): more than 5 % below" in caption
    assert ("VisualNet 12.00 m at 90 windows (best 12.00 m at 90, 1.00 × the constant of its seed 0, 12.00 m): at no "
            "size more than 5 % below the constant") in caption
    assert _constants(frame, "ideal") == {"constant (mean train GT), seeds 0, 1": 10.0,
                                          "constant (mean train GT), seed 0": 12.0}
    one_split = frame.assign(E_ideal=frame["E_ideal"].where(frame["kind"] != "constant", 12.0))
    assert "mean over up to 2 seeds per size" in learning_evidence(one_split, "by_sequence", {"audionet": "AudioNet"})
