"""Stationary Gaussian noise with a chosen power spectrum and inter-channel coherence.

Frames of random spectra are shaped, mixed between channels with a Cholesky factor of the
coherence matrix, inverse-FFT'd and overlap-added with square-root Hann windows (50 % overlap,
so the squared windows sum to one and the output is stationary). This is the usual way to make
diffuse, spatially coherent noise fields for microphone arrays (sinc coherence between mics).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def _mixing_matrices(coherence: np.ndarray) -> np.ndarray:
    """Per-frequency factors L with L L^H = coherence (F x C x C), robust to rank deficiency."""
    values, vectors = np.linalg.eigh(coherence)
    return vectors * np.sqrt(np.clip(values, 0.0, None))[:, None, :]


def coloured_noise(
    num_samples: int,
    sample_rate: float,
    psd: Callable[[np.ndarray], np.ndarray],
    rng: np.random.Generator,
    channels: int = 1,
    coherence: Callable[[np.ndarray], np.ndarray] | None = None,
    frame_length: int = 4096,
    block_frames: int = 256,
    dtype: type = np.float64,
) -> np.ndarray:
    """Noise with one-sided power spectral density ``psd(f)`` (units^2/Hz) per channel.

    Args:
        num_samples: output length.
        sample_rate: Hz.
        psd: vectorised one-sided PSD; its integral is the output variance.
        rng: random source (deterministic output for a given state).
        channels: number of channels.
        coherence: ``coherence(f) -> F x C x C`` complex coherence matrices (identity if None).
        frame_length: FFT length (even); the spectral resolution is ``sample_rate / frame_length``.
        block_frames: frames synthesised per batch (bounds memory).
        dtype: output dtype (float32 halves the memory of long signals).

    Returns:
        array of ``dtype``, channels x num_samples.
    """
    n = frame_length
    hop = n // 2
    freqs = np.fft.rfftfreq(n, 1.0 / sample_rate)
    gains = np.sqrt(np.clip(psd(freqs), 0.0, None) * sample_rate * n / 2.0)
    gains[0] = gains[-1] = 0.0
    mixing = _mixing_matrices(coherence(freqs)) if coherence is not None else None
    window = np.sqrt(0.5 - 0.5 * np.cos(2.0 * np.pi * np.arange(n) / n))  # periodic sqrt-Hann

    total_frames = int(np.ceil(num_samples / hop)) + 1
    out = np.empty((channels, total_frames * hop + hop), dtype=dtype)
    carry = np.zeros((channels, hop))
    pos = 0
    for start in range(0, total_frames, block_frames):
        count = min(block_frames, total_frames - start)
        z = (rng.standard_normal((count, freqs.size, channels)) + 1j * rng.standard_normal(
            (count, freqs.size, channels))) / np.sqrt(2.0)
        if mixing is not None:
            z = np.einsum("fij,tfj->tfi", mixing, z)
        frames = np.fft.irfft(z * gains[None, :, None], n=n, axis=1) * window[None, :, None]
        frames = frames.transpose(2, 0, 1)  # channels x count x n
        first, second = frames[:, :, :hop], frames[:, :, hop:]
        block = first.copy()
        block[:, 0] += carry
        block[:, 1:] += second[:, :-1]
        carry = second[:, -1]
        out[:, pos:pos + count * hop] = block.reshape(channels, -1)
        pos += count * hop
    # the first half-frame has only one window: skip it so the output is stationary
    return out[:, hop:hop + num_samples]


def ou_process(
    num_samples: int, dt: float, sigma: float, time_constant: float, rng: np.random.Generator, shape: tuple = ()
) -> np.ndarray:
    """Ornstein-Uhlenbeck process (stationary, std ``sigma``, correlation time ``time_constant``).

    Returns an array of ``shape + (num_samples,)`` starting in the stationary distribution.
    """
    from scipy.signal import lfilter

    decay = np.exp(-dt / time_constant)
    kick = sigma * np.sqrt(1.0 - decay**2)
    white = rng.standard_normal(shape + (num_samples,))
    white[..., 0] *= sigma / max(kick, 1e-300)
    return lfilter([kick], [1.0, -decay], white, axis=-1)
