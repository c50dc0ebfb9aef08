"""Live self-calibration of the clocks of audio nodes that do not share one: the phase front end of
``aaute track`` for such a source.

:class:`CalibratingPhase` keeps the stream's first ``seconds`` of audio, estimates the nodes' clock offsets
and drifts from it (:func:`~datamodules.features.clock_calibration.estimate_clock_offsets`) in a worker
process while the rows go on, and corrects the cross-spectra of every frame after the estimate is done; then
it estimates again from every further ``seconds`` and corrects by the line through its estimates (those that
agree with each other), so drifting clocks are followed. Rows before the first estimate, and all rows while
every estimate is refused (a log line says why), use the uncorrected time differences (the tracker marks their
rows ``uncorrected``: :meth:`CalibratingPhase.corrected`).

Why a process and not a thread: the estimate holds the interpreter lock for up to 1.4 s at a time (its
robust fit), and a tracker thread beside it then waits that long for one update.
"""

from __future__ import annotations

import logging
import multiprocessing
import signal
import time
from multiprocessing.pool import AsyncResult, Pool

import numpy as np
import torch

from datamodules.features import IncrementalPhase, PhaseRecipe
from datamodules.features.clock_calibration import (
    ClockCalibration,
    ClockCalibrationConfig,
    ClockCalibrationError,
    estimate_clock_offsets,
)
from datamodules.features.clock_following import combine_clock_estimates

log = logging.getLogger(__name__)

Estimate = tuple[ClockCalibration | ClockCalibrationError, float, float]  #: result, wall s, CPU s


def estimate_stretch(samples: np.ndarray, sample_rate: float, mics: np.ndarray) -> Estimate:
    """The clocks of one stretch of audio (channels x samples), or why not, with its wall and CPU seconds."""
    from datamodules.recording import ArrayAudio

    wall, cpu = time.perf_counter(), time.thread_time()
    try:
        result: ClockCalibration | ClockCalibrationError = estimate_clock_offsets(  # the line adds the floor
            ArrayAudio(samples, sample_rate, 0.0, mics), ClockCalibrationConfig(std_floor=0.0))
    except ClockCalibrationError as error:
        result = error
    return result, time.perf_counter() - wall, time.thread_time() - cpu


def limit_to_one_thread() -> None:
    """Run this process's torch, BLAS and OpenMP pools on one thread each, for good.

    SciPy's BLAS is loaded first (it loads lazily, and a limit reaches only the libraries already loaded).
    On the fit's small matrices more BLAS threads are overhead: a 30 s stretch of a development flight took
    20-24 s (31-35 s of CPU) with two, 16 s (as much CPU) with one, to the same offsets (two runs each)."""
    import scipy.linalg  # noqa: F401
    import scipy.optimize  # noqa: F401
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(1)
    threadpool_limits(limits=1)


def _start_worker() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the tracker's to handle
    limit_to_one_thread()  # one core for the estimate, the others stay with the tracker


class CalibratingPhase(IncrementalPhase):
    """:class:`~datamodules.features.IncrementalPhase` that estimates the nodes' clocks from the stream's first
    ``seconds`` and corrects every later frame by them (see the module docstring).

    With ``follow`` (the default) it estimates again from every further ``seconds`` of the stream and
    corrects by the line through its estimates so far, leaving out those that disagree with the line most of
    them agree with (:func:`~datamodules.features.clock_following.combine_clock_estimates`): clocks that
    drift are followed, a stretch whose fit went wrong does not bend the line,
    and a stretch whose estimate is refused (a drone too faint to hear) leaves the correction as it was, or
    the stream uncorrected until a later stretch succeeds. Without it, one estimate from the first
    ``seconds`` serves the whole stream.

    With ``background`` (the default) each estimate runs in a worker process (started with the stream, one
    thread: :func:`limit_to_one_thread`) while the stream goes on: the rows keep coming, uncorrected (or
    corrected by the earlier estimates), and the correction starts with the first block after the estimate is
    done; a stretch that ends while an estimate is still running is skipped. :meth:`close` ends the worker.
    Without it the block that completes a stretch waits for its estimate (seconds of CPU), and so do the rows
    behind it; a replay is then the same whatever the machine's speed. ``estimate_seconds`` and
    ``estimate_cpu_seconds`` say what the first estimate took (wall and CPU), ``calibrated_at``
    from which stream second frames are corrected, ``history`` each correction with the stream second it
    started.
    """

    def __init__(self, recipe: PhaseRecipe, sample_rate: float, mics: np.ndarray, seconds: float, name: str,
                 background: bool = True, follow: bool = True):
        super().__init__(recipe, sample_rate, mics.shape[0])
        self.mics, self.name, self.background, self.follow = mics, name, background, follow
        self.needed = max(1, int(round(seconds * self.sample_rate)))
        self._kept: list[np.ndarray] | None = []
        self._stretch_start = 0  #: stream sample of the kept audio's first sample
        self._pool: Pool | None = None
        self._running: tuple[int, AsyncResult] | None = None  #: the stretch's first sample, its estimate
        self.estimates: list[tuple[float, float, ClockCalibration]] = []  #: (start s, duration s, estimate)
        self.calibration: ClockCalibration | None = None
        self.corrected_from: int | None = None  #: stream sample from which frames are corrected (first estimate)
        self.history: list[tuple[float, ClockCalibration]] = []  #: each correction and its first stream second
        self.estimate_seconds: float | None = None  #: wall seconds of the first estimate
        self.estimate_cpu_seconds: float | None = None  #: its CPU seconds

    def push(self, block: np.ndarray) -> None:
        super().push(block)
        if self._running is not None and self._running[1].ready():
            (start, job), self._running = self._running, None
            self._apply(start, job.get())
        if self._kept is None:
            return
        if self.background and self._pool is None:  # its imports overlap the first stretch
            self._pool = multiprocessing.get_context("spawn").Pool(1, initializer=_start_worker)
        self._kept.append(np.array(block, dtype=np.float32))
        while self._kept is not None and self.end - self._stretch_start >= self.needed:  # a stretch is complete
            kept = np.concatenate(self._kept, axis=1)
            stretch, start = kept[:, :self.needed], self._stretch_start
            self._kept = [kept[:, self.needed:]] if self.follow else None
            self._stretch_start += self.needed
            self._start_estimate(stretch, start)

    def _start_estimate(self, stretch: np.ndarray, start: int) -> None:
        if self._running is not None:  # the previous estimate is still running: this stretch is skipped
            log.info("%s: a clock estimate is still running; the stretch %.1f-%.1f s is skipped", self.name,
                     start / self.sample_rate, (start + self.needed) / self.sample_rate)
        elif self.background and self._pool is not None:
            self._running = (start, self._pool.apply_async(estimate_stretch, (stretch, self.sample_rate, self.mics)))
        else:
            self._apply(start, estimate_stretch(stretch, self.sample_rate, self.mics))

    @property
    def calibrated_at(self) -> float | None:
        """Stream seconds from which frames are corrected (None before the first estimate)."""
        return None if self.corrected_from is None else self.corrected_from / self.sample_rate

    def corrected(self, stop: int) -> bool:
        """Whether the window ending at stream sample ``stop`` was computed from corrected cross-spectra (its
        features are computed when its last block arrives, after any estimate that block completes)."""
        return self.corrected_from is not None and stop >= self.corrected_from

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for a running estimate (at most ``timeout`` s); whether none is left running. Its correction
        starts with the next block."""
        if self._running is not None:
            self._running[1].wait(timeout)
        return self._running is None or self._running[1].ready()

    def close(self) -> None:
        """End the worker process (an estimate still running is dropped: the stream has ended)."""
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()
            self._pool, self._running = None, None

    def _apply(self, start: int, estimate: Estimate) -> None:
        result, wall, cpu = estimate
        if self.estimate_seconds is None:
            self.estimate_seconds, self.estimate_cpu_seconds = wall, cpu
        seconds = start / self.sample_rate, self.needed / self.sample_rate
        if isinstance(result, ClockCalibrationError):
            if self.calibration is not None:
                log.info("%s: stretch %.1f-%.1f s: %s; the earlier estimates stay", self.name, seconds[0],
                         sum(seconds), result)
                return
            retry = f"; trying again on the next {seconds[1]:g} s" if self.follow else ""
            log.log(logging.WARNING if start == 0 else logging.INFO,
                    "%s: stretch %.1f-%.1f s: %s; the live positions keep the nodes' clock offsets (uncorrected)%s",
                    self.name, seconds[0], sum(seconds), result, retry)
            return
        self.estimates.append((*seconds, result))
        combined = combine_clock_estimates(self.estimates)
        self.set_clocks(combined)
        now = self.end / self.sample_rate
        self.calibration = combined
        self.history.append((now, combined))
        if self.corrected_from is None:
            self.corrected_from = self.end
            log.warning("%s: from %.1f s of the stream on, phase features corrected by the %s (estimated in %.1f s)",
                        self.name, now, combined.summary(), self.estimate_seconds)
        else:
            log.info("%s: from %.1f s on, corrected by the %s (%d estimates)", self.name, now, combined.summary(),
                     len(self.estimates))
