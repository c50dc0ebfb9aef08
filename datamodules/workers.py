"""Worker processes that stop cleanly on Ctrl-C.

A terminal's Ctrl-C reaches every process of the group. Pool workers started with
:func:`interruptible_pool` ignore it (the parent alone decides, so no worker prints a traceback),
and the parent, leaving the pool, terminates them at once; a terminated worker unwinds like an
exception, so its temporary files are removed (see :mod:`datamodules.atomic`) and no finished file
is touched.
"""

from __future__ import annotations

import multiprocessing
import signal
import sys
from multiprocessing.pool import Pool


def _ignore_interrupt() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(1))


def interruptible_pool(processes: int) -> Pool:
    """A process pool whose workers leave Ctrl-C to the parent; use it as a context manager (exit terminates)."""
    return multiprocessing.get_context().Pool(processes, initializer=_ignore_interrupt)
