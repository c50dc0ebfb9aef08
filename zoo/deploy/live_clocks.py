"""Live self-calibration of the clocks of audio nodes that do not share one: the phase front end of
``aaute track`` for such a source.

:class:`CalibratingPhase` keeps the stream's first ``seconds`` of audio, estimates the nodes' clock offsets
and drifts from it (:func:`~datamodules.features.clock_calibration.estimate_clock_offsets`) in a thread while
the rows go on, and corrects the cross-spectra of every frame after the estimate is done; then it estimates
again from every further ``seconds`` and corrects by the line through all its estimates, so drifting clocks
are followed. Rows before the first estimate, and all rows while every estimate is refused (a log line
says why), use the uncorrected time differences.
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from datamodules.features import IncrementalPhase, PhaseRecipe
from datamodules.features.clock_calibration import (
    ClockCalibration,
    ClockCalibrationError,
    combine_clock_estimates,
    estimate_clock_offsets,
)

log = logging.getLogger(__name__)


class CalibratingPhase(IncrementalPhase):
    """:class:`~datamodules.features.IncrementalPhase` that estimates the nodes' clocks from the stream's first
    ``seconds`` and corrects every later frame by them (see the module docstring).

    With ``follow`` (the default) it estimates again from every further ``seconds`` of the stream and
    corrects by the line through all its estimates so far
    (:func:`~datamodules.features.clock_calibration.combine_clock_estimates`): clocks that drift are followed,
    and a stretch whose estimate is refused (a drone too faint to hear) leaves the correction as it was, or
    the stream uncorrected until a later stretch succeeds. Without it, one estimate from the first
    ``seconds`` serves the whole stream.

    With ``background`` (the default) each estimate runs in a thread while the stream goes on: the rows keep
    coming, uncorrected (or corrected by the earlier estimates), and the correction starts with the first
    block after the estimate is done; a stretch that ends while an estimate is still running is skipped.
    Without it the block that completes a stretch waits for its estimate (seconds of CPU), and so do the rows
    behind it; a replay is then the same whatever the machine's speed. ``estimate_seconds`` and
    ``estimate_cpu_seconds`` say what the first estimate took (wall and its thread's CPU), ``calibrated_at``
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
        self._thread: threading.Thread | None = None
        self._result: tuple[int, ClockCalibration | ClockCalibrationError] | None = None
        self.estimates: list[tuple[float, float, ClockCalibration]] = []  #: (start s, duration s, estimate)
        self.calibration: ClockCalibration | None = None
        self.calibrated_at: float | None = None  #: stream seconds from which frames are corrected
        self.history: list[tuple[float, ClockCalibration]] = []  #: each correction and its first stream second
        self.estimate_seconds: float | None = None  #: wall seconds of the first estimate
        self.estimate_cpu_seconds: float | None = None  #: CPU seconds of the thread that made it

    def push(self, block: np.ndarray) -> None:
        super().push(block)
        if self._thread is not None and not self._thread.is_alive():
            self._thread = None
            self._apply()
        if self._kept is None:
            return
        self._kept.append(np.array(block, dtype=np.float32))
        while self._kept is not None and self.end - self._stretch_start >= self.needed:  # a stretch is complete
            kept = np.concatenate(self._kept, axis=1)
            stretch, start = kept[:, :self.needed], self._stretch_start
            self._kept = [kept[:, self.needed:]] if self.follow else None
            self._stretch_start += self.needed
            self._start_estimate(stretch, start)

    def _start_estimate(self, stretch: np.ndarray, start: int) -> None:
        if self._thread is not None:  # the previous estimate is still running: this stretch is skipped
            log.info("%s: a clock estimate is still running; the stretch %.1f-%.1f s is skipped", self.name,
                     start / self.sample_rate, (start + self.needed) / self.sample_rate)
        elif self.background:
            self._thread = threading.Thread(target=self._estimate, args=(stretch, start), daemon=True,
                                            name=f"clock calibration of {self.name}")
            self._thread.start()
        else:
            self._estimate(stretch, start)
            self._apply()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for a running estimate (at most ``timeout`` s); whether none is left running. Its correction
        starts with the next block."""
        if self._thread is not None:
            self._thread.join(timeout)
        return self._thread is None or not self._thread.is_alive()

    def _estimate(self, samples: np.ndarray, start: int) -> None:
        import time

        from datamodules.recording import ArrayAudio

        wall, cpu = time.perf_counter(), time.thread_time()
        try:
            result: ClockCalibration | ClockCalibrationError = estimate_clock_offsets(
                ArrayAudio(samples, self.sample_rate, 0.0, self.mics))
        except ClockCalibrationError as error:
            result = error
        if self.estimate_seconds is None:
            self.estimate_seconds, self.estimate_cpu_seconds = time.perf_counter() - wall, time.thread_time() - cpu
        self._result = (start, result)

    def _apply(self) -> None:
        if self._result is None:
            return
        (start, result), self._result = self._result, None
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
        if self.calibrated_at is None:
            self.calibrated_at = now
            log.warning("%s: from %.1f s of the stream on, phase features corrected by the %s (estimated in %.1f s)",
                        self.name, now, combined.summary(), self.estimate_seconds)
        else:
            log.info("%s: from %.1f s on, corrected by the %s (%d estimates)", self.name, now, combined.summary(),
                     len(self.estimates))
