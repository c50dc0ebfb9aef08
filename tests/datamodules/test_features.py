"""Audio and image recipes: shapes, ranges, frequency placement, window timing, darkness."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torchaudio

from datamodules.features import (
    MEL_RECIPES,
    IncrementalMel,
    audio_window,
    image_features,
    image_recipe,
    mel_features,
    mel_recipe,
    published_dark,
    scale_image,
)
from datamodules.recording import ArrayAudio, RecordingError

FS = 48000


@pytest.mark.parametrize("name", sorted(MEL_RECIPES))
def test_every_recipe_has_its_shape_and_range(name):
    recipe = mel_recipe(name)
    x = np.random.default_rng(0).normal(size=(4, 2 * FS)).astype(np.float32)
    out = mel_features(x, FS, recipe)
    assert tuple(out.shape) == (4, *recipe.output_shape)
    assert out.dtype == torch.float32 and float(out.min()) >= 0.0 and float(out.max()) <= 1.0 + 1e-6
    expected = {"aaute": (64, 64), "aaute_joint": (64, 64), "avfdti": (64, 64), "avfdti_224": (224, 224),
                "avfdti_13": (13, 13)}[name]
    assert recipe.output_shape == expected


def _expected_row(recipe, frequency: float, sample_rate: float) -> float:
    rate = recipe.mel_sample_rate or sample_rate
    banks = torchaudio.functional.melscale_fbanks(recipe.n_fft // 2 + 1, recipe.f_min, recipe.f_max or rate / 2,
                                                  recipe.n_mels, int(rate), norm="slaney", mel_scale="slaney")
    bin_index = int(round(frequency / (rate / recipe.n_fft)))
    band = int(torch.argmax(banks[bin_index]))
    return (band + 0.5) * recipe.resize[0] / recipe.n_mels - 0.5


@pytest.mark.parametrize(("name", "frequency"), [("aaute", 600.0), ("aaute", 1000.0), ("avfdti", 3000.0)])
def test_pure_tone_peaks_in_its_mel_row(name, frequency):
    recipe = mel_recipe(name)
    t = np.arange(2 * FS) / FS
    tone = np.tile(np.sin(2 * np.pi * frequency * t), (4, 1)).astype(np.float32)
    out = mel_features(tone, FS, recipe)
    row = int(torch.argmax(out[0].mean(dim=1)))
    assert abs(row - _expected_row(recipe, frequency, FS)) <= 1.5


def test_student_recipe_sees_only_low_frequencies():
    recipe = mel_recipe("aaute")
    t = np.arange(2 * FS) / FS
    low = mel_features(np.tile(np.sin(2 * np.pi * 400 * t), (4, 1)).astype(np.float32), FS, recipe)
    high = np.sin(2 * np.pi * 400 * t) + np.sin(2 * np.pi * 5000 * t)
    with_high = mel_features(np.tile(high, (4, 1)).astype(np.float32), FS, recipe)
    # 5 kHz lies above the ~1.2 kHz crop: it only changes the min-max scale, computed before the crop
    correlation = np.corrcoef(low.flatten().numpy(), with_high.flatten().numpy())[0, 1]
    assert correlation > 0.999


def test_window_ends_at_the_label_time_and_faithful_order_is_newest_first():
    fs = 1000.0
    ramp = np.tile(np.arange(10000, dtype=np.float32), (4, 1))
    audio = ArrayAudio(ramp, fs, t0=50.0, mic_positions=np.zeros((4, 3)))
    recipe = mel_recipe("aaute")
    window = audio_window(audio, 55.0, recipe, 2.0)
    assert window.shape == (4, 2000) and window[0, -1] == 4999.0 and window[0, 0] == 3000.0
    faithful = audio_window(audio, 55.0, recipe, 2.0, faithful_order=True)
    starts = faithful[0, ::100]
    assert list(starts) == [4900.0, 4700.0, 4500.0, 4300.0, 4100.0]  # idx, idx-2, ..., idx-8
    with pytest.raises(RecordingError, match="outside the audio"):
        audio_window(audio, 50.5, recipe, 2.0)


@pytest.mark.parametrize("name", sorted(MEL_RECIPES))
def test_features_equal_torchaudios_mel_spectrogram(name):
    """The fast power path is torchaudio's MelSpectrogram, to float32 rounding."""
    recipe = mel_recipe(name)
    x = np.random.default_rng(3).normal(0, 0.1, (4, 2 * FS)).astype(np.float32)
    reference = torchaudio.transforms.MelSpectrogram(
        sample_rate=int(recipe.mel_sample_rate or FS), n_fft=recipe.n_fft, hop_length=recipe.hop, f_min=recipe.f_min,
        f_max=recipe.f_max, n_mels=recipe.n_mels, power=2.0, norm="slaney", mel_scale="slaney", pad_mode="constant")
    spec = reference(torch.from_numpy(x))
    dims = (-3, -2, -1) if recipe.joint_minmax else (-2, -1)
    lo, hi = spec.amin(dim=dims, keepdim=True), spec.amax(dim=dims, keepdim=True)
    expected = torch.nn.functional.interpolate(((spec - lo) / (hi - lo))[None], size=recipe.resize,
                                               mode="bilinear", antialias=True, align_corners=False)[0]
    if recipe.keep_rows is not None:
        expected = expected[:, :recipe.keep_rows]
    if recipe.final_resize is not None:
        expected = torch.nn.functional.interpolate(expected[None], size=recipe.final_resize, mode="bilinear",
                                                   antialias=True, align_corners=False)[0]
    assert torch.allclose(mel_features(x, FS, recipe), expected, atol=1e-5)


def test_joint_variant_keeps_the_level_differences_between_microphones():
    t = np.arange(2 * FS) / FS
    tone = np.sin(2 * np.pi * 400.0 * t).astype(np.float32)
    x = np.stack([tone, 0.5 * tone, tone, tone])  # microphone 1 is 6 dB quieter
    per_channel = mel_features(x, FS, mel_recipe("aaute"))
    joint = mel_features(x, FS, mel_recipe("aaute_joint"))
    assert torch.allclose(per_channel[0], per_channel[1], atol=1e-4)
    assert joint[1].amax() / joint[0].amax() == pytest.approx(0.25, rel=0.02)  # power ratio


def test_nan_audio_is_refused():
    x = np.zeros((4, FS), dtype=np.float32)
    x[2, 100] = np.nan
    with pytest.raises(RecordingError, match="NaN"):
        mel_features(x, FS, mel_recipe("aaute"))


def test_image_recipe_crops_the_left_camera_and_scales():
    frame = np.zeros((960, 2560, 3), dtype=np.uint8)
    frame[:, 1280:] = 255  # the right camera of a UG2 side-by-side frame
    out = image_features(frame, image_recipe("resnet256"))
    assert tuple(out.shape) == (3, 256, 256) and out.dtype == torch.uint8 and int(out.max()) == 0
    small = image_features(np.full((720, 1280, 3), 200, np.uint8), image_recipe("talknet112"))
    assert tuple(small.shape) == (3, 112, 112)
    scaled = scale_image(small)
    assert torch.allclose(scaled, torch.full_like(scaled, 200 / 127.5 - 1))
    dark = scale_image(published_dark(small))
    assert torch.allclose(dark, torch.full_like(dark, 3 / 127.5 - 1))


@pytest.mark.parametrize(("recipe", "rate"), [("aaute", 48000.0), ("aaute_joint", 46080.0), ("avfdti", 48000.0),
                                              ("avfdti_13", 48000.0)])
def test_incremental_mel_equals_the_offline_recipe(recipe, rate):
    rng = np.random.default_rng(1)
    n = int(3.3 * rate)
    audio = (rng.standard_normal((4, n)) * np.linspace(0.05, 1.0, n)).astype(np.float32)
    window, block = int(2 * rate), int(0.1 * rate)
    front = IncrementalMel(mel_recipe(recipe), rate, 4, window)
    checked, distinct, edges = 0, set(), 0
    for k in range(n // block):
        front.push(audio[:, k * block:(k + 1) * block])
        stop = (k + 1) * block
        if stop >= window:
            reference = mel_features(audio[:, stop - window:stop], rate, mel_recipe(recipe))
            assert torch.allclose(front.features(), reference, atol=1e-5, rtol=0)
            checked += 1
            distinct |= set((stop - window + front.offsets[front.inner]).tolist())
            edges += int((~front.inner).sum())
    assert checked == 14
    # each frame inside a window was computed once, whichever windows share it; only edge frames are per window
    assert front.computed == len(distinct) + edges
    assert front.used == 14 * front.frames
