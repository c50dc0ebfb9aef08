"""The results.csv schema: atomic appends, schema checks, interrupted writes."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from benchmarks.results import COLUMNS, SCHEMA_VERSION, ResultsError, append_rows, latest, read_results

ROW = {"kind": "model", "suite": "s", "job_id": "student-by_sequence-s0", "status": "ok", "model": "student",
       "protocol": "by_sequence", "seed": 0, "E_ideal": 7.5, "E_dark": float("nan")}


def test_rows_round_trip_with_empty_cells_for_what_does_not_apply(tmp_path):
    path = tmp_path / "results.csv"
    append_rows(path, [ROW])
    append_rows(path, [{**ROW, "E_ideal": 6.0}, {"kind": "profile", "suite": "s", "job_id": "profile-student",
                                                   "status": "ok", "model": "student", "gmacs": 0.0061}])
    frame = read_results(path)
    assert list(frame.columns) == COLUMNS and len(frame) == 3
    assert frame["E_ideal"].tolist()[:2] == [7.5, 6.0]
    assert frame["E_dark"].isna().all() and frame["gmacs"].isna().tolist() == [True, True, False]
    assert (frame["schema_version"] == str(SCHEMA_VERSION)).all()
    newest = latest(frame)
    assert len(newest) == 2 and newest.loc[newest["kind"] == "model", "E_ideal"].item() == 6.0


def test_unknown_columns_and_kinds_are_refused_before_anything_is_written(tmp_path):
    path = tmp_path / "results.csv"
    with pytest.raises(ResultsError, match=r"outside schema 1: \['E_idael'\]"):
        append_rows(path, [{**ROW, "E_idael": 1.0}])
    with pytest.raises(ResultsError, match="kind must be one of"):
        append_rows(path, [{**ROW, "kind": "training"}])
    assert not path.exists()


def test_another_schema_or_a_missing_column_is_named(tmp_path):
    path = tmp_path / "results.csv"
    append_rows(path, [ROW])
    text = path.read_text()
    other = tmp_path / "other.csv"
    other.write_text(text.replace(f"\n{SCHEMA_VERSION},", "\n0,", 1))
    with pytest.raises(ResultsError, match=r"schema version\(s\) \['0'\]"):
        read_results(other)
    with pytest.raises(ResultsError, match=r"schema version\(s\) \['0'\]"):
        append_rows(other, [ROW])  # a file of another schema is never extended
    header, body = text.split("\n", 1)
    missing = tmp_path / "missing.csv"
    missing.write_text(header.replace(",E_ideal,", ",") + "\n")
    with pytest.raises(ResultsError, match=r"missing column\(s\) \['E_ideal'\]"):
        read_results(missing)


def test_an_interrupted_last_line_is_dropped_and_the_file_stays_readable(tmp_path, caplog):
    path = tmp_path / "results.csv"
    append_rows(path, [ROW, {**ROW, "job_id": "other"}])
    text = path.read_text()
    path.write_text(text[: len(text) - 40])  # a writer killed mid-line
    frame = read_results(path)
    assert frame["job_id"].tolist() == ["student-by_sequence-s0"]
    assert "incomplete" in caplog.text
    append_rows(path, [{**ROW, "job_id": "third"}])  # the next append completes the file
    assert read_results(path)["job_id"].tolist() == ["student-by_sequence-s0", "third"]


def test_a_file_from_before_the_smoother_column_is_read_and_extended(tmp_path):
    path = tmp_path / "results.csv"
    append_rows(path, [ROW])
    header, body = path.read_text().split("\n", 1)
    columns = header.split(",")
    at = columns.index("smoother")
    older = [",".join(cells[:at] + cells[at + 1:]) for cells in (line.split(",") for line in [header, body.strip()])]
    path.write_text("\n".join(older) + "\n")  # as written before the column existed
    assert read_results(path)["smoother"].tolist() == [""]
    append_rows(path, [{**ROW, "job_id": "robust-job", "smoother": "robust"}])
    assert path.read_text().split("\n", 1)[0] == header  # rewritten under the current header
    frame = read_results(path)
    assert frame["job_id"].tolist() == ["student-by_sequence-s0", "robust-job"]
    assert frame["smoother"].tolist() == ["", "robust"] and frame["E_ideal"].tolist() == [7.5, 7.5]


@pytest.mark.parametrize(("column", "cell"), [("E_ideal", "inf"), ("E_ideal", "-1.5"), ("E_dark", "oops"),
                                              ("E_ideal_r0_10", "nan"), ("gmacs", "-0.1"), ("seed", "zero")])
def test_a_broken_number_is_refused_naming_the_file_line_and_column(tmp_path, column, cell):
    path = tmp_path / "results.csv"
    append_rows(path, [ROW, {**ROW, "job_id": "second"}])
    header, first, second = path.read_text().splitlines()
    cells = second.split(",")
    cells[header.split(",").index(column)] = cell
    path.write_text("\n".join([header, first, ",".join(cells)]) + "\n")
    with pytest.raises(ResultsError, match=rf"results\.csv: line 3, column {column}: '{cell}' is not"):
        read_results(path)
    append_rows(path, [{**ROW, "job_id": "third"}])  # appending is not the place to refuse it
    assert len(read_results(path, check_values=False)) == 3


def test_columns_a_user_added_are_kept_when_rows_are_appended(tmp_path):
    path = tmp_path / "results.csv"
    append_rows(path, [ROW])
    header, body = path.read_text().splitlines()
    path.write_text(f"notes,{header},owner\n\"rerun, lr too high\",{body},ana\n")
    append_rows(path, [{**ROW, "job_id": "second"}])
    assert path.read_text().split("\n", 1)[0] == ",".join([*COLUMNS, "notes", "owner"])
    frame = read_results(path)
    assert frame["notes"].tolist() == ["rerun, lr too high", ""] and frame["owner"].tolist() == ["ana", ""]
    assert frame["E_ideal"].tolist() == [7.5, 7.5]
    append_rows(path, [{**ROW, "job_id": "third"}])  # now in place: a plain append
    assert read_results(path)["notes"].tolist() == ["rerun, lr too high", "", ""]


def test_a_detecting_nets_prediction_file_says_which_windows_it_detected(tmp_path):
    """srp_phat's job file carries detection_score, detected and state, so aaute smooth and readers can tell its
    held and fallback positions from its detections; another net's file keeps the plain columns."""
    from types import SimpleNamespace

    from benchmarks.jobs import _prediction_frame, _write_predictions
    from benchmarks.results import PREDICTION_COLUMNS
    from zoo.smoothing import read_tracks_csv

    piece = SimpleNamespace(sequence_id="sim0_0001", recording_id="sim0_0001", drone="avata")
    datamodule = SimpleNamespace(test_lights=["ideal"], sequences={"test": [piece]})
    plain = {"time": 100 + np.arange(4) * 0.1, "gt_valid": np.ones(4, dtype=bool), "position": np.zeros((4, 3)),
             "gt": np.ones((4, 3)), "detected": np.ones(4, dtype=bool)}
    detecting = dict(plain, detected=np.array([True, False, False, False]),
                     detection_score=np.array([2.0, 0.5, 0.4, 0.3]), state=np.array([0, 1, 2, 3]))
    for sequence, extra in ((plain, []), (detecting, ["detection_score", "detected", "state"])):
        task = SimpleNamespace(smoothed_predictions={}, sequence_predictions=lambda index, s=sequence: {0: s})
        path = _write_predictions(tmp_path / "predictions.csv", _prediction_frame(task, datamodule))
        table = pd.read_csv(path)
        assert list(table.columns) == PREDICTION_COLUMNS + extra
    assert list(table["state"]) == ["detected", "held", "fallback", "uncorrected"]
    assert read_tracks_csv(path)[0].detected.tolist() == [True, False, False, False]
