"""The streaming twin of the phase recipe: GCC-PHAT of the window ending now, each frame's cross-spectra once.

:class:`IncrementalPhase` receives a stream in blocks and gives, after any block, the recipe's features
(pairs x frames x lags) of the window ending at the stream's last sample, the same frames, band, lags and
interpolation as :class:`~datamodules.features.PhaseWindows` computes offline (it uses the same
:class:`~datamodules.features.GccPhat`), so the two agree to float rounding (tested to 1e-5 against
float32 features).

What is shared. Every frame's cross-spectra (pairs x band bins) are kept by the frame's first sample and
computed once, whichever windows or long-term mean use them. A window ending at sample ``s`` reads the
frames starting at ``s - span + j * frame``, so windows share frames only when the hop between them is a
multiple of the frame: at 48 kHz a 4800-sample hop and a 4096-sample frame share none (the grids meet
again only every 6.4 s), and each update computes its window's frames anew; a hop of whole frames
(e.g. 4096 samples) computes one new frame per update.

Static suppression (``recipe.suppress_static``): the causal long-term mean of the cross-spectra runs over
the consecutive frames from the stream's first sample (the grid ``0, frame, 2 frame, ...``), folded as
the audio arrives: every frame that ends before the current window's first sample, with equal weights
at first and then exponentially, exactly as :meth:`PhaseWindows._fold_past` does. A frame holding NaN
or infinite samples is left out of the mean (offline such audio is refused).

Node clocks (:meth:`IncrementalPhase.set_clocks`): from then on every frame's cross-spectra are corrected
to node 0's clock as :class:`~datamodules.features.PhaseWindows` does with ``clocks``; frames already
computed are computed again, and the long-term mean is corrected by the offsets of the newest sample (a
newer estimate replaces the clocks the same way, the mean moved by the change).
"""

from __future__ import annotations

import numpy as np
import torch

from datamodules.errors import ConfigError
from datamodules.features.phase import (
    GccPhat,
    NodeClocks,
    PhaseRecipe,
    correct_cross_spectra,
    fold_mean,
    without_mean,
)


class IncrementalPhase:
    """Phase features of the window ending at the stream's last sample (see the module docstring).

    Args:
        recipe: a phase recipe of :data:`~datamodules.features.PHASE_RECIPES`.
        sample_rate: Hz.
        channels: microphones (at least 2).
    """

    def __init__(self, recipe: PhaseRecipe, sample_rate: float, channels: int):
        self.recipe, self.sample_rate, self.channels = recipe, float(sample_rate), int(channels)
        try:
            self.gcc = GccPhat(recipe, self.sample_rate, self.channels)
        except ValueError as error:
            raise ConfigError(str(error)) from None
        self.frame = self.gcc.frame
        self.window = self.frame * recipe.frames  #: samples one window reads
        self.keep = self.window + 2 * self.frame  #: samples retained behind the newest
        self._buffer = np.zeros((self.channels, 2 * self.keep), dtype=np.float32)
        self._filled = 0
        self.end = 0  #: samples received so far (absolute index of the next one)
        #: first sample of a frame -> its cross-spectra (pairs x bins), None where it holds non-finite samples
        self._store: dict[int, torch.Tensor | None] = {}
        self.mean: torch.Tensor | None = None  #: long-term mean cross-spectra (pairs x bins)
        self.next_frame = 0  #: first sample of the next frame to fold into the mean
        self.folded = 0
        self.decay = float(np.exp(-(self.frame / self.sample_rate) / recipe.static_seconds))
        self.computed = 0  #: frames whose cross-spectra were computed
        self.clocks: NodeClocks | None = None  #: the nodes' clocks the cross-spectra are corrected by
        self.freqs = self.gcc.bins.to(torch.float64) * self.sample_rate / self.gcc.n_fft
        self.used = 0  #: frames read by windows and the mean

    # ------------------------------------------------------------------------------ audio in

    def push(self, block: np.ndarray) -> None:
        """Append a block (channels x n) and fold the frames that have left the next window into the mean."""
        block = np.asarray(block, dtype=np.float32)
        if block.ndim != 2 or block.shape[0] != self.channels:
            raise ValueError(f"expected a block of {self.channels} channels x samples, got shape {block.shape}")
        for first in range(0, block.shape[1], self.frame):  # long blocks in pieces: the mean keeps pace
            piece = block[:, first:first + self.frame]
            n = piece.shape[1]
            if self._filled + n > self._buffer.shape[1]:
                retained = min(self._filled, self.keep)
                self._buffer[:, :retained] = self._buffer[:, self._filled - retained:self._filled].copy()
                self._filled = retained
            self._buffer[:, self._filled:self._filled + n] = piece
            self._filled += n
            self.end += n
            if self.recipe.suppress_static:
                self._fold(self.end - self.window)

    def _samples(self, start: int, stop: int) -> np.ndarray:
        first = self.end - self._filled
        if start < first or stop > self.end:
            raise IndexError(f"samples {start}:{stop} are not buffered ({first}:{self.end})")
        return self._buffer[:, start - first:stop - first]

    # ------------------------------------------------------------------------------ frames

    def _cross(self, starts: list[int]) -> torch.Tensor | None:
        """Cross-spectra (pairs x frames x bins) of the frames starting at ``starts`` (from the store, or
        computed together); None when one of them holds non-finite samples."""
        missing = [s for s in dict.fromkeys(starts) if s not in self._store]
        computed = None
        if missing:
            if missing[-1] - missing[0] == (len(missing) - 1) * self.frame:  # back to back: a view, no copy
                frames = self._samples(missing[0], missing[-1] + self.frame).reshape(self.channels, len(missing), -1)
            else:
                frames = np.stack([self._samples(s, s + self.frame) for s in missing], axis=1)  # C x M x frame
            finite = np.isfinite(frames).all(axis=(0, 2))
            if not finite.all():
                frames = np.nan_to_num(frames)
            with torch.no_grad():
                computed = self.gcc.cross_spectra(torch.from_numpy(frames))  # pairs x M x bins
                if self.clocks is not None:
                    centres = (np.asarray(missing) + 0.5 * self.frame) / self.sample_rate
                    computed = self._corrected(computed, self.clocks.offsets_at(centres))
            for m, s in enumerate(missing):
                self._store[s] = computed[:, m] if finite[m] else None
            self.computed += len(missing)
        self.used += len(starts)
        if computed is not None and missing == starts and all(self._store[s] is not None for s in starts):
            return computed  # all new, in order: no second copy
        cross = [self._store[s] for s in starts]
        if any(c is None for c in cross):
            return None
        return torch.stack(cross, dim=1)  # type: ignore[arg-type]

    def _corrected(self, cross: torch.Tensor, offsets: np.ndarray) -> torch.Tensor:
        return correct_cross_spectra(cross, self.freqs, offsets, self.gcc.first, self.gcc.second)

    def set_clocks(self, clocks: NodeClocks) -> None:
        """Correct the cross-spectra to node 0's clock from now on (``clocks.offsets_at(t)``: each node's offset
        ``t`` seconds after the stream's first sample). Called again (a newer estimate), it replaces the earlier
        clocks: the long-term mean is moved by the difference of the two at the newest sample."""
        previous, self.clocks = self.clocks, clocks
        self._store.clear()
        if self.mean is not None:
            now = self.end / self.sample_rate
            change = clocks.offsets_at(now) - (previous.offsets_at(now) if previous is not None else 0.0)
            with torch.no_grad():
                self.mean = self._corrected(self.mean[:, None], change)[:, 0]

    def _fold(self, window_start: int) -> None:
        """Fold every whole grid frame that ends at or before ``window_start`` into the long-term mean."""
        starts = []
        while self.next_frame + self.frame <= window_start:
            starts.append(self.next_frame)
            self.next_frame += self.frame
        if not starts:
            return
        for start in starts:
            cross = self._cross([start])
            if cross is None:
                continue
            self.folded += 1
            weight = max(1.0 / self.folded, 1.0 - self.decay)
            self.mean = fold_mean(self.mean, cross[:, 0], weight)
        self._prune(min(window_start, self.end - self.window))

    def _prune(self, before: int) -> None:
        for key in [k for k in self._store if k < before - self.frame]:
            del self._store[key]

    # ------------------------------------------------------------------------------ features out

    def ready(self) -> bool:
        """Whether a whole window has arrived."""
        return self.end >= self.window

    def features(self) -> torch.Tensor:
        """The recipe's features (pairs x frames x lags, float32) of the window ending at the last sample.

        Raises:
            ValueError: fewer samples than one window so far, or a frame of the window holds non-finite samples.
        """
        if not self.ready():
            raise ValueError(f"a window needs {self.window} samples; {self.end} received")
        start = self.end - self.window
        cross = self._cross([start + j * self.frame for j in range(self.recipe.frames)])
        if cross is None:
            raise ValueError("the window holds NaN or infinite samples")
        with torch.no_grad():
            out = self.gcc.correlate(without_mean(cross, self.mean if self.recipe.suppress_static else None))
        self._prune(start)
        return out
