"""Benchmark suites and the runner: validation, job expansion, crash isolation, resumption, the shipped suites."""

from __future__ import annotations

import json

import pytest
import torch

from benchmarks.results import read_results
from benchmarks.runner import finished_jobs, run_suite
from benchmarks.suite import SuiteError, check_job_args, expand_jobs, load_suite
from tests.helpers.layouts import make_derived
from tests.helpers.suites import REPO, SPLIT, write_suite
from zoo.task import TrajectoryTask

#: the paper suite expands to dozens of jobs whose LightningCLI arguments are each parsed: slow
SUITES = [pytest.param(path, marks=pytest.mark.slow) if path.stem == "paper" else path
          for path in sorted((REPO / "configs" / "benchmark").glob("*.yaml"))]


@pytest.mark.slow  # two student trainings in job processes (the mmaud_v1 suite test covers a normal run)
def test_a_crashed_job_keeps_the_others_rows_and_a_rerun_completes_only_it(labelled_dir, feature_cache, tmp_path):
    kwargs = {"root": str(labelled_dir), "cache": str(feature_cache)}
    suite = load_suite(write_suite(tmp_path / "suite.yaml", lr=-1.0, **kwargs))  # Adam refuses lr < 0
    first = run_suite(suite)
    assert first.failed == ["student-by_sequence-s0"] and first.done == ["constant_gt-by_sequence-s0"]
    rows = read_results(suite.results_path)
    failed = rows[rows["status"] == "failed"].iloc[0]
    assert "learning rate" in failed["error"].lower()
    assert (suite.out / failed["log_path"]).is_file()
    constant = rows[rows["kind"] == "constant"].iloc[0]
    assert constant["E_ideal"] > 0 and constant["E_ideal"] == pytest.approx(constant["E_dark"])
    assert constant["n_test_sequences"] == 1 and constant["git_commit"]

    fixed = load_suite(write_suite(tmp_path / "suite.yaml", **kwargs))
    second = run_suite(fixed)
    assert second.skipped == ["constant_gt-by_sequence-s0"] and second.done == ["student-by_sequence-s0"]
    rows = read_results(fixed.results_path)
    model = rows[(rows["kind"] == "model") & (rows["status"] == "ok")].iloc[0]
    assert model["protocol"] == "by_sequence" and model["category"] == "self-supervised"
    assert model["E_ideal"] > 0 and model["E_ideal_mavic2"] == pytest.approx(model["E_ideal"])
    assert (fixed.out / model["predictions_path"]).is_file()
    assert set(finished_jobs(fixed.results_path)) == {"constant_gt-by_sequence-s0", "student-by_sequence-s0"}
    assert run_suite(fixed).skipped == ["student-by_sequence-s0", "constant_gt-by_sequence-s0"]


def test_two_entries_of_one_model_need_distinct_tags(tmp_path, labelled_dir):
    entry = {"model": "student", "config": str(REPO / "configs/model/student.yaml")}
    twice = write_suite(tmp_path / "suite.yaml", root=str(labelled_dir), cache=str(tmp_path), models=[entry, entry])
    with pytest.raises(SuiteError, match=r"'student' is listed twice.*its own tag"):
        load_suite(twice)
    tagged = write_suite(tmp_path / "suite.yaml", root=str(labelled_dir), cache=str(tmp_path),
                         models=[entry, {**entry, "tag": "small"}])
    ids = [job.job_id for job in expand_jobs(load_suite(tagged)) if job.kind == "model"]
    assert ids == ["student-by_sequence-s0", "student_small-by_sequence-s0"]


def test_an_entry_runs_on_its_own_seeds_with_its_own_split_keys(tmp_path, labelled_dir):
    entry = {"model": "student", "config": str(REPO / "configs/model/student.yaml")}
    fractions = {"val": 0.3, "test": 0.3}
    base = {"root": str(labelled_dir), "cache": str(tmp_path / "cache"), "protocols": {"by_sequence": fractions},
            "seeds": [0, 1]}
    suite = load_suite(write_suite(tmp_path / "suite.yaml", models=[
        {**entry, "split": {"train_flights": 1}}, {**entry, "tag": "once", "seeds": [1]}], **base))
    splits = {job.job_id: json.loads(job.cli_args[job.cli_args.index("--data.split") + 1])
              for job in expand_jobs(suite) if job.kind in ("model", "constant")}
    assert splits == {  # the split's seed is the job's; the entry's keys join the protocol's
        "student-by_sequence-s0": {"protocol": "by_sequence", "seed": 0, **fractions, "train_flights": 1},
        "student-by_sequence-s1": {"protocol": "by_sequence", "seed": 1, **fractions, "train_flights": 1},
        "student_once-by_sequence-s1": {"protocol": "by_sequence", "seed": 1, **fractions},
        "constant_gt-by_sequence-s0": {"protocol": "by_sequence", "seed": 0, **fractions},
        "constant_gt-by_sequence-s1": {"protocol": "by_sequence", "seed": 1, **fractions}}
    for bad, message in (({"seeds": [2]}, "seeds must be a non-empty list of the suite's seeds"),
                         ({"split": [1]}, "split must be a mapping")):
        with pytest.raises(SuiteError, match=rf"suite\.yaml: model 'student': {message}"):
            load_suite(write_suite(tmp_path / "suite.yaml", models=[{**entry, **bad}], **base))


def test_suite_errors_name_the_key(tmp_path, labelled_dir):
    base = {"root": str(labelled_dir), "cache": str(tmp_path / "cache")}
    with pytest.raises(SuiteError, match="unknown model 'bogus'; known models: .*student"):
        load_suite(write_suite(tmp_path / "a.yaml", models=[{"model": "bogus"}], **base))
    with pytest.raises(SuiteError, match=r"unknown protocol\(s\) \['leaky'\]; known: .*time_blocks"):
        load_suite(write_suite(tmp_path / "b.yaml", protocols={"leaky": {}}, **base))
    with pytest.raises(SuiteError, match=r"unknown key\(s\) \['modles'\]"):
        load_suite(write_suite(tmp_path / "c.yaml", modles=[], **base))
    suite = load_suite(write_suite(tmp_path / "d.yaml", models=[
        {"model": "student", "config": str(REPO / "configs/model/student.yaml"), "args": {"model.bogus_key": 1}}],
        **base))
    with pytest.raises(SuiteError, match="student-by_sequence-s0: its configuration does not parse.*bogus_key"):
        check_job_args(suite, expand_jobs(suite))


@pytest.mark.parametrize("seeds", [[], [0, 0], ["a"], [1.5], None])
def test_seeds_must_be_a_non_empty_list_of_distinct_integers(tmp_path, seeds):
    path = write_suite(tmp_path / "s.yaml", root=str(tmp_path), cache=str(tmp_path / "cache"), seeds=seeds)
    with pytest.raises(SuiteError, match=r"s\.yaml: seeds must be a non-empty list of distinct integers"):
        load_suite(path)


def test_a_model_listed_twice_in_one_protocol_is_refused(tmp_path):
    student = {"model": "student", "config": str(REPO / "configs/model/student.yaml")}
    path = write_suite(tmp_path / "s.yaml", root=str(tmp_path), cache=str(tmp_path / "cache"),
                        models=[student, {**student, "budget_note": "longer"}])
    with pytest.raises(SuiteError, match=r"s\.yaml: model 'student' is listed twice for protocol 'by_sequence'"):
        load_suite(path)
    protocols = {"by_sequence": SPLIT, "time_blocks": {}}
    apart = write_suite(tmp_path / "t.yaml", root=str(tmp_path), cache=str(tmp_path / "cache"), protocols=protocols,
                         models=[{**student, "protocols": ["by_sequence"]}, {**student, "protocols": ["time_blocks"]}])
    jobs = expand_jobs(load_suite(apart))
    assert len({j.job_id for j in jobs}) == len(jobs)


@pytest.mark.parametrize("path", SUITES, ids=lambda p: getattr(p, "stem", None))
def test_shipped_suites_expand_and_parse(path):
    suite = load_suite(path, {"data.root": "/data/mmaud"} if path.stem == "mmaud_v1" else None)
    jobs = expand_jobs(suite, "fingerprint")
    assert jobs and len({j.job_id for j in jobs}) == len(jobs)
    check_job_args(suite, jobs)
    kinds = {j.kind for j in jobs}
    assert {"model", "constant"} <= kinds
    for job in jobs:
        if job.kind == "model":
            assert job.protocol in suite.raw["protocols"]


def test_the_demo_suite_covers_the_comparison():
    from zoo.registry import list_models

    suite = load_suite(REPO / "configs" / "benchmark" / "quick.yaml")
    jobs = expand_jobs(suite)
    trained = {(j.model, j.protocol) for j in jobs if j.kind == "model"}
    assert {m for m, _ in trained} == set(list_models())
    assert {p for _, p in trained} == {"by_sequence", "random_windows"}
    assert ("student", "random_windows") in trained
    assert suite.raw["lights"] == ["ideal", "dark"] and suite.raw["smoothing"]
    assert suite.data["simulate"]["sequences"] >= 15  # three flights per drone type at least
    assert {j.model for j in jobs if j.kind == "profile"} == set(list_models())
    assert str(suite.out).startswith("demo_out")


def test_the_mmaud_v1_suite_runs_on_a_derived_npy_copy(tmp_path, monkeypatch):
    """The real-data suite on a small fixture of the derived per-sample layout (two 8 s flights)."""
    monkeypatch.setattr("tests.helpers.layouts.CHUNK", 4608)  # 0.1 s per file at 46080 Hz
    root = tmp_path / "Data-M"
    make_derived(root, {"0": 80, "3": 80}, images=False)
    suite = load_suite(REPO / "configs" / "benchmark" / "mmaud_v1.yaml",
                       {"data.root": str(root), "out": str(tmp_path / "out")})
    suite.raw["data"]["init_args"] = {"num_workers": 0, "window_seconds": 0.5, "batch_size": 8,
                                      "cache_dir": str(tmp_path / "cache")}
    suite.raw["trainer"]["overrides"] = {"accelerator": "cpu", "max_epochs": 1, "enable_model_summary": False}
    summary = run_suite(suite, launcher="debug", only=["student-time_blocks-s0", "constant_gt-time_blocks-s0"])
    assert summary.failed == [] and len(summary.done) == 2
    rows = read_results(suite.results_path)
    assert set(rows["protocol"]) == {"time_blocks"} and set(rows["data_kind"]) == {"real"}
    assert (rows["n_train_sequences"] == 2).all() and (rows["n_test_sequences"] == 2).all()
    assert rows["E_ideal"].notna().all() and (rows["peak_rss_mb"] > 100).all()
    # one checkpoint per job: the best epoch's weights, no optimizer state, loadable on its own
    checkpoints = tmp_path / "out" / "jobs" / "student-time_blocks-s0" / "checkpoints"
    assert [p.name for p in checkpoints.iterdir()] == ["best.ckpt"]
    state = torch.load(checkpoints / "best.ckpt", map_location="cpu", weights_only=False)
    assert "optimizer_states" not in state and state["state_dict"]
    assert TrajectoryTask.load_from_checkpoint(checkpoints / "best.ckpt", map_location="cpu").net is not None


@pytest.mark.slow
def test_the_demo_suite_runs_end_to_end_to_the_leaderboard(tmp_path, monkeypatch):
    """`make demo` in a temporary folder: about 12 minutes on 2 cores."""
    from benchmarks.leaderboard import render_leaderboard
    from zoo.registry import list_models, model_class
    from zoo.weights import list_weights, load_pretrained

    monkeypatch.setenv("AAUTE_CACHE", str(tmp_path / "home_cache"))  # the weights registry of this run

    suite = load_suite(REPO / "configs" / "benchmark" / "quick.yaml",
                       {"out": str(tmp_path / "benchmark"), "data.root": str(tmp_path / "data")})
    suite.raw["data"]["init_args"]["cache_dir"] = str(tmp_path / "cache")
    summary = run_suite(suite)
    assert summary.failed == []
    rows = read_results(suite.results_path)
    assert (rows["status"] == "ok").all()
    assert set(rows.loc[rows["kind"] == "model", "model"]) == set(list_models())
    assert set(rows.loc[rows["kind"] != "profile", "protocol"]) == {"by_sequence", "random_windows"}
    report = render_leaderboard(suite.results_path, tmp_path / "leaderboard")
    assert "Constant (mean train GT)" in report.markdown and (tmp_path / "leaderboard" / "leaderboard.html").is_file()
    learned = {model for model in list_models() if model_class(model).category != "non-learned"}
    assert {f"{model}.sim_quick" for model in learned} | {"student.sim_quick_random_windows"} <= set(list_weights())
    assert not load_pretrained("student", weights="sim_quick").training


def test_the_paper_suite_smooths_with_the_papers_gp_and_the_others_with_the_default():
    import json

    paper = [j for j in expand_jobs(load_suite(REPO / "configs" / "benchmark" / "paper.yaml")) if j.kind == "model"]
    for job in paper:
        at = job.cli_args.index("--model.smoother")
        assert json.loads(job.cli_args[at + 1]) == {"preset": "paper"}
    quick = [j for j in expand_jobs(load_suite(REPO / "configs" / "benchmark" / "quick.yaml")) if j.kind == "model"]
    assert quick and all("--model.smoother" not in j.cli_args for j in quick)  # the model configs' robust preset
