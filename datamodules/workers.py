"""Worker processes that stop cleanly on Ctrl-C.

A terminal's Ctrl-C reaches every process of the group. Pool workers started with
:func:`interruptible_pool` ignore it (the parent alone decides, so no worker prints a traceback),
and the parent, leaving the pool, terminates them at once; a terminated worker unwinds like an
exception, so its temporary files are removed (see :mod:`datamodules.atomic`) and no finished file
is touched.

A pool left normally is closed and joined, not terminated: its workers end by the pool's own sentinel. A
worker that has run PyTorch has threads of its own, and a terminating SIGTERM that lands on one of them
leaves the main thread waiting on the task queue for good (the pool's exit then never returns).
"""

from __future__ import annotations

import multiprocessing
import signal
import sys
from multiprocessing.pool import Pool


def _ignore_interrupt() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(1))


class _ClosingPool(Pool):
    """A pool that, left without an exception, closes and waits for its workers instead of terminating them."""

    def __exit__(self, exc_type, exc_value, traceback) -> None:
        if exc_type is None:
            self.close()
            self.join()
        else:
            self.terminate()


def interruptible_pool(processes: int) -> Pool:
    """A process pool whose workers leave Ctrl-C to the parent; use it as a context manager (an exception
    terminates the workers, a normal exit lets them finish)."""
    return _ClosingPool(processes, initializer=_ignore_interrupt, context=multiprocessing.get_context())
