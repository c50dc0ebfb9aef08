"""Atomic file writes: write a temporary sibling, make it durable, then rename it into place.

An interrupted or failing write therefore never leaves a half-written file under the final name,
and never destroys the file that was there before. The temporary file is named
``.<name>.tmp-<pid>`` and locked (``flock``) while it is written; a process killed outright
(SIGKILL, power loss) leaves it behind unlocked, and the next write of the same file removes it
and says so.
"""

from __future__ import annotations

import fcntl
import logging
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

log = logging.getLogger(__name__)

TEMPORARY_MARK = ".tmp-"  #: temporary files are ``.<name>.tmp-<pid>``


def temporary_path(path: str | Path, pid: int | None = None) -> Path:
    """The temporary sibling a write of ``path`` by process ``pid`` (default this one) uses."""
    path = Path(path)
    return path.with_name(f".{path.name}{TEMPORARY_MARK}{os.getpid() if pid is None else pid}")


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Remove temporary files of earlier, interrupted writes of ``path``; return the removed ones.

    A temporary file is stale when no process holds its lock and it was last written before this
    process started; a write in progress (locked) is left alone.
    """
    path = Path(path)
    if not path.parent.is_dir():
        return []
    started = _process_start_time()
    removed = []
    for candidate in path.parent.glob(f".{path.name}{TEMPORARY_MARK}*"):
        if candidate == temporary_path(path) or not candidate.is_file():
            continue
        try:
            stat = candidate.stat()
            if stat.st_mtime >= started:
                continue
            with open(candidate, "rb") as handle:
                try:
                    fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    continue  # another process is writing it
                candidate.unlink()
        except FileNotFoundError:
            continue
        removed.append(candidate)
        log.warning("removed %s (%.1f MB), the temporary file of an interrupted write of %s", candidate,
                    stat.st_size / 1e6, path.name)
    return removed


def _process_start_time() -> float:
    """When this process started (Unix time), from /proc; now, where /proc is unavailable."""
    import time

    try:
        ticks = int(Path(f"/proc/{os.getpid()}/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return time.time() - uptime + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return time.time()


def check_output_folder(folder: str | Path, what: str = "the output folder") -> Path:
    """Create ``folder`` if needed and prove it writable (a probe file), before any work is done for it.

    Raises:
        NotADirectoryError: ``folder`` is an existing file (a folder was expected).
        PermissionError: ``folder`` cannot be created or written (the message names it).
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise NotADirectoryError(f"{folder}: is a file; {what} must be a folder (new or existing)")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        handle, probe = tempfile.mkstemp(prefix=".aaute-write-check-", dir=folder)
    except NotADirectoryError:
        raise NotADirectoryError(f"{folder}: a part of this path is a file; {what} must be a folder") from None
    except OSError as error:
        raise PermissionError(f"{folder}: cannot write into {what} ({error.strerror})") from None
    os.close(handle)
    os.unlink(probe)
    return folder


@contextmanager
def atomic_write(path: str | Path, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it replaces ``path``, on error it is removed.

    Stale temporary files of earlier interrupted writes of ``path`` are removed first (logged).

    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is False (checked before anything is written).
        PermissionError: the folder cannot be written (the message names ``path``, not the temporary file).
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} already exists; refusing to overwrite it")
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    tmp = temporary_path(path)
    try:
        lock = os.open(tmp, os.O_WRONLY | os.O_CREAT, 0o644)
    except OSError as error:  # name the file asked for, not the hidden temporary one
        raise PermissionError(f"{path}: cannot write into {path.parent} ({error.strerror})") from None
    try:
        fcntl.flock(lock, fcntl.LOCK_EX)  # held until the rename: marks the write as in progress
        yield tmp
        with open(tmp, "rb") as written:
            os.fsync(written.fileno())
        os.replace(tmp, path)
    finally:
        os.close(lock)
        if tmp.exists():
            tmp.unlink()
