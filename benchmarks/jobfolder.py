"""A benchmark job's folder: one running job owns it (a lock), and a rerun starts from a clean one.

The job's process holds an exclusive ``flock`` on ``<job folder>/.job.lock`` while it runs (on a
multi-process job, rank 0 alone). The kernel drops the lock when the process ends, however it ends,
so a lock file whose lock nobody holds is stale: the process that wrote it is gone. Before a job
runs again in a folder:

- a live lock (a job still running there, e.g. one orphaned by a killed ``aaute benchmark``) stops
  that job with :class:`JobFolderBusy`, naming the running process; it is not started twice;
- a stale lock (a non-empty lock file nobody holds: its writer died; a job that ends normally empties
  it) is taken over with a warning;
- the earlier run's files are moved aside to ``jobs/<job>.previous/`` (replacing an older one), so
  the new run's checkpoint has its plain name again (``checkpoints/best.ckpt``), never a ``-v1``
  copy beside a stale one.
"""

from __future__ import annotations

import fcntl
import logging
import os
import shutil
import socket
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from datamodules.errors import AauteError

log = logging.getLogger(__name__)

LOCK_NAME = ".job.lock"
PREVIOUS_SUFFIX = ".previous"
#: environment variables naming a process's global rank, in the order they are trusted
RANK_VARIABLES = ("SLURM_PROCID", "SUBMITIT_LOCAL_GLOBALID", "LOCAL_RANK")


class JobFolderBusy(AauteError, RuntimeError):
    """A job folder whose lock is held by a running process (the message names the folder and the process)."""


def task_rank() -> int:
    """This process's rank in a multi-process job (Slurm, submitit's local tasks, torchrun); 0 alone."""
    for name in RANK_VARIABLES:
        value = os.environ.get(name, "").strip()
        if value.isdigit():
            return int(value)
    return 0


def lock_owner(folder: str | Path) -> str:
    """What the lock file of ``folder`` says about its writer (``pid 123 on host``), '' if unknown."""
    try:
        return (Path(folder) / LOCK_NAME).read_text().strip()
    except OSError:
        return ""


def _try_lock(handle) -> bool:
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def check_free(folder: str | Path) -> None:
    """Raise :class:`JobFolderBusy` if a running process holds ``folder``'s lock; warn about a stale one."""
    path = Path(folder) / LOCK_NAME
    if not path.is_file():
        return
    with open(path, "rb") as handle:
        if not _try_lock(handle):
            owner = lock_owner(folder) or "its lock is held"
            raise JobFolderBusy(f"{folder}: a job is still running in this folder ({owner}); it is not started "
                                f"again: wait for it to end, or stop that process")
        fcntl.flock(handle, fcntl.LOCK_UN)
    owner = lock_owner(folder)
    if owner:  # a job that ended normally empties its lock file
        log.warning("%s: stale lock of a job that is no longer running (%s) taken over", folder, owner)


def clear_for_rerun(folder: str | Path) -> Path | None:
    """Make ``folder`` ready for a new run: refuse a live job, move an earlier run aside; where it went.

    Raises:
        JobFolderBusy: a running process holds the folder's lock (nothing is moved).
    """
    folder = Path(folder)
    if not folder.exists():
        return None
    check_free(folder)
    if not any(folder.iterdir()):
        return None
    previous = folder.with_name(folder.name + PREVIOUS_SUFFIX)
    if previous.exists():
        shutil.rmtree(previous)
    folder.rename(previous)
    log.info("%s: the earlier run's files were moved aside to %s (the new run starts from an empty folder)",
             folder, previous)
    return previous


@contextmanager
def hold(folder: str | Path) -> Iterator[None]:
    """Hold ``folder``'s lock while the block runs (rank 0 only; other ranks hold nothing).

    Raises:
        JobFolderBusy: another running process holds it.
    """
    if task_rank() != 0:
        yield
        return
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_NAME
    with open(path, "a+") as handle:  # closing drops the lock
        if not _try_lock(handle):
            owner = lock_owner(folder) or "its lock is held"
            raise JobFolderBusy(f"{folder}: a job is already running in this folder ({owner}); this one stops")
        if handle.seek(0, os.SEEK_END):  # the writer died holding it (a normal end empties the file)
            log.warning("%s: stale lock of a job that is no longer running (%s) taken over", folder,
                        lock_owner(folder) or "writer unknown")
        handle.truncate(0)
        handle.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        handle.flush()
        try:
            yield
        finally:
            handle.truncate(0)  # ended: nothing stale is left
