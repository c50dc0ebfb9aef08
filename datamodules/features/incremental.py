"""The streaming twin of the mel front end: mel maps of consecutive windows of one stream, each STFT frame once.

:class:`IncrementalMel` keeps the last window of samples and a store of power-mel frames keyed
by their first sample, so every STFT frame of the stream is computed once, whichever windows share it.
Each window's spectrogram is assembled from the store (plus its two zero-padded edge frames, which belong
to that window alone) and finished by :func:`datamodules.features.mel_map`, the offline recipe's own
normalisation and resizing, so the map equals :func:`datamodules.features.mel_features` on the same
samples (to float rounding, tested to 1e-5). How much is shared depends on the grid: frames of a window
starting at sample ``s`` start at ``s + j * hop - n_fft / 2``, so windows 0.1 s apart share frames only
when the hop divides the block. At 48 kHz with hop 1024 (the student's recipe) a 4800-sample block moves
the grid by 704 samples: a window shares frames only with the window 1.6 s (16 blocks, 75 hops) before
it, and each update computes 77 of its 94 frames. Where the hop divides the block (hop 1024 or 512 at
51.2 kHz) an update computes ``block / hop`` interior frames and its two edge frames.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from datamodules.errors import ConfigError
from datamodules.features.mel import MelRecipe, frame_power_mel, mel_frame_layout, mel_map


class IncrementalMel:
    """Mel maps of consecutive windows of one stream, each STFT frame computed once (see the module docstring).

    Args:
        recipe: a mel recipe of :mod:`datamodules.features`.
        sample_rate: Hz.
        channels: microphones.
        window_samples: samples per window.
    """

    def __init__(self, recipe: MelRecipe, sample_rate: float, channels: int, window_samples: int):
        self.recipe, self.sample_rate, self.channels = recipe, float(sample_rate), int(channels)
        self.window = int(window_samples)
        self.frames, self.n_fft, self.hop = mel_frame_layout(recipe, sample_rate, self.window)
        self.half = self.n_fft // 2
        if self.window < self.n_fft:
            raise ConfigError(f"recipe {recipe.name!r}: a {self.window}-sample window is shorter than one "
                              f"{self.n_fft}-sample frame")
        offsets = np.arange(self.frames) * self.hop - self.half  #: first sample of each frame, window-relative
        self.inner = (offsets >= 0) & (offsets + self.n_fft <= self.window)
        self.offsets = offsets
        self._buffer = np.zeros((self.channels, 2 * (self.window + self.n_fft)), dtype=np.float32)
        self._filled = 0  #: valid samples in the buffer
        self.end = 0  #: samples received so far (absolute index of the next one)
        #: first sample of a frame -> (C x n_mels x frames power mel computed with it, its column there)
        self._store: dict[int, tuple[torch.Tensor, int]] = {}
        self.computed = 0  #: frames computed (for the report)
        self.used = 0  #: frames used by the windows made

    def push(self, block: np.ndarray) -> None:
        """Append a block (channels x n) to the stream."""
        n = block.shape[1]
        keep = self.window + self.n_fft
        if self._filled + n > self._buffer.shape[1]:
            retained = min(self._filled, keep)
            self._buffer[:, :retained] = self._buffer[:, self._filled - retained:self._filled]
            self._filled = retained
            if n > self._buffer.shape[1] - retained:
                self._buffer = np.concatenate([self._buffer[:, :retained], np.zeros((self.channels, n + keep),
                                                                                   np.float32)], axis=1)
        self._buffer[:, self._filled:self._filled + n] = block
        self._filled += n
        self.end += n

    def _samples(self, start: int, stop: int) -> np.ndarray:
        """Absolute samples ``start:stop`` from the buffer."""
        first = self.end - self._filled
        if start < first or stop > self.end:
            raise IndexError(f"samples {start}:{stop} are not buffered ({first}:{self.end})")
        return self._buffer[:, start - first:stop - first]

    def features(self, stop: int | None = None) -> torch.Tensor:
        """The recipe's map (C x H x W) of the window ending just before absolute sample ``stop`` (default: now)."""
        stop = self.end if stop is None else int(stop)
        start = stop - self.window
        starts = start + self.offsets
        missing = [j for j in np.flatnonzero(self.inner) if int(starts[j]) not in self._store]
        for run in _runs(missing):
            first, last = int(starts[run[0]]), int(starts[run[-1]])
            segment = torch.from_numpy(self._samples(first, last + self.n_fft))
            frames = segment.unfold(-1, self.n_fft, self.hop)  # C x len(run) x n_fft
            block = frame_power_mel(frames, self.recipe, self.sample_rate)  # C x n_mels x len(run)
            for column, j in enumerate(run):
                self._store[int(starts[j])] = (block, column)
            self.computed += len(run)
        edges = np.flatnonzero(~self.inner)
        window = self._samples(start, stop)
        padded = np.zeros((self.channels, len(edges), self.n_fft), dtype=np.float32)
        for i, j in enumerate(edges):
            lo, hi = int(self.offsets[j]), int(self.offsets[j]) + self.n_fft
            padded[:, i, max(0, -lo):self.n_fft - max(0, hi - self.window)] = window[:, max(lo, 0):min(hi, self.window)]
        edge_block = frame_power_mel(torch.from_numpy(padded), self.recipe, self.sample_rate)
        edge_column = {int(j): i for i, j in enumerate(edges)}
        self.computed += len(edges)
        # consecutive frames that were computed together are copied as one slice
        pieces: list[list[Any]] = []  # [block, first column, last column]
        for j in range(self.frames):
            block, column = (edge_block, edge_column[j]) if j in edge_column else self._store[int(starts[j])]
            if pieces and pieces[-1][0] is block and pieces[-1][2] == column - 1:
                pieces[-1][2] = column
            else:
                pieces.append([block, column, column])
        spectrogram = torch.cat([block[:, :, a:b + 1] for block, a, b in pieces], dim=-1)
        self.used += self.frames
        for key in [k for k in self._store if k < start + self.hop - self.half]:
            del self._store[key]  # later windows start later: frames before this one's second are done
        return mel_map(spectrogram, self.recipe)


def _runs(indices: Sequence[int]) -> list[list[int]]:
    """Consecutive runs of sorted integers: [1, 2, 3, 7, 8] -> [[1, 2, 3], [7, 8]]."""
    runs: list[list[int]] = []
    for index in indices:
        if runs and index == runs[-1][-1] + 1:
            runs[-1].append(int(index))
        else:
            runs.append([int(index)])
    return runs
