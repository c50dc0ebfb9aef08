"""Input recipes of the zoo's models: mel spectrograms (recipes A and B) and camera images.

Recipes follow the published preprocessing of each model family:

- ``aaute`` (recipe B, the AAUTE student and the original AV-PedAware): torchaudio mel spectrogram
  with n_fft 2048, hop 1024, 200 Slaney mels over 0..sr/2, power 2 (no log), per-channel
  min-max to [0, 1], bilinear resize to 224 x 64 (mel x time), keep the first 64 mel rows
  (about 0-1.2 kHz) -> C x 64 x 64. ``aaute_joint`` is the same with one min-max over all channels,
  which keeps the level differences between microphones (not in the paper; a measured variant).
- ``avfdti`` (recipe A, AV-FDTI and every comparison baseline): hop 512, 20 Slaney mels from 1 to
  8 kHz with the sample rate passed as 48 kHz, per-channel min-max, resize to 64 x 64;
  ``avfdti_224`` (VorasNet) and ``avfdti_13`` (ASDNet) resize that 64 x 64 map again.
- images: the left 1280 columns, resized with antialiasing to 256 x 256 (``resnet256``; 112 x 112,
  ``talknet112``, for ASDNet), kept as uint8 and scaled to [-1, 1] (value / 127.5 - 1, no ImageNet
  statistics) at batch time.
- reduced-budget images (not the papers' recipes): ``resnet128`` and ``resnet64`` (the same crop at
  128 x 128 and 64 x 64) and ``talknet56`` (56 x 56) cut the image models' compute about 4x and 16x
  so they can train on a CPU demo budget. A net reads them only when asked
  (``TrajectoryNet(input_recipes={"image": "resnet64"})``, which keeps its parameters unchanged);
  results so obtained are reduced-budget results and are reported as such.
- darkness: ``published`` replaces the image by img * 0 + 3 (a near-black constant, -0.976 after
  scaling) and sets the visibility label to 0 (AV-FDTI ``dark_aug``); ``physical`` renders the
  frame in low light (:func:`datamodules.simulate.camera.darken_image`).

The original loaders concatenate audio chunks newest first ([idx, idx-2, ..., idx-8] for B,
[idx, idx-1, ..., idx-9] for A); ``faithful_window_order`` reproduces that, while the default is
one continuous causal window ending at the label time.
"""

from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass
from functools import lru_cache

import numpy as np
import torch
import torchaudio
from torchvision.transforms.functional import InterpolationMode, resize

from datamodules.recording import AudioStream, RecordingError

DARK_MODES = ("published", "physical")
PUBLISHED_DARK_VALUE = 3  #: cv2.addWeighted(img, 0, black, 1, 3) in the AV-FDTI loaders


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
        return hashlib.sha256(repr(sorted(asdict(self).items())).encode()).hexdigest()[:12]


@dataclass(frozen=True)
class ImageRecipe:
    """An image recipe: crop the left ``crop_width`` columns, resize to ``size`` (H, W)."""

    name: str
    size: tuple[int, int]
    crop_width: int = 1280

    def key(self) -> str:
        return hashlib.sha256(repr(sorted(asdict(self).items())).encode()).hexdigest()[:12]


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
IMAGE_RECIPES: dict[str, ImageRecipe] = {
    r.name: r
    for r in (
        ImageRecipe("resnet256", (256, 256)),
        ImageRecipe("talknet112", (112, 112)),
        # reduced-budget variants (not the papers'): the same crop at a smaller size
        ImageRecipe("resnet128", (128, 128)),
        ImageRecipe("resnet64", (64, 64)),
        ImageRecipe("talknet56", (56, 56)),
    )
}


def mel_recipe(name: str) -> MelRecipe:
    try:
        return MEL_RECIPES[name]
    except KeyError:
        raise ValueError(f"unknown audio recipe {name!r}; known: {sorted(MEL_RECIPES)}") from None


def image_recipe(name: str) -> ImageRecipe:
    try:
        return IMAGE_RECIPES[name]
    except KeyError:
        raise ValueError(f"unknown image recipe {name!r}; known: {sorted(IMAGE_RECIPES)}") from None


# --------------------------------------------------------------------------------------------- audio


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


def mel_features(samples: np.ndarray, sample_rate: float, recipe: MelRecipe) -> torch.Tensor:
    """Apply ``recipe`` to raw audio (channels x samples) -> float32 C x H x W."""
    samples = np.ascontiguousarray(samples, dtype=np.float32)
    if not np.isfinite(samples).all():
        raise RecordingError("audio window holds NaN or infinite samples")
    x = torch.from_numpy(samples)
    with torch.no_grad():
        spec = _minmax(_power_mel(x, _mel_transform(recipe, float(sample_rate))), recipe.joint_minmax)
        out = resize(spec, list(recipe.resize), interpolation=InterpolationMode.BILINEAR, antialias=True)
        if recipe.keep_rows is not None:
            out = out[:, : recipe.keep_rows]
        if recipe.final_resize is not None:
            out = resize(out, list(recipe.final_resize), interpolation=InterpolationMode.BILINEAR, antialias=True)
    return out.contiguous()


# --------------------------------------------------------------------------------------------- image


def image_features(image: np.ndarray, recipe: ImageRecipe) -> torch.Tensor:
    """Crop and resize an H x W x 3 uint8 frame -> uint8 3 x h x w (scaled at batch time)."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise RecordingError(f"expected an H x W x 3 uint8 image, got {image.shape} {image.dtype}")
    crop = torch.from_numpy(np.array(image[:, : recipe.crop_width])).permute(2, 0, 1)
    return resize(crop, list(recipe.size), interpolation=InterpolationMode.BILINEAR, antialias=True).contiguous()


def scale_image(image: torch.Tensor) -> torch.Tensor:
    """uint8 -> float32 in [-1, 1] (value / 127.5 - 1, as the AV-FDTI loaders do)."""
    return image.to(torch.float32) / 127.5 - 1.0


def published_dark(image: torch.Tensor) -> torch.Tensor:
    """The published darkness protocol: every pixel becomes the constant 3 (uint8)."""
    return torch.full_like(image, PUBLISHED_DARK_VALUE)
