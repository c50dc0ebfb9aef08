"""Suite jobs on a Slurm cluster: one job array per stage, states from ``squeue``, submitit kept quiet.

The jobs of a stage go to Slurm as one job array (submitit's batch submission), at most
``launcher.parallel`` of them running at once (the array's ``%`` limit): one ``sbatch`` for the
whole stage, and the cluster's scheduler, not this process, keeps the limit. Whether a job is
queued, running or over, and why it ended, is read from ``squeue`` (finished jobs stay listed for
the controller's ``MinJobAge``), because small clusters keep no accounting and submitit's own
``sacct`` polling then fills the console with warnings; those are filtered out here. A job that
Slurm ended without a result (``scancel``, its time limit, a node failure, out of memory) is
reported with Slurm's state and reason.
"""

from __future__ import annotations

import getpass
import logging
import shutil
import subprocess
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchmarks.suite import JobSpec, Suite
from datamodules.errors import AauteError

log = logging.getLogger(__name__)

QUEUED_STATES = {"PENDING", "CONFIGURING", "REQUEUED", "REQUEUE_HOLD", "REQUEUE_FED", "RESV_DEL_HOLD",
                 "SUSPENDED", "RESIZING", "STOPPED"}
#: states of a job that ended; COMPLETED and FAILED jobs wrote submitit's result (or error) file
ENDED_STATES = {"COMPLETED", "FAILED", "CANCELLED", "TIMEOUT", "NODE_FAIL", "OUT_OF_MEMORY", "PREEMPTED",
                "BOOT_FAIL", "DEADLINE", "SPECIAL_EXIT", "REVOKED"}
WHY_ENDED = {"CANCELLED": "cancelled (scancel)", "TIMEOUT": "killed at its time limit",
             "NODE_FAIL": "its node failed", "OUT_OF_MEMORY": "out of memory", "PREEMPTED": "preempted",
             "BOOT_FAIL": "its node failed to boot", "DEADLINE": "past its deadline"}
#: how long a submitted job may be missing from ``squeue`` before it counts as ended without a trace
VANISHED_AFTER_S = 30.0


class LauncherError(AauteError, ValueError):
    """A launcher that cannot run here (no Slurm on this machine)."""


class SacctNoise(logging.Filter):
    """Drops submitit's messages about ``sacct``, which fails on clusters without accounting."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "sacct" not in record.getMessage()


def quiet_submitit() -> None:
    """Silence submitit's ``sacct`` warnings (idempotent)."""
    logger = logging.getLogger("submitit")
    if not any(isinstance(f, SacctNoise) for f in logger.filters):
        logger.addFilter(SacctNoise())


@dataclass(frozen=True)
class SlurmState:
    """One job's line of ``squeue``."""

    state: str
    reason: str = ""
    node: str = ""


def parse_squeue(text: str) -> dict[str, SlurmState]:
    """``squeue -h -r -o '%i|%T|%r|%N'`` output -> Slurm job id (``123`` or ``123_4``) -> state."""
    states: dict[str, SlurmState] = {}
    for line in text.splitlines():
        parts = line.strip().split("|")
        if len(parts) != 4 or not parts[0]:
            continue
        job_id, state, reason, node = parts
        states[job_id] = SlurmState(state.split()[0], "" if reason in ("None", "(null)") else reason, node)
    return states


def queue_states() -> dict[str, SlurmState] | None:
    """The states of this user's jobs (finished ones too, while the controller keeps them); None if squeue fails."""
    command = ["squeue", "-h", "-r", "--states=all", "-u", getpass.getuser(), "-o", "%i|%T|%r|%N"]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=60, check=True)
    except (OSError, subprocess.SubprocessError) as error:
        log.warning("squeue failed (%s); retrying", error)
        return None
    return parse_squeue(done.stdout)


def ended_without_result(state: SlurmState, timeout_min: int) -> str:
    """The error of a job Slurm ended before it wrote a result."""
    why = WHY_ENDED.get(state.state, "ended by Slurm")
    if state.state == "TIMEOUT":
        why += f" of {timeout_min} min (launcher.timeout_min)"
    return f"Slurm {state.state}: {why}" + (f" [{state.reason}]" if state.reason else "")


def require_slurm() -> None:
    """Refuse early (before any data is prepared) where there is no Slurm to submit to."""
    missing = [command for command in ("sbatch", "srun", "squeue") if shutil.which(command) is None]
    if missing:
        raise LauncherError(f"launcher slurm: no {', '.join(missing)} on PATH (run from a Slurm login node, start "
                            f"a local cluster with scripts/local_slurm.sh up, or use --launcher local)")


def array_parameters(suite: Suite, parallel: int) -> dict[str, Any]:
    """submitit ``SlurmExecutor`` parameters of one stage's array: the suite's ``launcher.slurm`` keys,
    its timeout, and the array's concurrency limit (``launcher.parallel``).

    Slurm warns a job (submitit's USR2, on which a job is stopped as timed out) ``signal_delay_s`` before
    its limit, and may warn up to 60 s earlier still (``sbatch --signal``); submitit's default of 90 s
    would then warn a job of a few minutes as it starts, so short limits get a quarter of the limit.
    """
    minutes = int(suite.launcher["timeout_min"])
    return {"time": minutes, "job_name": f"aaute-{suite.name}", "array_parallelism": max(1, int(parallel)),
            "signal_delay_s": min(90, minutes * 15), **dict(suite.launcher.get("slurm") or {})}


def array_executor(suite: Suite, parallel: int, folder: Path | None = None):
    """A submitit Slurm executor for a stage's array, its logs in ``folder`` (default ``<out>/slurm``)."""
    import submitit

    try:
        executor = submitit.SlurmExecutor(folder or Path(suite.out) / "slurm")
    except RuntimeError as error:  # no srun on this machine
        raise LauncherError(f"launcher slurm: {error} (run from a Slurm login node, or use --launcher local)"
                            ) from None
    executor.update_parameters(**array_parameters(suite, parallel))
    return executor


def submit_array(suite: Suite, jobs: list[JobSpec], parallel: int, function: Callable[[JobSpec], Any]) -> list:
    """Submit ``function(job)`` for every job as one Slurm array; the submitit handles, in order."""
    executor = array_executor(suite, parallel)
    with executor.batch():
        handles = [executor.submit(function, job) for job in jobs]
    return handles


def stage_counts(states: Iterable[str]) -> dict[str, int]:
    """queued / running / ended counts of Slurm states."""
    counts = {"queued": 0, "running": 0, "ended": 0}
    for state in states:
        counts["queued" if state in QUEUED_STATES else "ended" if state in ENDED_STATES else "running"] += 1
    return counts


def has_result(handle) -> bool:
    """Whether every task of a submitit job wrote its result file."""
    tasks = getattr(handle, "_sub_jobs", None) or [handle]
    return all(task.paths.result_pickle.exists() for task in tasks)


def run_on_slurm(suite: Suite, jobs: list[JobSpec], parallel: int, function: Callable[[JobSpec], Any],
                 finish: Callable[[JobSpec, Any, str | None, dict[str, Any]], bool],
                 poll_seconds: float = 2.0) -> None:
    """Run ``jobs`` as one array and call ``finish(job, handle, failure, slurm_columns)`` as each ends.

    ``failure`` is Slurm's reason when the job ended without a result (else None: read the result);
    ``finish`` returns whether the job succeeded, for the counts of the progress line.
    """
    if not jobs:
        return
    quiet_submitit()
    start = time.perf_counter()
    handles = submit_array(suite, jobs, parallel, function)
    pending = {handle.job_id: (job, handle) for job, handle in zip(jobs, handles, strict=True)}
    log.info("submitted %d job(s) as Slurm array %s (at most %d at once)", len(jobs),
             handles[0].job_id.split("_")[0], parallel)
    try:
        _follow(suite, pending, finish, start, poll_seconds)
    except KeyboardInterrupt:  # the suite is stopped: so are its jobs (they would train on, unrecorded)
        for _, handle in pending.values():
            handle.cancel(check=False)
        log.warning("interrupted: cancelled %d unfinished Slurm job(s) of array %s; a rerun submits them again",
                    len(pending), handles[0].job_id.split("_")[0])
        raise


def _follow(suite: Suite, pending: dict[str, tuple[JobSpec, Any]],
            finish: Callable[[JobSpec, Any, str | None, dict[str, Any]], bool], start: float,
            poll_seconds: float) -> None:
    """Poll ``squeue`` until every job of ``pending`` has ended, calling ``finish`` for each as it does."""
    done = failed = 0
    last_line = ""
    seen: set[str] = set()
    while pending:
        states = queue_states()
        if states is None:
            time.sleep(poll_seconds)
            continue
        for slurm_id, (job, handle) in list(pending.items()):
            state = states.get(slurm_id)
            if state is not None:
                seen.add(slurm_id)
            result = has_result(handle)
            if state is not None and state.state not in ENDED_STATES and not result:
                continue
            if (state is None and not result and slurm_id not in seen
                    and time.perf_counter() - start < VANISHED_AFTER_S):
                continue  # not listed yet
            del pending[slurm_id]
            failure = None
            if not result and (state is None or state.state not in ("COMPLETED", "FAILED")):
                failure = ended_without_result(state or SlurmState("UNKNOWN", "no longer listed by squeue"),
                                               int(suite.launcher["timeout_min"]))
            columns = {"slurm_job_id": slurm_id, "node": state.node if state else ""}
            if finish(job, handle, failure, columns):
                done += 1
            else:
                failed += 1
        counts = stage_counts(states[i].state for i in pending if i in states)
        line = (f"[slurm: {counts['queued'] + len(pending) - sum(counts.values())} queued, {counts['running']} "
                f"running, {done} done, {failed} failed]")
        if line != last_line:
            elapsed = time.perf_counter() - start
            log.info("%s %02d:%02d", line, elapsed // 60, elapsed % 60)
            last_line = line
        if pending:
            time.sleep(poll_seconds)
