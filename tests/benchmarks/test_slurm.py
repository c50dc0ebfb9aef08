"""The benchmark runner on a real Slurm cluster: rows with their Slurm provenance, failures, cancelled and
timed-out jobs, resumption, job arrays with a concurrency limit.

These tests submit jobs, so they run only on this project's one-node cluster (``scripts/local_slurm.sh up``,
cluster name ``aaute``), or on any cluster when ``AAUTE_SLURM_TESTS=1``; elsewhere they skip and say why.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest

from benchmarks.results import read_results
from benchmarks.runner import run_suite
from benchmarks.suite import load_suite
from tests.helpers.suites import REPO
from tests.helpers.suites import write_suite as tiny_suite

CLUSTER = "aaute"


def slurm_skip_reason() -> str | None:
    """Why the Slurm tests cannot run here, or None."""
    if shutil.which("sbatch") is None:
        return "no sbatch on PATH (start a local cluster with scripts/local_slurm.sh up)"
    if os.environ.get("AAUTE_SLURM_TESTS") == "1":
        return None
    try:
        config = subprocess.run(["scontrol", "show", "config"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError) as error:
        return f"scontrol show config failed: {error}"
    names = [line.split("=", 1)[1].strip() for line in config.splitlines() if line.startswith("ClusterName")]
    if names != [CLUSTER]:
        return (f"the Slurm cluster here is {names[0] if names else 'unreachable'!r}, not the project's {CLUSTER!r} "
                f"(scripts/local_slurm.sh up); set AAUTE_SLURM_TESTS=1 to submit to it anyway")
    return None


REASON = slurm_skip_reason()
pytestmark = [pytest.mark.slurm, pytest.mark.skipif(REASON is not None, reason=REASON or "")]


def write_suite(path: Path, root: Path, cache: Path, **changes) -> Path:
    """A suite of tiny jobs on the three 4 s simulated flights, sent to Slurm."""
    slurm = {"name": "slurm", "lights": ["ideal"], "constant": ["gt", "pseudo"],
             "launcher": {"kind": "slurm", "parallel": 2, "threads_per_job": 1, "timeout_min": 10}}
    return tiny_suite(path, root=str(root), cache=str(cache), **{**slurm, **changes})


def test_three_jobs_on_slurm_a_failure_keeps_the_others_and_a_rerun_submits_only_it(labelled_dir, feature_cache,
                                                                                       tmp_path):
    suite = load_suite(write_suite(tmp_path / "suite.yaml", labelled_dir, feature_cache, lr=-1.0))
    first = run_suite(suite)
    assert first.failed == ["student-by_sequence-s0"]
    assert sorted(first.done) == ["constant_gt-by_sequence-s0", "constant_pseudo-by_sequence-s0"]
    rows = read_results(suite.results_path)
    assert set(rows["launcher"]) == {"slurm"}
    assert rows["slurm_job_id"].str.fullmatch(r"\d+_\d").all() and rows["slurm_job_id"].is_unique
    assert (rows["node"] != "").all()
    failed = rows[rows["status"] == "failed"].iloc[0]
    assert "learning rate" in failed["error"].lower()
    assert (suite.out / failed["log_path"]).is_file()

    fixed = load_suite(write_suite(tmp_path / "suite.yaml", labelled_dir, feature_cache))
    second = run_suite(fixed)
    assert second.done == ["student-by_sequence-s0"] and not second.failed
    assert sorted(second.skipped) == ["constant_gt-by_sequence-s0", "constant_pseudo-by_sequence-s0"]
    rows = read_results(fixed.results_path)
    model = rows[(rows["kind"] == "model") & (rows["status"] == "ok")].iloc[0]
    assert model["E_ideal"] > 0 and model["slurm_job_id"] and model["node"]
    assert len(rows) == 4


def _cancel_when_running(name: str, stop: threading.Event, cancelled: list[str]) -> None:
    """scancel the first task of array ``name`` once it runs."""
    while not stop.is_set():
        lines = subprocess.run(["squeue", "-h", "-r", "-n", name, "-t", "RUNNING", "-o", "%i"],
                               capture_output=True, text=True).stdout.split()
        first = sorted(line for line in lines if line.endswith("_0"))
        if first:
            subprocess.run(["scancel", first[0]], check=True)
            cancelled.append(first[0])
            return
        time.sleep(1)


def test_a_cancelled_job_and_one_killed_at_its_time_limit_say_so(labelled_dir, feature_cache, tmp_path):
    """Two students that would train for hours: one is cancelled, the other reaches its 2-minute limit."""
    name = f"slurm_killed_{os.getpid()}"  # its jobs alone are cancelled, whoever else uses the cluster
    suite = load_suite(write_suite(
        tmp_path / "suite.yaml", labelled_dir, feature_cache, name=name, constant=[], seeds=[0, 1],
        launcher={"kind": "slurm", "parallel": 2, "threads_per_job": 1, "timeout_min": 2}))
    suite.raw["trainer"]["overrides"].update(max_epochs=100000, limit_val_batches=0)
    stop, cancelled = threading.Event(), []
    canceller = threading.Thread(target=_cancel_when_running, args=(f"aaute-{name}", stop, cancelled))
    canceller.start()
    try:
        summary = run_suite(suite)
    finally:
        stop.set()
        canceller.join()
    assert len(cancelled) == 1 and sorted(summary.failed) == ["student-by_sequence-s0", "student-by_sequence-s1"]
    rows = read_results(suite.results_path).set_index("slurm_job_id")
    assert rows.loc[cancelled[0], "error"].startswith("Slurm CANCELLED")
    other = rows.drop(index=cancelled[0]).iloc[0]
    assert other["status"] == "failed" and other["error"].startswith(("timed out: ", "Slurm TIMEOUT"))
    assert len(rows) == 2


def test_many_jobs_go_as_one_array_with_the_suites_concurrency_limit(labelled_dir, feature_cache, tmp_path):
    suite = load_suite(write_suite(
        tmp_path / "suite.yaml", labelled_dir, feature_cache, name="slurm_array", seeds=[0, 1],
        launcher={"kind": "slurm", "parallel": 1, "threads_per_job": 1, "timeout_min": 10}))
    summary = run_suite(suite, only=["constant"])
    assert len(summary.done) == 4 and not summary.failed
    rows = read_results(suite.results_path)
    arrays = {slurm_id.split("_")[0] for slurm_id in rows["slurm_job_id"]}
    assert len(arrays) == 1 and sorted(rows["slurm_job_id"].str.split("_").str[1]) == ["0", "1", "2", "3"]
    scripts = list((suite.out / "slurm").glob("*submission.sh"))
    assert len(scripts) == 1 and "#SBATCH --array=0-3%1" in scripts[0].read_text()
    # at most one at a time: each job started after the one before it ended (started_at has 1 s resolution)
    starts = sorted(zip(pd_seconds(rows["started_at"]), rows["wall_time_s"], strict=True))
    for (start, wall), (next_start, _) in zip(starts, starts[1:], strict=False):
        assert next_start >= start + wall - 1.0


def pd_seconds(column) -> list[float]:
    import pandas as pd

    return list(pd.to_datetime(column).map(lambda stamp: stamp.timestamp()))


def test_ddp_through_slurm_equals_one_process_of_the_same_seed(labelled_dir, feature_cache, tmp_path):
    """Two CPU processes (gloo) under ``srun`` against one process: one optimiser step on every training window.

    With every window in the step, no dropout and the ground-truth loss (every window valid, so each rank's
    mean has the same weight), the averaged DDP gradient is the single process's gradient, so the trained
    weights and test errors agree up to float32 summation order: relative tolerance 1e-4 (measured: equal in
    the 6 significant digits results.csv keeps, while the step itself moves E by about a third).
    """
    nets = {"kernels": 16, "feature_dim": 512, "dropout": 0.0, "head_dropout": 0.0}
    models = [{"model": "student", "config": str(REPO / "configs/model/student.yaml"),
               "args": {"model.alpha": 0.0, "model.net_kwargs": nets, "model.lr": 0.01}}]  # a step that counts
    overrides = {"accelerator": "cpu", "max_epochs": 1, "limit_train_batches": 1, "limit_val_batches": 1,
                 "enable_model_summary": False}

    def run(name: str, launcher: dict, **trainer) -> dict:
        folder = tmp_path / name
        folder.mkdir()
        suite = load_suite(write_suite(folder / "suite.yaml", labelled_dir, feature_cache, name=name, constant=[],
                                       models=models, launcher=launcher))
        suite.raw["data"]["init_args"]["batch_size"] = 1000  # per process: every training window in one step
        suite.raw["trainer"]["overrides"] = {**overrides, **trainer}
        summary = run_suite(suite)
        assert summary.done == ["student-by_sequence-s0"], summary
        return read_results(suite.results_path).iloc[0].to_dict()

    single = run("single", {"kind": "local", "parallel": 1, "threads_per_job": 1, "timeout_min": 10})
    assert single["n_train_windows"] % 2 == 0  # an odd count would make the sampler repeat a window on one rank
    ddp = run("ddp", {"kind": "slurm", "parallel": 1, "threads_per_job": 1, "timeout_min": 10,
                      "slurm": {"ntasks_per_node": 2, "cpus_per_task": 1}},
              devices=2, strategy="ddp", num_nodes=1)
    assert ddp["slurm_job_id"] and ddp["launcher"] == "slurm"
    assert ddp["n_test_windows"] == single["n_test_windows"]
    for column in ("E_ideal", "Dx_ideal", "Dy_ideal", "Dz_ideal"):
        print(f"{column}: one process {single[column]:.6f}, DDP {ddp[column]:.6f}")
        assert ddp[column] == pytest.approx(single[column], rel=1e-4), column
