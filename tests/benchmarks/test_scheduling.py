"""The local launcher's scheduling: expected peaks, start order, the memory rule, the runner with fake jobs, keys."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from benchmarks import runner
from benchmarks.jobs import base_row
from benchmarks.results import append_rows
from benchmarks.scheduling import DEFAULT_JOB_GB, Peak, expected_peaks, longest_first, next_job, simulate_schedule
from benchmarks.suite import JobSpec, Suite, SuiteError, expand_jobs, load_suite
from tests.helpers.suites import REPO, write_suite


def spec(job_id: str, tmp_path: Path, memory_gb: float | None = None, suite: str = "fake") -> JobSpec:
    return JobSpec(job_id=job_id, kind="constant", suite=suite, model="constant", method="Constant",
                   category="reference", protocol="by_sequence", seed=0, cli_args=[],
                   job_dir=str(tmp_path / "jobs" / job_id), threads=1, memory_gb=memory_gb)


def peaks(**sizes: float) -> dict[str, Peak]:
    return {name: Peak(gb, "hint") for name, gb in sizes.items()}


def test_the_next_job_fits_the_budget_and_a_lone_job_always_starts():
    sizes = peaks(big=2.5, mid=1.8, small=1.2, huge=6.0)
    assert next_job(["big", "mid"], [], sizes, 4.0) == 0
    assert next_job(["huge"], [], sizes, 4.0) == 0  # bigger than the budget: starts alone
    assert next_job(["mid", "small"], ["big"], sizes, 4.0) == 1  # mid waits, small fits beside big and mid
    assert next_job(["mid"], ["big"], sizes, 4.0) is None
    assert next_job(["huge", "small"], ["small"], sizes, 4.0) is None  # nothing passes a job that needs all
    assert next_job(["mid", "small"], ["big"], sizes, None) == 0  # no budget: order alone


def test_a_later_job_never_delays_the_waiting_one():
    sizes = peaks(running=2.0, waiting=2.8, later=1.5)
    # later fits beside the running job (3.5) but not beside the waiting one (4.3): it must not start
    assert next_job(["waiting", "later"], ["running"], sizes, 4.0) is None


def test_expected_peaks_come_from_an_earlier_run_then_the_hint_then_the_default(tmp_path):
    results = tmp_path / "results.csv"
    append_rows(results, [{**base_row(spec("a", tmp_path)), "peak_rss_mb": 3072.0},
                          {**base_row(spec("a", tmp_path)), "peak_rss_mb": 2048.0},  # the newest row wins
                          {**base_row(spec("c", tmp_path, suite="other")), "peak_rss_mb": 9000.0}])
    jobs = [spec("a", tmp_path, memory_gb=1.0), spec("b", tmp_path, memory_gb=1.7), spec("c", tmp_path)]
    found = expected_peaks(jobs, results)
    assert found["a"] == Peak(2.0, "measured")
    assert found["b"] == Peak(1.7, "hint")
    assert found["c"] == Peak(DEFAULT_JOB_GB, "default")  # another suite's row of that id does not count
    assert expected_peaks(jobs, tmp_path / "none.csv", 1.1)["a"] == Peak(1.0, "hint")


def test_timed_jobs_go_longest_first_after_the_untimed_ones_in_suite_order(tmp_path):
    results = tmp_path / "results.csv"
    append_rows(results, [{**base_row(spec("short", tmp_path)), "wall_time_s": 10.0},
                          {**base_row(spec("long", tmp_path)), "wall_time_s": 300.0},
                          {**base_row(spec("failed", tmp_path)), "status": "failed", "wall_time_s": 999.0}])
    jobs = [spec(name, tmp_path) for name in ("short", "new", "long", "failed", "other")]
    assert [job.job_id for job in longest_first(jobs, results)] == ["new", "failed", "other", "long", "short"]
    assert [job.job_id for job in longest_first(jobs, tmp_path / "none.csv")] == [job.job_id for job in jobs]


class FakeHandle:
    """A submitted fake job: done after ``ticks`` polls; it records which jobs ran beside it."""

    def __init__(self, job: JobSpec, ticks: int, live: dict[str, JobSpec], seen: list[list[str]]):
        self.job, self.ticks, self.live = job, ticks, live
        live[job.job_id] = job
        seen.append(sorted(live))
        self.paths = type("Paths", (), {"stderr": Path(job.job_dir) / "log.err"})()

    def done(self) -> bool:
        self.ticks -= 1
        if self.ticks <= 0:
            self.live.pop(self.job.job_id, None)
        return self.ticks <= 0

    def results(self) -> list[dict]:
        return [{**base_row(self.job), "wall_time_s": 1.0}]


def test_the_runner_never_exceeds_the_budget_and_runs_a_too_big_job_alone(tmp_path, monkeypatch, caplog):
    caplog.set_level(logging.INFO)
    sizes = {"a": 2.5, "b": 1.8, "c": 2.2, "huge": 5.0, "d": 1.2, "e": 1.3, "f": 2.0, "g": 1.2}
    ticks = {"a": 6, "b": 3, "c": 4, "huge": 2, "d": 1, "e": 2, "f": 3, "g": 5}
    jobs = [spec(name, tmp_path, memory_gb=gb) for name, gb in sizes.items()]
    live: dict[str, JobSpec] = {}
    seen: list[list[str]] = []
    executor = type("Executor", (), {"submit": lambda self, function, job: FakeHandle(job, ticks[job.job_id], live,
                                                                                       seen)})
    monkeypatch.setattr(runner, "make_executor", lambda suite, job, kind: executor())
    suite = Suite(tmp_path / "suite.yaml", "fake", tmp_path / "out",
                  {"launcher": {"kind": "local", "parallel": 3, "memory_gb": 4}})
    suite.out.mkdir()
    summary = runner.RunSummary(suite.results_path)
    runner.launch_jobs(suite, jobs, 3, "local", summary, poll_seconds=0.0)
    assert sorted(summary.done) == sorted(sizes) and not summary.failed
    for together in seen:
        assert len(together) == 1 or sum(sizes[name] for name in together) <= 4.0, together
    assert ["huge"] in seen and not any("huge" in together and len(together) > 1 for together in seen)
    assert any(len(together) > 1 for together in seen)  # the budget still lets jobs share the machine
    assert "b waits for memory: expected peak 1.8 GB (hint) beside 2.5 GB of running jobs (a)" in caplog.text


def test_a_replayed_schedule_keeps_the_budget_and_costs_time():
    sizes = peaks(a=2.5, b=1.8, c=2.2, d=1.2, e=1.3)
    durations = {"a": 400.0, "b": 300.0, "c": 120.0, "d": 10.0, "e": 50.0}
    free, free_peak, _ = simulate_schedule(list(sizes), durations, sizes, 2, None)
    kept, kept_peak, starts = simulate_schedule(list(sizes), durations, sizes, 2, 4.0)
    assert free_peak > 4.0 and kept_peak <= 4.0
    assert kept >= free
    assert starts["b"] >= 400.0  # b waited for a; d and e ran beside a meanwhile
    assert starts["d"] < 400.0 and starts["e"] < 400.0


@pytest.mark.parametrize(("where", "value"), [("launcher", 0), ("launcher", "4 GB"), ("launcher", True),
                                              ("model", -1.0), ("job", float("inf"))])
def test_the_suite_refuses_a_memory_figure_that_is_not_a_positive_number(tmp_path, where, value):
    student = {"model": "student", "config": str(REPO / "configs/model/student.yaml")}
    launcher = {"kind": "local", "parallel": 2}
    if where == "model":
        student["memory_gb"] = value
    else:
        launcher["memory_gb" if where == "launcher" else "job_memory_gb"] = value
    path = write_suite(tmp_path / "s.yaml", root=str(tmp_path), cache=str(tmp_path / "cache"), models=[student],
                       launcher=launcher)
    with pytest.raises(SuiteError, match=r"memory_gb must be a positive number of GB"):
        load_suite(path)


def test_memory_keys_and_budget_notes_leave_job_identity_alone(tmp_path):
    student = {"model": "student", "config": str(REPO / "configs/model/student.yaml")}
    plain = load_suite(write_suite(tmp_path / "a.yaml", root=str(tmp_path), cache=str(tmp_path / "c"),
                                   models=[student]))
    budgeted = load_suite(write_suite(
        tmp_path / "b.yaml", root=str(tmp_path), cache=str(tmp_path / "c"),
        models=[{**student, "memory_gb": 1.4, "budget_note": "a note"}],
        launcher={"kind": "local", "parallel": 2, "memory_gb": 4, "job_memory_gb": 1.3}))
    before = [(job.job_id, job.config_hash) for job in expand_jobs(plain, "fp")]
    after = [(job.job_id, job.config_hash) for job in expand_jobs(budgeted, "fp")]
    assert before == after  # a finished job is reused after the keys are added
    assert [job.memory_gb for job in expand_jobs(budgeted) if job.kind == "model"] == [1.4]


def test_the_demo_keeps_its_jobs_within_four_gb():
    suite = load_suite(REPO / "configs" / "benchmark" / "quick.yaml")
    assert suite.launcher["memory_gb"] <= 4
    trained = [job for job in expand_jobs(suite) if job.kind == "model"]
    assert all(job.memory_gb is not None for job in trained)  # every model has a hint before its first run
