"""Which of a suite's local jobs starts next: longest first, within a memory budget, as a cluster scheduler does.

Order: jobs that an earlier run of the suite timed (``wall_time_s`` of their newest ``ok`` row in its
``results.csv``) go longest first, so the parallel lanes finish together; jobs never timed go before them, in
the suite's order (the suite lists its longest first).

Memory: each job has an expected peak, the resident memory it reached when it last ran (``peak_rss_mb`` of its
newest row with one), else the suite's hint for its model (``memory_gb:`` beside the model), else
``launcher.job_memory_gb``. A job starts only if the expected peaks of the running jobs plus its own fit
``launcher.memory_gb``; a job alone always starts, however large. When the next job does not fit beside the
running ones it waits, and a later job may start in its place only if it fits now and would also fit beside
the waiting one: so once the running jobs end the waiting job starts, never passed over again (EASY
backfilling, with memory instead of nodes). Peaks are resident set sizes: pages shared between processes (the
libraries) count in each, so their sum errs high, which leaves room for the runner's own process.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from benchmarks.results import read_results
from benchmarks.suite import JobSpec

DEFAULT_JOB_GB = 1.5  #: expected peak of a job never run and without a hint (light jobs measured 1.1-1.3 GB)


@dataclass(frozen=True)
class Peak:
    """A job's expected peak memory and where the figure comes from."""

    gb: float
    source: str  #: 'measured' (an earlier row), 'hint' (the suite's memory_gb) or 'default'


def _newest(results: Path, column: str, ok_only: bool) -> dict[tuple[str, str], float]:
    """(suite, job_id) -> the positive value of ``column`` in the newest row that has one; {} without a file."""
    if not results.exists():
        return {}
    frame = read_results(results, check_values=False)  # a bad cell is the leaderboard's to refuse
    if ok_only:
        frame = frame[frame["status"] == "ok"]
    values: dict[tuple[str, str], float] = {}
    for suite, job_id, value in zip(frame["suite"], frame["job_id"], frame[column], strict=True):
        if not pd.isna(value) and math.isfinite(value) and value > 0:
            values[(suite, job_id)] = float(value)
    return values


def expected_peaks(jobs: Sequence[JobSpec], results: Path, default_gb: float = DEFAULT_JOB_GB) -> dict[str, Peak]:
    """The expected peak of every job: measured in ``results`` (an earlier run), else its hint, else the default."""
    measured = _newest(results, "peak_rss_mb", ok_only=False)
    peaks = {}
    for job in jobs:
        if (job.suite, job.job_id) in measured:
            peaks[job.job_id] = Peak(measured[(job.suite, job.job_id)] / 1024, "measured")
        elif job.memory_gb is not None:
            peaks[job.job_id] = Peak(float(job.memory_gb), "hint")
        else:
            peaks[job.job_id] = Peak(float(default_gb), "default")
    return peaks


def longest_first(jobs: Sequence[JobSpec], results: Path) -> list[JobSpec]:
    """``jobs`` in start order: those never timed in ``results`` first (the suite's order), then longest first."""
    seconds = _newest(results, "wall_time_s", ok_only=True)
    return sorted(jobs, key=lambda job: -seconds.get((job.suite, job.job_id), math.inf))


def next_job(pending: Sequence[str], running: Sequence[str], peaks: Mapping[str, Peak],
             budget_gb: float | None) -> int | None:
    """Index in ``pending`` (job ids, in start order) of the job to start now, or None to wait.

    ``running``: the ids of the running jobs (the caller keeps their number below its parallel limit).
    Without a budget the first pending job starts.
    """
    if not pending:
        return None
    if budget_gb is None or not running:
        return 0
    used = sum(peaks[job_id].gb for job_id in running)
    head = peaks[pending[0]].gb
    if used + head <= budget_gb:
        return 0
    for index, job_id in enumerate(pending[1:], start=1):
        size = peaks[job_id].gb
        if used + size <= budget_gb and head + size <= budget_gb:
            return index
    return None


def wait_message(job_id: str, running: Sequence[str], peaks: Mapping[str, Peak], budget_gb: float) -> str:
    """Why ``job_id`` waits: its expected peak beside the running jobs' would exceed the budget."""
    used = sum(peaks[other].gb for other in running)
    peak = peaks[job_id]
    return (f"{job_id} waits for memory: expected peak {peak.gb:.1f} GB ({peak.source}) beside {used:.1f} GB of "
            f"running jobs ({', '.join(running)}) exceeds launcher.memory_gb {budget_gb:g}")


def simulate_schedule(order: Sequence[str], durations: Mapping[str, float], peaks: Mapping[str, Peak],
                      parallel: int, budget_gb: float | None) -> tuple[float, float, dict[str, float]]:
    """Replay the launcher's choices with known durations: (makespan s, highest summed expected peak GB, starts).

    What a budget costs in time can be estimated from an earlier run's ``wall_time_s`` before running again.
    """
    clock, pending = 0.0, list(order)
    running: dict[str, float] = {}  # job id -> end time
    starts: dict[str, float] = {}
    highest = 0.0
    while pending or running:
        while pending and len(running) < max(1, parallel):
            index = next_job(pending, list(running), peaks, budget_gb)
            if index is None:
                break
            job_id = pending.pop(index)
            starts[job_id] = clock
            running[job_id] = clock + durations[job_id]
            highest = max(highest, sum(peaks[other].gb for other in running))
        ending = min(running, key=running.__getitem__)
        clock = running.pop(ending)
    return clock, highest, starts
