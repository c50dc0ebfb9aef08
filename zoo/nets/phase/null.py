"""The null statistic's input: GCC-PHAT of independent white noise per microphone.

Nothing in such noise is coherent between microphones (like channels shifted apart by seconds), so
the phase nets' responses to it set what "no source" looks like: ``srp_phat``'s detection threshold and
``phase_student``'s per-cube null mean. Both draw it here, seeded, so it is the same on every run.
"""

from __future__ import annotations

import numpy as np
import torch

from datamodules.features import GccPhat, PhaseRecipe, split_frames

#: Hz: the rate the white noise is made at by default (the simulator's and MMAUD's audio rate)
NULL_SAMPLE_RATE = 48000.0
#: windows transformed at once (each frame's transform is independent, so the result does not depend on it)
CHUNK_WINDOWS = 16


def white_noise_correlations(recipe: PhaseRecipe, channels: int, windows: int, frames: int,
                             sample_rate: float = NULL_SAMPLE_RATE, seed: int = 0) -> torch.Tensor:
    """The phase recipe's correlations of ``windows`` windows of ``frames`` frames of independent standard
    normal noise on each of ``channels`` microphones, pairs x windows x frames x lags (float32).

    Args:
        recipe: the phase recipe (frame length, band, lags).
        channels: microphones.
        windows, frames: how many windows of how many consecutive frames.
        sample_rate: Hz, the noise's sample rate (sets the frame length in samples and the band's bins).
        seed: the noise generator's seed (``numpy.random.default_rng``).
    """
    gcc = GccPhat(recipe, sample_rate, channels)
    rng = np.random.default_rng(seed)  # channel by channel: the same draws as one (channels x samples) array
    noise = np.stack([rng.standard_normal(windows * frames * gcc.frame).astype(np.float32) for _ in range(channels)])
    framed = split_frames(noise, gcc.frame, windows * frames).reshape(channels, windows, frames, gcc.frame)
    chunks = []
    with torch.no_grad():  # a few windows at a time: the zero-padded FFTs of all of them would take gigabytes
        for start in range(0, windows, CHUNK_WINDOWS):
            chunk = framed[:, start:start + CHUNK_WINDOWS].reshape(channels, -1, gcc.frame)
            chunks.append(gcc.correlate(gcc.cross_spectra(chunk)))  # pairs x (chunk windows * frames) x lags
    correlation = torch.cat(chunks, dim=1)
    return correlation.reshape(correlation.shape[0], windows, frames, -1)
