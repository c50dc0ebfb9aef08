"""The Slurm launcher's parts that need no cluster: squeue parsing, the reasons of jobs Slurm ended, the array's
parameters, submitit's sacct noise filtered out, and one clear line where Slurm is missing."""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.runner import make_executor
from benchmarks.slurm import (
    LauncherError,
    SacctNoise,
    SlurmState,
    array_executor,
    array_parameters,
    ended_without_result,
    parse_squeue,
    require_slurm,
    run_on_slurm,
    stage_counts,
)
from benchmarks.suite import expand_jobs, load_suite

REPO = Path(__file__).resolve().parents[2]


def test_squeue_lines_become_states_per_job_and_array_task():
    text = "41_0|RUNNING|None|vm\n41_1|PENDING|JobArrayTaskLimit|\n40|TIMEOUT|TimeLimit|vm\n\nnot a line\n"
    states = parse_squeue(text)
    assert states == {"41_0": SlurmState("RUNNING", "", "vm"), "41_1": SlurmState("PENDING", "JobArrayTaskLimit", ""),
                      "40": SlurmState("TIMEOUT", "TimeLimit", "vm")}
    assert stage_counts(s.state for s in states.values()) == {"queued": 1, "running": 1, "ended": 1}


def test_a_job_slurm_ended_says_why():
    assert ended_without_result(SlurmState("TIMEOUT", "TimeLimit", "vm"), 2) == (
        "Slurm TIMEOUT: killed at its time limit of 2 min (launcher.timeout_min) [TimeLimit]")
    assert ended_without_result(SlurmState("CANCELLED"), 2) == "Slurm CANCELLED: cancelled (scancel)"
    assert ended_without_result(SlurmState("OUT_OF_MEMORY"), 2).endswith("out of memory")


def test_the_array_takes_the_suites_options_and_concurrency_limit(tmp_path):
    suite = load_suite(REPO / "configs" / "benchmark" / "paper.yaml", {"out": str(tmp_path)})
    parameters = array_parameters(suite, 3)
    assert parameters["partition"] == "gpu" and parameters["gpus_per_node"] == 1
    assert parameters["time"] == suite.launcher["timeout_min"] and parameters["array_parallelism"] == 3
    assert parameters["job_name"] == "aaute-paper" and parameters["signal_delay_s"] == 90
    suite.raw["launcher"]["timeout_min"] = 2
    assert array_parameters(suite, 1)["signal_delay_s"] == 30  # warned 30 to 90 s after it starts
    with pytest.raises(ValueError, match="unknown launcher 'pbs'"):
        make_executor(suite, expand_jobs(suite)[0], "pbs")


def test_submitits_sacct_warnings_are_dropped_and_nothing_else():
    noise = SacctNoise()
    record = logging.LogRecord("submitit", logging.WARNING, "", 0, "Call #3 - Bypassing sacct error %s", ("x",), None)
    other = logging.LogRecord("submitit", logging.WARNING, "", 0, "Job failed", (), None)
    assert not noise.filter(record) and noise.filter(other)


def test_without_slurm_the_launcher_says_so_in_one_line(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))  # no srun
    suite = load_suite(REPO / "configs" / "benchmark" / "paper.yaml", {"out": str(tmp_path)})
    with pytest.raises(LauncherError, match="launcher slurm: .*srun.*--launcher local"):
        array_executor(suite, 1)
    with pytest.raises(LauncherError, match="launcher slurm: no sbatch, srun, squeue on PATH"):
        require_slurm()
    done = subprocess.run([sys.executable, "-m", "benchmarks.cli", "benchmark", "--suite",
                           str(REPO / "configs/benchmark/quick.yaml"), "--launcher", "slurm",
                           "--out", str(tmp_path / "out")],
                          capture_output=True, text=True, cwd=REPO, env={"PATH": str(tmp_path),
                                                                         "PYTHONPATH": str(REPO)})
    assert done.returncode == 2, done.stderr
    assert [line for line in done.stderr.splitlines() if "launcher slurm" in line] and "Traceback" not in done.stderr


class _Handle:
    """A submitted array task as run_on_slurm sees it: an id, result paths, and cancel()."""

    def __init__(self, job_id: str, folder: Path):
        self.job_id, self.cancelled = job_id, False
        self.paths = type("Paths", (), {"result_pickle": folder / f"{job_id}_result.pkl"})()

    def cancel(self, check: bool = True) -> None:
        self.cancelled = True


def test_an_interrupted_suite_cancels_its_unfinished_slurm_jobs(tmp_path, monkeypatch):
    suite = load_suite(REPO / "configs" / "benchmark" / "paper.yaml", {"out": str(tmp_path)})
    jobs = expand_jobs(suite)[:3]
    handles = [_Handle(f"77_{i}", tmp_path) for i in range(3)]
    handles[0].paths.result_pickle.write_bytes(b"")  # the first has finished
    monkeypatch.setattr("benchmarks.slurm.submit_array", lambda *args: handles)
    polls = iter([{"77_1": SlurmState("RUNNING", "", "vm"), "77_2": SlurmState("PENDING")}])

    def queue():  # one poll, then the user presses Ctrl-C
        try:
            return next(polls)
        except StopIteration:
            raise KeyboardInterrupt from None

    monkeypatch.setattr("benchmarks.slurm.queue_states", queue)
    finished = []
    with pytest.raises(KeyboardInterrupt):
        run_on_slurm(suite, jobs, 1, print, lambda job, *rest: finished.append(job.job_id) or True, poll_seconds=0)
    assert finished == [jobs[0].job_id]
    assert [h.cancelled for h in handles] == [False, True, True]
