"""Clocks of separate microphone nodes: offsets, drifts and receive-time stamping, drawn per recording.

A real rig's nodes each sample on their own clock. Node ``n``'s sample ``k`` is taken at true time
``k / fs * (1 + drift_n) + offset_n``: a constant offset (milliseconds on real rigs when nodes are
aligned by stamps; 1 ms is 0.35 m of path difference) and a drift (crystal tolerance: tens of
ppm). When each node's messages are placed in time by receive times (MMAUD V1: no header stamps),
aligning the nodes leaves a further error per node: the median of its messages' receive latencies
(:func:`stamp_residuals`, latencies drawn exponential with mean ``stamp_jitter_ms``), which adds to
its offset.

The simulator applies the clocks physically: the drone's sound is rendered at each node's true
sample times (retarded-time propagation), and everything else the microphone hears (ambient noise,
the HVAC unit) is resampled at those times (:func:`resample_at_clock`, windowed-sinc interpolation).
The true values go into the recording's metadata as ``clocks_truth``, for evaluation only: no
reader or model may use them.

Here every channel is its own node (the default geometry has four single-microphone nodes).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

SINC_HALF_TAPS = 16  #: half-length of the interpolation kernel (Kaiser-windowed sinc, 32 taps)
SINC_BETA = 8.0  #: Kaiser window shape: > 80 dB stop band
BLOCK = 1 << 16  #: samples interpolated at a time (bounds the memory of the kernel matrix)


@dataclass
class ClockConfig:
    """Per-node clocks; fixed values and random ranges add up. Defaults: one shared, exact clock.

    A fixed offset or drift given as one value ``x`` means node ``n`` gets ``n * x`` (consecutive
    nodes differ by ``x``); a list gives one value per node.
    """

    offset_ms: list[float] | float | None = None  #: fixed per-node offsets (ms)
    offset_range_ms: float = 0.0  #: plus uniform(-r, r) per node, drawn per recording
    drift_ppm: list[float] | float | None = None  #: fixed per-node drifts (ppm)
    drift_range_ppm: float = 0.0  #: plus uniform(-r, r) per node, drawn per recording
    stamp_jitter_ms: float = 0.0  #: mean receive latency of a message (exponential); 0: stamps exact
    message_seconds: float = 0.1  #: audio per message (MMAUD V1: 0.1 s)

    def active(self) -> bool:
        """Whether any node's clock differs from the shared, exact one."""
        fixed = [v for v in (self.offset_ms, self.drift_ppm) if v is not None]
        return bool(any(np.any(np.asarray(v, dtype=np.float64)) for v in fixed)
                    or self.offset_range_ms or self.drift_range_ppm or self.stamp_jitter_ms)

    def check(self) -> None:
        """Refuse negative ranges and jitter (ValueError naming the setting)."""
        for name in ("offset_range_ms", "drift_range_ppm", "stamp_jitter_ms"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"clocks: {name} must be a finite number >= 0, got {value!r}")


@dataclass
class ClockRealisation:
    """The clocks drawn for one recording (per node)."""

    offsets_s: np.ndarray  #: clock offsets
    drifts_ppm: np.ndarray
    stamp_residuals_s: np.ndarray  #: alignment error the receive-time stamps leave

    @property
    def effective_offsets_s(self) -> np.ndarray:
        """What the nodes' audio is off by once aligned by stamps: clock offset plus stamp residual."""
        return self.offsets_s + self.stamp_residuals_s

    def meta(self) -> dict[str, Any]:
        """``clocks_truth`` for the recording's metadata (evaluation only)."""
        return {"offsets_s": self.offsets_s.tolist(), "drifts_ppm": self.drifts_ppm.tolist(),
                "stamp_residuals_s": self.stamp_residuals_s.tolist(),
                "effective_offsets_s": self.effective_offsets_s.tolist()}


def _per_node(value: list[float] | float | None, nodes: int) -> np.ndarray:
    if value is None:
        return np.zeros(nodes)
    values = np.atleast_1d(np.asarray(value, dtype=np.float64))
    if values.size == 1:
        return values[0] * np.arange(nodes)
    if values.size != nodes:
        raise ValueError(f"clocks: {values.size} per-node values for {nodes} nodes")
    return values


def stamp_residuals(nodes: int, duration: float, jitter_s: float, message_s: float,
                    rng: np.random.Generator) -> np.ndarray:
    """Per node, the median receive latency of its messages: the offset a stamp-based alignment leaves."""
    if jitter_s <= 0:
        return np.zeros(nodes)
    messages = max(1, int(duration / message_s))
    return np.median(rng.exponential(jitter_s, (nodes, messages)), axis=1)


def draw_clocks(config: ClockConfig, nodes: int, duration: float, rng: np.random.Generator) -> ClockRealisation:
    """Each node's offset, drift and stamp residual for one recording of ``duration`` seconds."""
    config.check()
    offsets = _per_node(config.offset_ms, nodes) * 1e-3 + rng.uniform(-1, 1, nodes) * config.offset_range_ms * 1e-3
    drifts = _per_node(config.drift_ppm, nodes) + rng.uniform(-1, 1, nodes) * config.drift_range_ppm
    residuals = stamp_residuals(nodes, duration, config.stamp_jitter_ms * 1e-3, config.message_seconds, rng)
    return ClockRealisation(offsets, drifts, residuals)


def resample_at_clock(x: np.ndarray, fs: float, offsets_s: np.ndarray, drifts_ppm: np.ndarray) -> np.ndarray:
    """Channels of ``x`` (sampled on the true clock) read at each node's sample times ``k / fs * (1 + d) + o``.

    Windowed-sinc interpolation; beyond the signal's ends it is mirrored (the few ms an offset
    reaches past them).
    """
    channels, count = x.shape
    pad = int(np.ceil(np.max(np.abs(offsets_s)) * fs + np.max(np.abs(drifts_ppm)) * 1e-6 * count)) + SINC_HALF_TAPS + 2
    padded = np.pad(x.astype(np.float64), ((0, 0), (pad, pad)), mode="reflect")
    taps = np.arange(-SINC_HALF_TAPS + 1, SINC_HALF_TAPS + 1)
    out = np.empty_like(x, dtype=np.float64)
    for c in range(channels):
        if offsets_s[c] == 0 and drifts_ppm[c] == 0:  # a node on the true clock is left exactly as it is
            out[c] = x[c]
            continue
        for start in range(0, count, BLOCK):
            k = np.arange(start, min(start + BLOCK, count))
            position = k * (1.0 + drifts_ppm[c] * 1e-6) + offsets_s[c] * fs + pad
            base = np.floor(position).astype(np.int64)
            frac = position - base
            distance = taps[None, :] - frac[:, None]
            ratio = np.clip(distance / SINC_HALF_TAPS, -1.0, 1.0)
            kernel = np.sinc(distance) * np.i0(SINC_BETA * np.sqrt(1.0 - ratio ** 2)) / np.i0(SINC_BETA)
            out[c, start:start + k.size] = np.einsum("nk,nk->n", padded[c][base[:, None] + taps[None, :]], kernel)
    return out.astype(x.dtype)
