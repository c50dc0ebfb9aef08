"""Phase recipes: GCC-PHAT of every microphone pair on short frames before the label time.

The features of the phase-feature nets (SRP-PHAT, the phase student): :class:`PhaseRecipe` says
what is computed, :class:`GccPhat` computes it at one sample rate, :func:`phase_features` applies it
to one window and :class:`PhaseWindows` to the windows of a stream (with the causal static-source
suppression some recipes ask for).
"""

from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass
from functools import lru_cache
from typing import Protocol

import numpy as np
import torch

from datamodules.recording import AudioStream, RecordingError

#: m/s: the speed of sound in air at 30 C (MMAUD V1, Singapore), the simulator's
#: ``datamodules.simulate.propagation.speed_of_sound(30.0)`` = 349.02 m/s, rounded as the configs state it;
#: the phase nets steer with it and the clock calibration fits with it
SPEED_OF_SOUND = 349.0


class NodeClocks(Protocol):
    """Estimated clock offsets of the nodes (:class:`datamodules.features.clock_calibration.ClockCalibration`)."""

    offsets_s: np.ndarray
    drifts_ppm: np.ndarray

    def offsets_at(self, times: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class PhaseRecipe:
    """GCC-PHAT of every microphone pair on the last ``frames`` short frames before the label time.

    Each frame (``frame_seconds``, Hann window, zero-padded to twice its length so the correlation
    does not wrap) gives one cross-spectrum per pair ``(i, j)``, i < j; PHAT keeps only its phase
    inside ``[f_min, f_max]``, and the inverse FFT is taken at ``lag_rate`` (band-limited
    interpolation of the correlation), over the lags ``-max_delay .. +max_delay`` seconds. The
    value at lag ``tau`` is 1 for a perfectly coherent source whose sound reaches microphone ``i``
    ``tau`` seconds after microphone ``j``, and near 0 for incoherent noise, at any sample rate.

    With ``suppress_static``, a causal long-term mean of each pair's cross-spectrum (an exponential
    average with time constant ``static_seconds`` over the frames before the window, never the
    window itself or the future) is subtracted before PHAT: a static coherent source such as a
    rooftop HVAC unit fades out, and so would a drone that hovers for longer than the time constant.
    """

    name: str
    frame_seconds: float = 4096 / 48000  #: 85.3 ms: delays drift ~25 samples/s, so frames stay short
    frames: int = 6  #: the last 0.51 s of the window
    max_delay: float = 0.0145  #: 5.06 m of path at 349 m/s: the 4.36 m diagonal of distributed4 + margin
    lag_rate: float = 24000.0  #: lag resolution 41.7 us (14.5 mm of path)
    f_min: float = 100.0  #: below: wind and HVAC rumble, few cycles per frame
    f_max: float = 8000.0  #: above: little drone energy left at range (rotor harmonics and broadband)
    suppress_static: bool = False
    static_seconds: float = 30.0

    def num_lags(self) -> int:
        return 2 * int(round(self.max_delay * self.lag_rate)) + 1

    def lags(self) -> np.ndarray:
        """The lag of each output column (s)."""
        half = int(round(self.max_delay * self.lag_rate))
        return np.arange(-half, half + 1) / self.lag_rate

    def output_shape(self, channels: int) -> tuple[int, int, int]:
        """pairs x frames x lags for ``channels`` microphones."""
        return (len(mic_pairs(channels)), self.frames, self.num_lags())

    @property
    def span_seconds(self) -> float:
        """Audio seconds one window reads (the frames, back to back, ending at the label time)."""
        return self.frames * self.frame_seconds

    def key(self) -> str:
        return hashlib.sha256(repr(sorted(asdict(self).items())).encode()).hexdigest()[:12]


PHASE_RECIPES: dict[str, PhaseRecipe] = {
    r.name: r for r in (
        PhaseRecipe("gcc_phat"),
        PhaseRecipe("gcc_phat_static", suppress_static=True),
        # the last 1.02 s / 1.96 s of the 2 s window: more frames integrate a weak source
        PhaseRecipe("gcc_phat_1s", frames=12),
        PhaseRecipe("gcc_phat_1s_static", frames=12, suppress_static=True),
        PhaseRecipe("gcc_phat_2s", frames=23),
        PhaseRecipe("gcc_phat_2s_static", frames=23, suppress_static=True),
    )
}


def phase_recipe(name: str) -> PhaseRecipe:
    try:
        return PHASE_RECIPES[name]
    except KeyError:
        raise ValueError(f"unknown phase recipe {name!r}; known: {sorted(PHASE_RECIPES)}") from None


@lru_cache(maxsize=8)
def mic_pairs(channels: int) -> tuple[tuple[int, int], ...]:
    """Every microphone pair (i, j), i < j, in the order of the phase features' first axis."""
    if channels < 2:
        raise RecordingError(f"phase features need at least 2 microphones, got {channels}")
    return tuple((i, j) for i in range(channels) for j in range(i + 1, channels))


def parabolic_offset(values: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Sub-step offset (-0.5 .. 0.5) of the peak at ``index`` along the last axis of ``values``, by the parabola
    through it and its neighbours (0 at the ends, or where the three do not bend down)."""
    idx = np.clip(index, 1, values.shape[-1] - 2)[..., None]
    y0, y1, y2 = (np.take_along_axis(values, idx + d, -1)[..., 0] for d in (-1, 0, 1))
    denominator = y0 - 2 * y1 + y2
    with np.errstate(invalid="ignore", divide="ignore"):
        shift = np.where(np.isfinite(denominator) & (denominator < 0), 0.5 * (y0 - y2) / denominator, 0.0)
    shift = np.clip(np.nan_to_num(shift), -0.5, 0.5)
    return np.where(idx[..., 0] == index, shift, 0.0)


def pair_indices(channels: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The first and second microphone of every pair of :func:`mic_pairs`, as index tensors."""
    pairs = mic_pairs(channels)
    return torch.tensor([i for i, _ in pairs]), torch.tensor([j for _, j in pairs])


#: values up to which :class:`GccPhat` keeps its FFTs' zero-padded inputs for the next call (at most 32 MB)
SPECTRUM_REUSE = 1 << 22


def _zeros_kept(kept: dict[tuple[int, ...], torch.Tensor], shape: tuple[int, ...], dtype: torch.dtype
                ) -> torch.Tensor:
    """The zero tensor of ``shape`` in ``kept`` (callers overwrite only its parts that they need nonzero), else
    a new one, kept there when it holds at most :data:`SPECTRUM_REUSE` values (a stream has two or three
    shapes: its windows' and its single frames')."""
    if shape in kept:
        return kept[shape]
    tensor = torch.zeros(shape, dtype=dtype)
    if tensor.numel() <= SPECTRUM_REUSE:
        if len(kept) >= 4:
            kept.clear()
        kept[shape] = tensor
    return tensor


class GccPhat:
    """The phase recipe at one sample rate: frames -> cross-spectra -> PHAT -> correlation at the lags."""

    def __init__(self, recipe: PhaseRecipe, sample_rate: float, channels: int):
        self.recipe = recipe
        self.frame = int(round(recipe.frame_seconds * sample_rate))
        self.n_fft = 2 * self.frame
        self.n_out = int(round(self.n_fft * recipe.lag_rate / sample_rate))
        half = int(round(recipe.max_delay * recipe.lag_rate))
        if half >= self.n_out // 2:
            raise ValueError(f"phase recipe {recipe.name!r}: max_delay {recipe.max_delay} s does not fit a "
                             f"{recipe.frame_seconds} s frame")
        self.half = half  #: lags each side of zero: the columns are -half .. +half
        freqs = np.fft.rfftfreq(self.n_fft, 1.0 / sample_rate)
        keep = (freqs >= recipe.f_min) & (freqs <= min(recipe.f_max, recipe.lag_rate / 2))
        self.bins = torch.from_numpy(np.flatnonzero(keep))
        #: the band as a slice (it is one run of bins): slicing is several times cheaper than index lists
        self.band = slice(int(self.bins[0]), int(self.bins[-1]) + 1) if len(self.bins) else slice(0, 0)
        # a coherent pure delay sums to 2 K / n_out at its lag: scale it to 1
        self.scale = self.n_out / (2.0 * max(int(keep.sum()), 1))
        self.first, self.second = pair_indices(channels)
        self.window = torch.hann_window(self.frame, periodic=False, dtype=torch.float32)
        #: the last zero-padded frames handed to the FFT and full spectra handed to the inverse FFT (both zero
        #: where no call writes: the padding, and outside the band), kept for the next call of the same shape
        self._pad: dict[tuple[int, ...], torch.Tensor] = {}
        self._full: dict[tuple[int, ...], torch.Tensor] = {}

    def _spectrum(self, shape: tuple[int, ...]) -> torch.Tensor:
        """A complex64 tensor of ``shape``, zero outside the band (which its users overwrite)."""
        return _zeros_kept(self._full, shape, torch.complex64)

    def _padded(self, frames: tuple[int, ...]) -> torch.Tensor:
        """A float32 tensor of frames x ``n_fft`` samples whose second half (the zero padding) is zero."""
        return _zeros_kept(self._pad, (*frames, self.n_fft), torch.float32)

    def cross_spectra(self, frames: torch.Tensor) -> torch.Tensor:
        """C x F x frame samples -> pairs x F x band bins (complex64).

        Single precision throughout, as the samples come (float32). A static mean subtracted from them
        is kept in double precision (it averages thousands of frames) and subtracted in single: the
        features' error from this stays near 1e-6, a thousandth of the float16 feature cache's resolution."""
        padded = self._padded(frames.shape[:-1])
        torch.mul(frames, self.window, out=padded[..., :self.frame])  # its second half stays zero
        spectra = torch.fft.rfft(padded)[..., self.band]
        return spectra.index_select(0, self.first) * spectra.index_select(0, self.second).conj()

    def correlate(self, cross: torch.Tensor) -> torch.Tensor:
        """PHAT-weighted cross-spectra (pairs x F x band bins) -> pairs x F x lags (float32; the unit-magnitude
        PHAT spectra are transformed back in single precision)."""
        single = np.ascontiguousarray(cross.to(torch.complex64).numpy())
        magnitude = np.abs(single)  # numpy's complex magnitude: several times faster than torch's
        np.reciprocal(np.maximum(magnitude, np.float32(1e-30), out=magnitude), out=magnitude)
        full = self._spectrum((*cross.shape[:-1], self.n_out // 2 + 1))
        np.multiply(single, magnitude, out=full.numpy()[..., self.band])
        correlation = torch.fft.irfft(full, n=self.n_out)
        # the lags -half .. -1 sit at the end of the transform, 0 .. half at its start
        lags = torch.cat([correlation[..., self.n_out - self.half:], correlation[..., :self.half + 1]], dim=-1)
        return lags * self.scale


def correct_cross_spectra(cross: torch.Tensor, freqs: torch.Tensor, offsets: np.ndarray, first: torch.Tensor,
                          second: torch.Tensor) -> torch.Tensor:
    """Pair cross-spectra (pairs x frames x bins) of audio whose node ``n`` runs ``offsets[..., n]`` seconds
    early, as if every node shared node 0's clock: times ``exp(-i w (o_i - o_j))`` (exact for a constant offset).

    ``offsets`` is C (all frames) or frames x C (per frame: a drifting clock).
    """
    offsets = torch.as_tensor(np.asarray(offsets, dtype=np.float64))
    difference = offsets[..., first] - offsets[..., second]  # P, or F x P
    difference = difference[:, None] if difference.dim() == 1 else difference.T  # P x 1, or P x F
    ramp = torch.exp(-2j * torch.pi * difference[..., None] * freqs.to(torch.float64))
    return cross * ramp.to(cross.dtype)


def split_frames(samples: np.ndarray, frame: int, frames: int) -> torch.Tensor:
    """The last ``frames`` x ``frame`` samples of C x N audio as C x frames x frame."""
    needed = frame * frames
    if samples.shape[1] < needed:
        raise RecordingError(f"phase features need {needed} samples per window, got {samples.shape[1]}")
    tail = np.ascontiguousarray(samples[:, samples.shape[1] - needed:], dtype=np.float32)
    if not np.isfinite(tail).all():
        raise RecordingError("audio window holds NaN or infinite samples")
    return torch.from_numpy(tail).reshape(samples.shape[0], frames, frame)


def phase_features(samples: np.ndarray, sample_rate: float, recipe: PhaseRecipe) -> torch.Tensor:
    """Apply ``recipe`` (without static suppression) to raw audio (C x N, ending at the label time).

    Returns pairs x frames x lags (float32); see :class:`PhaseRecipe`.
    """
    gcc = _gcc_phat(recipe, float(sample_rate), samples.shape[0])
    with torch.no_grad():
        return gcc.correlate(gcc.cross_spectra(split_frames(samples, gcc.frame, recipe.frames)))


def fold_mean(mean: torch.Tensor | None, cross: torch.Tensor, weight: float) -> torch.Tensor:
    """The static long-term mean (pairs x bins, complex128: it averages thousands of frames) after folding in
    one frame's cross-spectra (pairs x bins) with ``weight``; the frame itself when there is no mean yet."""
    cross = cross.to(torch.complex128)
    return cross if mean is None else (1 - weight) * mean + weight * cross


def without_mean(cross: torch.Tensor, mean: torch.Tensor | None) -> torch.Tensor:
    """Cross-spectra (pairs x F x bins, complex64) less the static mean (pairs x bins), in single precision."""
    return cross if mean is None else cross - mean.to(torch.complex64)[:, None, :]


@lru_cache(maxsize=8)
def _gcc_phat(recipe: PhaseRecipe, sample_rate: float, channels: int) -> GccPhat:
    return GccPhat(recipe, sample_rate, channels)


class PhaseWindows:
    """Phase features of the windows ending at increasing ``times`` of one audio stream.

    With ``clocks`` (the nodes' estimated clock offsets, :mod:`datamodules.features.clock_calibration`)
    every frame's cross-spectra are corrected to node 0's clock before anything else.

    Without static suppression each window is independent. With it, a causal exponential average
    of every pair's cross-spectrum is carried along the stream on consecutive frames from the start
    of the audio up to the start of each window, so windows must be asked for in time order (the
    feature cache builds them so); asking out of order raises.
    """

    def __init__(self, audio: AudioStream, recipe: PhaseRecipe, times: np.ndarray, source: str = "audio",
                 clocks: NodeClocks | None = None):
        self.audio, self.recipe, self.times, self.source = audio, recipe, np.asarray(times, dtype=np.float64), source
        self.gcc = _gcc_phat(recipe, float(audio.sample_rate), audio.num_channels)
        self.clocks = clocks
        self.freqs = self.gcc.bins.to(torch.float64) * float(audio.sample_rate) / self.gcc.n_fft
        self.mean: torch.Tensor | None = None  #: long-term mean cross-spectra (pairs x band bins)
        self.next_frame = 0  #: first sample of the next frame to fold into the mean
        self.folded = 0  #: frames folded into the mean so far
        self.last = -1
        frame_period = self.gcc.frame / audio.sample_rate
        self.decay = float(np.exp(-frame_period / recipe.static_seconds))

    def __call__(self, i: int) -> np.ndarray:
        t_end = float(self.times[i])
        try:
            samples = self.audio.window(t_end, self.recipe.span_seconds)
            frames = split_frames(samples, self.gcc.frame, self.recipe.frames)
        except RecordingError as error:
            raise RecordingError(f"{self.source}: window ending at {t_end:.3f} s: {error}") from None
        with torch.no_grad():
            first = self.audio.sample_index(t_end) - frames.shape[1] * self.gcc.frame
            cross = self._corrected(self.gcc.cross_spectra(frames), first)
            if self.recipe.suppress_static:
                if i <= self.last:
                    raise ValueError("static suppression needs the windows in time order")
                self._fold_past(self.audio.sample_index(t_end) - self.gcc.frame * self.recipe.frames)
                cross = without_mean(cross, self.mean)
            self.last = i
            return self.gcc.correlate(cross).numpy()

    def _fold_past(self, window_start: int) -> None:
        """Fold every whole frame that ends before sample ``window_start`` into the long-term mean.

        The first frames are averaged with equal weights, then exponentially (time constant
        ``static_seconds``), so the mean is unbiased from the start.
        """
        frame = self.gcc.frame
        while self.next_frame + frame <= window_start:
            try:
                samples = self.audio.read(self.next_frame, self.next_frame + frame)
            except RecordingError as error:
                raise RecordingError(f"{self.source}: {error}") from None
            if not np.isfinite(samples).all():
                start = self.audio.t0 + self.next_frame / self.audio.sample_rate
                raise RecordingError(f"{self.source}: audio at {start:.3f} s holds NaN or infinite samples")
            cross = self.gcc.cross_spectra(torch.from_numpy(samples)[:, None, :])
            cross = self._corrected(cross, self.next_frame)[:, 0]
            self.folded += 1
            weight = max(1.0 / self.folded, 1.0 - self.decay)
            self.mean = fold_mean(self.mean, cross, weight)
            self.next_frame += frame

    def _corrected(self, cross: torch.Tensor, first_sample: int) -> torch.Tensor:
        """Cross-spectra (pairs x frames x bins) of consecutive frames from ``first_sample`` on node 0's clock."""
        if self.clocks is None:
            return cross
        frame = self.gcc.frame
        centres = (first_sample + frame * (np.arange(cross.shape[1]) + 0.5)) / self.audio.sample_rate
        offsets = self.clocks.offsets_at(centres) if np.any(self.clocks.drifts_ppm) else self.clocks.offsets_s
        return correct_cross_spectra(cross, self.freqs, offsets, self.gcc.first, self.gcc.second)
