"""A job folder: cleared for a rerun (the earlier run moved aside), locked by the job that runs in it."""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import runner
from benchmarks.jobfolder import LOCK_NAME, JobFolderBusy, clear_for_rerun, hold, task_rank
from benchmarks.jobs import base_row
from benchmarks.results import read_results
from benchmarks.suite import expand_jobs, load_suite
from tests.helpers.suites import write_suite

REPO = Path(__file__).resolve().parents[2]
HOLDER = ("import os, sys, time\n"
          "from benchmarks.jobfolder import hold\n"
          "held = hold(sys.argv[1])\n"
          "held.__enter__()\n"
          "print('held', flush=True)\n"
          "os._exit(0) if sys.argv[2] == 'die' else time.sleep(120)\n")


def start_holder(folder: Path, then: str) -> subprocess.Popen:
    """A process that takes ``folder``'s lock, then dies at once (``die``) or keeps running (``run``)."""
    process = subprocess.Popen([sys.executable, "-c", HOLDER, str(folder), then], cwd=REPO, stdout=subprocess.PIPE,
                               text=True, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert process.stdout.readline().strip() == "held"
    return process


def fake_job(job):
    """A job as Lightning's ModelCheckpoint writes it: last.ckpt, or last-v1.ckpt beside an existing one."""
    with hold(job.job_dir):
        folder = Path(job.job_dir) / "checkpoints"
        folder.mkdir(parents=True, exist_ok=True)
        name = "last-v1.ckpt" if (folder / "last.ckpt").exists() else "last.ckpt"
        (folder / name).write_text("new run")
    return {**base_row(job), "wall_time_s": 0.1}


def test_a_rerun_starts_from_a_clean_folder_and_a_live_job_is_not_started_twice(tmp_path, monkeypatch, caplog):
    caplog.set_level(logging.INFO)
    suite = load_suite(write_suite(tmp_path / "suite.yaml", root=str(tmp_path), cache=str(tmp_path / "cache")))
    job = next(j for j in expand_jobs(suite) if j.kind == "constant")
    folder = Path(job.job_dir)
    (folder / "checkpoints").mkdir(parents=True)
    (folder / "checkpoints" / "last.ckpt").write_text("old run")
    for name, stand_in in (("run_job", fake_job), ("prepare_data", lambda suite: ""),
                           ("check_job_args", lambda suite, jobs: None)):
        monkeypatch.setattr(runner, name, stand_in)

    summary = runner.run_suite(suite, launcher="debug", only=[job.job_id])
    assert summary.done == [job.job_id]
    assert sorted(p.name for p in (folder / "checkpoints").iterdir()) == ["last.ckpt"]
    assert (folder / "checkpoints" / "last.ckpt").read_text() == "new run"
    previous = folder.with_name(folder.name + ".previous")
    assert (previous / "checkpoints" / "last.ckpt").read_text() == "old run"
    assert f"moved aside to {previous}" in caplog.text

    holder = start_holder(folder, "run")  # an orphan of a killed runner, still training
    try:
        busy = runner.run_suite(suite, rerun=True, launcher="debug", only=[job.job_id])
    finally:
        holder.kill()
        holder.wait()
    assert busy.busy == [job.job_id] and busy.done == [] and len(read_results(suite.results_path)) == 1
    assert (folder / "checkpoints" / "last.ckpt").read_text() == "new run"  # nothing moved under it
    line = next(r.getMessage() for r in caplog.records if "not started" in r.getMessage())
    assert f"a job is still running in this folder (pid {holder.pid} on" in line and "\n" not in line


def test_a_stale_lock_is_taken_over_with_a_warning(tmp_path, caplog):
    folder = tmp_path / "jobs" / "student-by_sequence-s0"
    holder = start_holder(folder, "die")  # killed while it held the folder
    holder.wait()
    assert (folder / LOCK_NAME).read_text().startswith(f"pid {holder.pid} on ")
    with hold(folder):
        assert (folder / LOCK_NAME).read_text().startswith("pid ")
    assert f"stale lock of a job that is no longer running (pid {holder.pid} on" in caplog.text
    assert (folder / LOCK_NAME).read_text() == ""  # a normal end leaves nothing stale
    caplog.clear()
    assert clear_for_rerun(folder) == folder.with_name(folder.name + ".previous")
    assert "stale" not in caplog.text


def test_only_rank_zero_of_a_multi_process_job_holds_the_lock(tmp_path, monkeypatch):
    for name in ("SLURM_PROCID", "SUBMITIT_LOCAL_GLOBALID", "LOCAL_RANK"):
        monkeypatch.delenv(name, raising=False)
    assert task_rank() == 0
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert task_rank() == 1
    monkeypatch.setenv("SLURM_PROCID", "0")  # the global rank wins over the local one
    assert task_rank() == 0
    with hold(tmp_path / "job"):
        monkeypatch.setenv("SLURM_PROCID", "3")
        with hold(tmp_path / "job"):  # rank 3 takes no lock, so it does not find rank 0's
            pass
        monkeypatch.setenv("SLURM_PROCID", "0")
        with pytest.raises(JobFolderBusy, match="a job is already running in this folder"), hold(tmp_path / "job"):
            pass
