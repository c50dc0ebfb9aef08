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


def mel_map(power_mel: torch.Tensor, recipe: MelRecipe) -> torch.Tensor:
    """A window's power mel spectrogram (C x n_mels x frames) -> the recipe's map (float32 C x H x W).

    The second half of :func:`mel_features`: min-max, resize, crop and the optional second resize.
    The streaming front end (:mod:`zoo.tracking`) assembles the spectrogram from frames it computed
    once (:func:`frame_power_mel`) and calls this on it.
    """
    with torch.no_grad():
        spec = _minmax(power_mel, recipe.joint_minmax)
        out = resize(spec, list(recipe.resize), interpolation=InterpolationMode.BILINEAR, antialias=True)
        if recipe.keep_rows is not None:
            out = out[:, : recipe.keep_rows]
        if recipe.final_resize is not None:
            out = resize(out, list(recipe.final_resize), interpolation=InterpolationMode.BILINEAR, antialias=True)
    return out.contiguous()


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


# --------------------------------------------------------------------------------------------- phase


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


def pair_indices(channels: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The first and second microphone of every pair of :func:`mic_pairs`, as index tensors."""
    pairs = mic_pairs(channels)
    return torch.tensor([i for i, _ in pairs]), torch.tensor([j for _, j in pairs])


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
        self.lag_index = torch.arange(-half, half + 1) % self.n_out
        freqs = np.fft.rfftfreq(self.n_fft, 1.0 / sample_rate)
        keep = (freqs >= recipe.f_min) & (freqs <= min(recipe.f_max, recipe.lag_rate / 2))
        self.bins = torch.from_numpy(np.flatnonzero(keep))
        # a coherent pure delay sums to 2 K / n_out at its lag: scale it to 1
        self.scale = self.n_out / (2.0 * max(int(keep.sum()), 1))
        self.first, self.second = pair_indices(channels)
        self.window = torch.hann_window(self.frame, periodic=False, dtype=torch.float64)

    def cross_spectra(self, frames: torch.Tensor) -> torch.Tensor:
        """C x F x frame samples -> pairs x F x band bins (complex128)."""
        spectra = torch.fft.rfft(frames.to(torch.float64) * self.window, n=self.n_fft)[..., self.bins]
        return spectra[self.first] * spectra[self.second].conj()

    def correlate(self, cross: torch.Tensor) -> torch.Tensor:
        """PHAT-weighted cross-spectra (pairs x F x band bins) -> pairs x F x lags (float32)."""
        phat = cross / cross.abs().clamp_min(1e-30)
        full = torch.zeros((*cross.shape[:-1], self.n_out // 2 + 1), dtype=phat.dtype)
        full[..., self.bins] = phat
        correlation = torch.fft.irfft(full, n=self.n_out) * self.scale
        return correlation[..., self.lag_index].to(torch.float32)


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


@lru_cache(maxsize=8)
def _gcc_phat(recipe: PhaseRecipe, sample_rate: float, channels: int) -> GccPhat:
    return GccPhat(recipe, sample_rate, channels)


class PhaseWindows:
    """Phase features of the windows ending at increasing ``times`` of one audio stream.

    Without static suppression each window is independent. With it, a causal exponential average
    of every pair's cross-spectrum is carried along the stream on consecutive frames from the start
    of the audio up to the start of each window, so windows must be asked for in time order (the
    feature cache builds them so); asking out of order raises.
    """

    def __init__(self, audio: AudioStream, recipe: PhaseRecipe, times: np.ndarray, source: str = "audio"):
        self.audio, self.recipe, self.times, self.source = audio, recipe, np.asarray(times, dtype=np.float64), source
        self.gcc = _gcc_phat(recipe, float(audio.sample_rate), audio.num_channels)
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
            cross = self.gcc.cross_spectra(frames)
            if self.recipe.suppress_static:
                if i <= self.last:
                    raise ValueError("static suppression needs the windows in time order")
                self._fold_past(self.audio.sample_index(t_end) - self.gcc.frame * self.recipe.frames)
                if self.mean is not None:
                    cross = cross - self.mean[:, None, :]
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
            cross = self.gcc.cross_spectra(torch.from_numpy(samples)[:, None, :])[:, 0]
            self.folded += 1
            weight = max(1.0 / self.folded, 1.0 - self.decay)
            self.mean = cross if self.mean is None else (1 - weight) * self.mean + weight * cross
            self.next_frame += frame
