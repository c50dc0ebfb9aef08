"""Run a benchmark suite: prepare its data, launch its jobs with submitit, append their rows to ``results.csv``.

Each job runs in its own process (submitit's local executor on one machine, its Slurm executor on a
cluster), so a crash or an out-of-memory kill loses that job alone: its row records the error
and the path of its log, and the suite goes on. Rows are appended atomically as jobs finish;
re-running a suite skips the jobs whose row is ``ok`` with the same configuration hash, so an
interrupted run loses nothing (``rerun=True`` forces every job again). A job that runs again finds
its folder cleared (the earlier run moved aside, :mod:`benchmarks.jobfolder`), and a job still running
in its folder (orphaned by a killed runner) is never started twice. Profiling jobs run last, one at a
time, so their timings do not share the cores with training.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from benchmarks.jobfolder import JobFolderBusy, clear_for_rerun
from benchmarks.jobs import base_row, run_job
from benchmarks.register import register_job_weights
from benchmarks.results import append_rows, read_results
from benchmarks.scheduling import DEFAULT_JOB_GB, expected_peaks, longest_first, next_job, wait_message
from benchmarks.suite import JobSpec, Suite, check_job_args, expand_jobs

log = logging.getLogger(__name__)

_EXCEPTION_LINE = re.compile(r"^[A-Za-z_][\w.]*(Error|Exception|Interrupt|Exit)\b.*")
SIMULATE_KEYS = {"sequences", "seconds", "seed", "workers", "scene"}


class JobEndedError(RuntimeError):
    """A job its launcher ended before it returned a result (cancelled, killed at its time limit, ...)."""


@dataclass
class RunSummary:
    """What a suite run did."""

    results: Path
    done: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    busy: list[str] = field(default_factory=list)  #: not started: a job still runs in their folder
    seconds: float = 0.0
    stages: dict[str, float] = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------- data


def prepare_data(suite: Suite) -> str:
    """Simulate and label the suite's data where it asks to (reusing what exists); return its fingerprint."""
    from datamodules.cache import path_fingerprint
    from datamodules.formats import discover_all

    data = suite.data
    root = Path(data["root"])
    simulate = data.get("simulate")
    if simulate:
        unknown = sorted(set(simulate) - SIMULATE_KEYS)
        if unknown:
            raise ValueError(f"{suite.path}: unknown data.simulate key(s) {unknown}; known: {sorted(SIMULATE_KEYS)}")
        from datamodules.simulate.simulator import SimulationConfig, simulate_dataset

        config = SimulationConfig(duration=float(simulate.get("seconds", 60.0)),
                                  scene=simulate.get("scene", "rooftop"))
        simulate_dataset(root, int(simulate.get("sequences", 15)), config, seed=int(simulate.get("seed", 0)),
                         workers=int(simulate.get("workers", 1)))
    label = data.get("label")
    if label:
        from datamodules.label import label_paths

        outcomes = label_paths([root], workers=int(label.get("workers", 1)), skip_existing=True)
        failed = [o for o in outcomes if o.error]
        if failed:
            raise ValueError(f"labelling failed for {len(failed)} recording(s), first: {failed[0].path}: "
                             f"{failed[0].error}")
    if not root.exists():
        raise ValueError(f"{suite.path}: data.root {root} does not exist (set data.root or --data.root)")
    paths = discover_all([root])
    if not paths:
        raise ValueError(f"{suite.path}: no recordings under data.root {root}")
    digest = hashlib.sha256("\n".join(path_fingerprint(p) for p in sorted(paths)).encode())
    return digest.hexdigest()[:16]


# ---------------------------------------------------------------------------------------------- launching


def make_executor(suite: Suite, job: JobSpec, kind: str):
    """A submitit executor for one job, its logs in the job's folder."""
    import submitit

    folder = Path(job.job_dir) / "logs"
    if kind == "debug":
        return submitit.DebugExecutor(folder)
    if kind == "local":
        executor = submitit.LocalExecutor(folder)
        executor.update_parameters(timeout_min=int(suite.launcher["timeout_min"]))
        return executor
    if kind == "slurm":  # one job alone (a suite's stages go as arrays: benchmarks.slurm)
        from benchmarks.slurm import array_executor

        executor = array_executor(suite, 1, folder)
        executor.update_parameters(job_name=f"aaute-{job.job_id}")
        return executor
    raise ValueError(f"unknown launcher {kind!r}; known: local, slurm, debug")


def _relative(path: Any, base: Path) -> Any:
    if not path or not isinstance(path, str) or path == "last":
        return path
    return os.path.relpath(Path(path).resolve(), base.resolve())


def _error_row(job: JobSpec, error: BaseException, log_path: str) -> dict[str, Any]:
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    # submitit's message holds the job's own traceback: its last "SomeError: ..." line is the cause
    raised = [line for line in lines if _EXCEPTION_LINE.match(line)]
    message = raised[-1] if raised else (lines[0] if lines else type(error).__name__)
    row = base_row(job)
    row.update(status="failed", error=message[:500], log_path=log_path)
    return row


def finished_jobs(results: Path) -> dict[str, str]:
    """job_id -> config hash of the jobs whose latest row is ok."""
    if not results.exists():
        return {}
    frame = read_results(results, check_values=False)  # a bad cell is the leaderboard's to refuse
    done: dict[str, str] = {}
    for _, row in frame.iterrows():
        if row["status"] == "ok":
            done[row["job_id"]] = row["config_hash"]
        else:
            done.pop(row["job_id"], None)
    return done


def _progress(summary: RunSummary, running: int, pending: int, start: float) -> str:
    elapsed = time.perf_counter() - start
    return (f"[{len(summary.done)} done, {running} running, {len(summary.failed)} failed, {pending} remaining, "
            f"{int(elapsed // 60):02d}:{int(elapsed % 60):02d}]")


def launch_jobs(suite: Suite, jobs: list[JobSpec], parallel: int, kind: str, summary: RunSummary,
                poll_seconds: float = 1.0) -> None:
    """Run ``jobs`` at most ``parallel`` at once, within the memory budget; append each row as its job ends.

    The start order and the budget (``launcher.memory_gb``, :mod:`benchmarks.scheduling`) are the local and
    debug launchers'; on Slurm its scheduler keeps the nodes' memory (``launcher.slurm: {mem: ...}``).
    """
    start = time.perf_counter()
    if kind == "slurm":  # one array; Slurm keeps the limit and its states drive the progress line
        from benchmarks.slurm import run_on_slurm

        def finish(job: JobSpec, handle: Any, failure: str | None, columns: dict[str, Any]) -> bool:
            log.info("%s %s", job.job_id, finish_job(suite, job, handle, kind, summary, failure, columns))
            return job.job_id in summary.done

        run_on_slurm(suite, jobs, parallel, run_job, finish)
        return
    budget = suite.launcher["memory_gb"]
    peaks = expected_peaks(jobs, suite.results_path, suite.launcher["job_memory_gb"] or DEFAULT_JOB_GB)
    pending = longest_first(jobs, suite.results_path)
    if budget is not None and parallel > 1:
        log.info("memory budget %g GB for %d jobs at once; expected peaks: %s", budget, parallel,
                 ", ".join(f"{job.job_id} {peaks[job.job_id].gb:.1f} GB ({peaks[job.job_id].source})"
                           for job in pending))
    running: dict[str, tuple[JobSpec, Any]] = {}
    waiting: set[str] = set()  # jobs already said to wait for memory
    while pending or running:
        while pending and len(running) < parallel:
            index = next_job([j.job_id for j in pending], list(running), peaks, budget)
            if index is None or index > 0:
                head = pending[0].job_id
                if head not in waiting:
                    waiting.add(head)
                    log.info("%s %s", _progress(summary, len(running), len(pending), start),
                             wait_message(head, list(running), peaks, budget))
                if index is None:
                    break
            job = pending.pop(index)
            try:
                clear_for_rerun(job.job_dir)  # an earlier run's files go aside; a live one stops this job
            except JobFolderBusy as error:
                summary.busy.append(job.job_id)
                log.error("%s %s not started: %s", _progress(summary, len(running), len(pending), start),
                          job.job_id, error)
                continue
            handle = make_executor(suite, job, kind).submit(run_job, job)
            running[job.job_id] = (job, handle)
            log.info("%s started %s", _progress(summary, len(running), len(pending), start), job.job_id)
        for job_id, (job, handle) in list(running.items()):
            if not handle.done():
                continue
            del running[job_id]
            status = finish_job(suite, job, handle, kind, summary)
            log.info("%s %s %s", _progress(summary, len(running), len(pending), start), job_id, status)
        if running:
            time.sleep(poll_seconds)


def finish_job(suite: Suite, job: JobSpec, handle: Any, kind: str, summary: RunSummary,
               failure: str | None = None, columns: dict[str, Any] | None = None) -> str:
    """Append the row of an ended job (its result, or its error and log); return its status for the log.

    ``failure``: why the launcher ended the job without a result (e.g. Slurm's TIMEOUT); ``columns``:
    launcher provenance (``slurm_job_id``, ``node``) that the job's own row does not override.
    """
    log_path = _relative(str(handle.paths.stderr), suite.out)
    try:
        if failure is not None:
            raise JobEndedError(failure)
        row = handle.results()[0]  # a multi-task (DDP) job: rank 0's row
        row["log_path"] = log_path
        for key in ("predictions_path", "checkpoint_path"):
            row[key] = _relative(row.get(key), suite.out)
        summary.done.append(job.job_id)
        status = f"ok in {row['wall_time_s']:.0f} s"
        if row.get("peak_rss_mb") is not None:
            status += f", peak {row['peak_rss_mb'] / 1024:.1f} GB"
        if row.get("E_ideal") is not None:
            status += f", E_ideal {row['E_ideal']:.2f} m"
    except Exception as error:  # the job's own failure, reported by submitit, or the launcher's
        row = _error_row(job, error, log_path)
        if "timed-out" in row["error"]:  # submitit stopped the job at the scheduler's warning before its limit
            row["error"] = (f"timed out: stopped at its time limit of {suite.launcher['timeout_min']} min "
                            f"(launcher.timeout_min): {row['error']}")[:500]
        summary.failed.append(job.job_id)
        status = f"FAILED: {row['error']} (log: {suite.out / log_path})"
    row["launcher"] = kind
    for key, value in (columns or {}).items():
        if value and not row.get(key):
            row[key] = value
    append_rows(suite.results_path, [row])
    register_finished_job(suite, job, row)
    return status


def register_finished_job(suite: Suite, job: JobSpec, row: dict[str, Any]) -> None:
    """A finished model job's best checkpoint becomes named weights; a failure here never fails the suite."""
    try:
        entry = register_job_weights(suite, job, row)
    except (ValueError, OSError) as error:
        log.warning("job %s: its checkpoint was not registered as weights: %s", job.job_id, error)
        return
    if entry is not None:
        log.info("weights %s registered (%s)", entry.name, entry.source)


def run_suite(suite: Suite, rerun: bool = False, launcher: str | None = None, only: list[str] | None = None
              ) -> RunSummary:
    """Prepare data, then run every unfinished job of ``suite`` (``only``: job ids or model names)."""
    start = time.perf_counter()
    summary = RunSummary(suite.results_path)
    suite.out.mkdir(parents=True, exist_ok=True)
    kind = launcher or suite.launcher["kind"]
    if kind == "slurm":
        from benchmarks.slurm import require_slurm

        require_slurm()
    if suite.raw.get("expected_runtime"):
        log.info("suite %s: expected run time: %s", suite.name, suite.raw["expected_runtime"])
    stage = time.perf_counter()
    fingerprint = prepare_data(suite)
    summary.stages["data"] = time.perf_counter() - stage
    jobs = expand_jobs(suite, fingerprint)
    if only:
        jobs = [j for j in jobs if j.job_id in only or j.model in only]
    check_job_args(suite, jobs)
    finished = {} if rerun else finished_jobs(suite.results_path)
    todo = [j for j in jobs if finished.get(j.job_id) != j.config_hash]
    summary.skipped = [j.job_id for j in jobs if j not in todo]
    if summary.skipped:
        log.info("%d of %d jobs already finished (results in %s); --rerun runs them again",
                 len(summary.skipped), len(jobs), suite.results_path)
    parallel = max(1, int(suite.launcher["parallel"]))
    stage = time.perf_counter()
    launch_jobs(suite, [j for j in todo if j.kind != "profile"], parallel, kind, summary)
    summary.stages["train_test"] = time.perf_counter() - stage
    stage = time.perf_counter()
    launch_jobs(suite, [j for j in todo if j.kind == "profile"], 1, kind, summary)
    summary.stages["profile"] = time.perf_counter() - stage
    summary.seconds = time.perf_counter() - start
    return summary
