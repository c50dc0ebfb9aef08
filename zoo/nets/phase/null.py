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
    noise = np.random.default_rng(seed).standard_normal((channels, windows * frames * gcc.frame))
    framed = split_frames(noise.astype(np.float32), gcc.frame, windows * frames)
    with torch.no_grad():
        correlation = gcc.correlate(gcc.cross_spectra(framed))  # pairs x (windows * frames) x lags
    return correlation.reshape(correlation.shape[0], windows, frames, -1)
