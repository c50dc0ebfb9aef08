"""Mel-spectrogram recipes (A and B) of the audio models, and the offline mel front end.

Recipes follow the published preprocessing of each model family:

- ``aaute`` (recipe B, the AAUTE student and the original AV-PedAware): torchaudio mel spectrogram
  with n_fft 2048, hop 1024, 200 Slaney mels over 0..sr/2, power 2 (no log), per-channel
  min-max to [0, 1], bilinear resize to 224 x 64 (mel x time), keep the first 64 mel rows
  (about 0-1.2 kHz) -> C x 64 x 64. ``aaute_joint`` is the same with one min-max over all channels,
  which keeps the level differences between microphones (not in the paper; a measured variant).
- ``avfdti`` (recipe A, AV-FDTI and every comparison baseline): hop 512, 20 Slaney mels from 1 to
  8 kHz with the sample rate passed as 48 kHz, per-channel min-max, resize to 64 x 64;
  ``avfdti_224`` (VorasNet) and ``avfdti_13`` (ASDNet) resize that 64 x 64 map again.

The original loaders concatenate audio chunks newest first ([idx, idx-2, ..., idx-8] for B,
[idx, idx-1, ..., idx-9] for A); ``faithful_window_order`` reproduces that, while the default is
one continuous causal window ending at the label time.

The per-frame pieces (:func:`mel_frame_layout`, :func:`frame_power_mel`, :func:`mel_map`) serve the
streaming twin of :func:`mel_features`, :class:`datamodules.features.incremental.IncrementalMel`.
"""

from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass, replace
from functools import lru_cache

import numpy as np
import torch
import torchaudio
from torchvision.transforms.functional import InterpolationMode, resize

from datamodules.recording import AudioStream, RecordingError


@dataclass(frozen=True)
class MelRecipe:
    """A mel-spectrogram recipe (all sizes as mel x time)."""

    name: str
    n_fft: int
    hop: int
    n_mels: int
    f_min: float
    f_max: float | None  #: None: sample_rate / 2
    resize: tuple[int, int]
    keep_rows: int | None = None  #: keep the first rows after resizing (recipe B's crop)
    final_resize: tuple[int, int] | None = None  #: a second resize (VorasNet 224, ASDNet 13)
    mel_sample_rate: float | None = None  #: the rate passed to the mel transform (None: the audio's)
    chunk_seconds: float = 0.1  #: faithful order: one original audio file
    chunk_offsets: tuple[int, ...] = (0,)  #: faithful order: files used, newest first
    joint_minmax: bool = False  #: one min-max over all channels instead of one per channel

    @property
    def output_shape(self) -> tuple[int, int]:
        if self.final_resize is not None:
            return self.final_resize
        return (self.keep_rows or self.resize[0], self.resize[1])

    def key(self) -> str:
        """A hash of the settings (not the name): recipes that compute the same map share cache entries."""
        settings = {k: v for k, v in asdict(self).items() if k != "name"}
        return hashlib.sha256(repr(sorted(settings.items())).encode()).hexdigest()[:12]


_RECIPE_A = dict(n_fft=2048, hop=512, n_mels=20, f_min=1000.0, f_max=8000.0, resize=(64, 64),
                 mel_sample_rate=48000.0, chunk_offsets=tuple(-k for k in range(10)))
_RECIPE_B = dict(n_fft=2048, hop=1024, n_mels=200, f_min=0.0, f_max=None, resize=(224, 64), keep_rows=64,
                 chunk_offsets=(0, -2, -4, -6, -8))
MEL_RECIPES: dict[str, MelRecipe] = {
    r.name: r
    for r in (
        MelRecipe("aaute", **_RECIPE_B),
        MelRecipe("aaute_joint", joint_minmax=True, **_RECIPE_B),
        MelRecipe("avfdti", **_RECIPE_A),
        MelRecipe("avfdti_224", final_resize=(224, 224), **_RECIPE_A),
        MelRecipe("avfdti_13", final_resize=(13, 13), **_RECIPE_A),
    )
}


def mel_recipe(name: str) -> MelRecipe:
    try:
        return MEL_RECIPES[name]
    except KeyError:
        raise ValueError(f"unknown audio recipe {name!r}; known: {sorted(MEL_RECIPES)}") from None


def stored_recipe(recipe: MelRecipe) -> MelRecipe:
    """The recipe whose maps a feature cache stores: ``recipe`` without its second resize.

    The second resize (VorasNet's 224 x 224, ASDNet's 13 x 13) is cheap and applied on reading
    (:func:`final_resize`), so those recipes share AV-FDTI's 64 x 64 entries instead of storing a map
    12x its size.
    """
    return replace(recipe, final_resize=None)


def final_resize(stored_map: torch.Tensor, recipe: MelRecipe) -> torch.Tensor:
    """Apply ``recipe``'s second resize, if any, to maps of :func:`stored_recipe` (... x C x H x W)."""
    if recipe.final_resize is None:
        return stored_map
    with torch.no_grad():
        out = resize(stored_map, list(recipe.final_resize), interpolation=InterpolationMode.BILINEAR, antialias=True)
    return out.contiguous()


def audio_window(
    audio: AudioStream, t_end: float, recipe: MelRecipe, window_seconds: float, faithful_order: bool = False
) -> np.ndarray:
    """The raw samples a recipe looks at for a label at ``t_end`` (channels x samples).

    Default: the continuous, causal ``window_seconds`` ending at ``t_end``. With
    ``faithful_order``: the original code's files (``recipe.chunk_offsets`` x ``chunk_seconds``)
    concatenated newest first.
    """
    if not faithful_order:
        return audio.window(t_end, window_seconds)
    chunks = [audio.window(t_end + k * recipe.chunk_seconds, recipe.chunk_seconds) for k in recipe.chunk_offsets]
    return np.concatenate(chunks, axis=1)


@lru_cache(maxsize=16)
def _mel_transform(recipe: MelRecipe, sample_rate: float) -> torchaudio.transforms.MelSpectrogram:
    rate = recipe.mel_sample_rate or sample_rate
    return torchaudio.transforms.MelSpectrogram(
        sample_rate=int(round(rate)),
        n_fft=recipe.n_fft,
        hop_length=recipe.hop,
        f_min=recipe.f_min,
        f_max=recipe.f_max,
        n_mels=recipe.n_mels,
        power=2.0,
        norm="slaney",
        mel_scale="slaney",
        pad_mode="constant",
    )


def _power_mel(x: torch.Tensor, transform: torchaudio.transforms.MelSpectrogram) -> torch.Tensor:
    """``transform(x)`` computed from the transform's own window and filterbank, about 2x faster.

    torchaudio squares ``|X|`` through a complex ``abs`` (a square root, then a power); the power
    is ``re^2 + im^2`` directly here. The result equals ``transform(x)`` to float32 rounding.
    """
    stft = transform.spectrogram
    spec = torch.stft(x, stft.n_fft, stft.hop_length, stft.win_length, window=stft.window, center=stft.center,
                      pad_mode=stft.pad_mode, normalized=False, onesided=stft.onesided, return_complex=True)
    power = spec.real.square() + spec.imag.square()
    return torch.matmul(power.transpose(-1, -2), transform.mel_scale.fb).transpose(-1, -2)


def _minmax(spec: torch.Tensor, joint: bool = False) -> torch.Tensor:
    """Min-max to [0, 1] per channel, or over all channels with ``joint`` (a constant map becomes 0)."""
    dims = (-3, -2, -1) if joint else (-2, -1)
    lo = spec.amin(dim=dims, keepdim=True)
    hi = spec.amax(dim=dims, keepdim=True)
    return (spec - lo) / torch.clamp(hi - lo, min=torch.finfo(spec.dtype).tiny)


def mel_map(power_mel: torch.Tensor, recipe: MelRecipe) -> torch.Tensor:
    """A window's power mel spectrogram (C x n_mels x frames) -> the recipe's map (float32 C x H x W).

    The second half of :func:`mel_features`: min-max, resize, crop and the optional second resize.
    The streaming front end (:class:`~datamodules.features.incremental.IncrementalMel`) assembles the
    spectrogram from frames it computed once (:func:`frame_power_mel`) and calls this on it.
    """
    with torch.no_grad():
        spec = _minmax(power_mel, recipe.joint_minmax)
        out = resize(spec, list(recipe.resize), interpolation=InterpolationMode.BILINEAR, antialias=True)
        if recipe.keep_rows is not None:
            out = out[:, : recipe.keep_rows]
    return final_resize(out.contiguous(), recipe)


def mel_features(samples: np.ndarray, sample_rate: float, recipe: MelRecipe) -> torch.Tensor:
    """Apply ``recipe`` to raw audio (channels x samples) -> float32 C x H x W."""
    samples = np.ascontiguousarray(samples, dtype=np.float32)
    if not np.isfinite(samples).all():
        raise RecordingError("audio window holds NaN or infinite samples")
    with torch.no_grad():
        return mel_map(_power_mel(torch.from_numpy(samples), _mel_transform(recipe, float(sample_rate))), recipe)


def mel_frame_layout(recipe: MelRecipe, sample_rate: float, window_samples: int) -> tuple[int, int, int]:
    """(frames, n_fft, hop) of the recipe's STFT over a window of ``window_samples`` (centred frames).

    Frame ``j`` of a window starting at sample ``s`` covers samples ``s + j * hop - n_fft // 2`` to
    ``s + j * hop + n_fft // 2`` (zeros outside the window), as torch.stft with ``center=True`` places it.
    """
    stft = _mel_transform(recipe, float(sample_rate)).spectrogram
    if not stft.center or stft.win_length != stft.n_fft or stft.pad_mode != "constant":
        raise ValueError(f"recipe {recipe.name!r}: frames are laid out for centred, zero-padded STFTs whose window "
                         f"spans n_fft")
    return 1 + window_samples // stft.hop_length, stft.n_fft, stft.hop_length


@lru_cache(maxsize=16)
def _interleaved_filterbank(recipe: MelRecipe, sample_rate: float):
    """The recipe's mel filterbank as a sparse n_mels x (2 x bins) matrix acting on squared (re, im) pairs."""
    import scipy.sparse

    bank = _mel_transform(recipe, sample_rate).mel_scale.fb.numpy()  # bins x n_mels
    return scipy.sparse.csr_matrix(np.repeat(bank, 2, axis=0).T)


def frame_power_mel(frames: torch.Tensor, recipe: MelRecipe, sample_rate: float) -> torch.Tensor:
    """Power mel of raw STFT frames (... x F x n_fft samples, not yet windowed) -> ... x n_mels x F.

    The same window, FFT size, power and filterbank as :func:`mel_features` (the recipe's torchaudio
    transform), applied to frames one at a time. The filterbank is applied as a sparse matrix (each FFT
    bin feeds at most two mel bands) to the squared real and imaginary parts side by side, which sums
    ``re^2 + im^2`` inside the product: the same sums as the dense product, in another order.
    """
    stft = _mel_transform(recipe, float(sample_rate)).spectrogram
    with torch.no_grad():
        spectrum = torch.fft.rfft(frames * stft.window, n=stft.n_fft)
        squares = torch.view_as_real(spectrum).square_().reshape(-1, 2 * spectrum.shape[-1])
        mel = _interleaved_filterbank(recipe, float(sample_rate)) @ squares.numpy().T  # n_mels x (... F)
    mel = torch.from_numpy(np.ascontiguousarray(mel, dtype=np.float32))
    return mel.reshape(mel.shape[0], *frames.shape[:-1]).movedim(0, -2)

