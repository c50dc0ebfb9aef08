"""The streaming phase front end equals the offline phase recipe over the same past."""

from __future__ import annotations

import numpy as np
import pytest

from datamodules.features import IncrementalPhase, PhaseRecipe, PhaseWindows, mic_pairs
from datamodules.recording import ArrayAudio

RATE = 48000.0
#: a short recipe whose static mean turns exponential within the test's audio (after 4 frames)
SHORT = PhaseRecipe("short", frames=5, static_seconds=4 * 4096 / RATE)


def _audio(channels: int, seconds: float, seed: int = 0) -> np.ndarray:
    """A delayed common source (a static one, like an HVAC unit) plus independent noise per channel."""
    rng = np.random.default_rng(seed)
    n = int(seconds * RATE)
    common = rng.standard_normal(n + 100)
    out = [common[5 * c:5 * c + n] + 0.5 * rng.standard_normal(n) for c in range(channels)]
    return np.stack(out).astype(np.float32)


def _stream(front: IncrementalPhase, audio: np.ndarray, sizes: list[int]) -> list[tuple[int, np.ndarray]]:
    """Push ``audio`` in blocks of the cycled ``sizes``; the features after every block with a whole window."""
    out, start, k = [], 0, 0
    while start < audio.shape[1]:
        stop = min(start + sizes[k % len(sizes)], audio.shape[1])
        front.push(audio[:, start:stop])
        if front.ready():
            out.append((stop, front.features().numpy()))
        start, k = stop, k + 1
    return out


@pytest.mark.parametrize("channels", [2, 3, 4])
@pytest.mark.parametrize("static", [False, True])
def test_streamed_windows_equal_the_offline_recipe(channels, static):
    recipe = PhaseRecipe("short", frames=5, suppress_static=static, static_seconds=SHORT.static_seconds)
    audio = _audio(channels, 1.6, seed=channels)
    front = IncrementalPhase(recipe, RATE, channels)
    streamed = _stream(front, audio, [4800, 1234, 7000, 333])  # blocks of uneven size
    assert len(streamed) > 5
    stream = ArrayAudio(audio, RATE, 10.0, np.zeros((channels, 3)))
    times = np.array([10.0 + stop / RATE for stop, _ in streamed])
    offline = PhaseWindows(stream, recipe, times)
    for i, (_, features) in enumerate(streamed):
        expected = offline(i)
        assert features.shape == (len(mic_pairs(channels)), recipe.frames, recipe.num_lags())
        np.testing.assert_allclose(features, expected, atol=1e-5, rtol=0)
    if static:
        assert front.folded > 4  # the mean went past its equal-weight start
        plain = IncrementalPhase(PhaseRecipe("short", frames=5), RATE, channels)
        _stream(plain, audio, [4800])
        assert not np.allclose(plain.features().numpy(), streamed[-1][1], atol=1e-3)  # suppression did something


def test_frames_are_computed_once_when_the_hop_is_whole_frames():
    front = IncrementalPhase(SHORT, RATE, 3)
    frame = front.frame
    audio = _audio(3, 1.0)[:, :11 * frame]
    _stream(front, audio, [frame])
    updates = audio.shape[1] // frame - SHORT.frames + 1
    assert front.computed == audio.shape[1] // frame  # every frame once
    assert front.used == updates * SHORT.frames


def test_a_block_of_nan_spoils_only_the_windows_that_contain_it_and_stays_out_of_the_mean():
    recipe = PhaseRecipe("short", frames=5, suppress_static=True, static_seconds=SHORT.static_seconds)
    audio = _audio(2, 2.0)
    front = IncrementalPhase(recipe, RATE, 2)
    bad = slice(24000, 28800)
    audio[:, bad] = np.nan
    start, spoiled, clean_after = 0, 0, 0
    while start + 4800 <= audio.shape[1]:
        front.push(audio[:, start:start + 4800])
        start += 4800
        if not front.ready():
            continue
        contains = start - front.window < bad.stop and start > bad.start
        if contains:
            with pytest.raises(ValueError, match="NaN"):
                front.features()
            spoiled += 1
        else:
            assert np.isfinite(front.features().numpy()).all()
            clean_after += start > bad.stop
    assert spoiled > 0 and clean_after > 0
    assert front.mean is not None and bool(np.isfinite(front.mean.numpy()).all())


def test_one_long_block_folds_the_whole_past():
    recipe = PhaseRecipe("short", frames=5, suppress_static=True, static_seconds=SHORT.static_seconds)
    audio = _audio(2, 1.2)
    whole, pieces = IncrementalPhase(recipe, RATE, 2), IncrementalPhase(recipe, RATE, 2)
    whole.push(audio)
    _stream(pieces, audio, [4800])
    np.testing.assert_allclose(whole.features().numpy(), pieces.features().numpy(), atol=1e-6)


def test_a_newer_clock_estimate_replaces_the_earlier_one():
    """Correcting by one estimate and then by another leaves the stream as the second alone would."""
    from datamodules.features.clock_calibration import ClockCalibration

    def clocks(offsets: list[float], drifts: list[float]) -> ClockCalibration:
        return ClockCalibration(np.array(offsets), np.zeros(3), np.array(drifts), np.zeros(3), frames=1,
                                residual_rms_s=0.0)

    recipe = PhaseRecipe("short", frames=5, suppress_static=True, static_seconds=SHORT.static_seconds)
    audio = _audio(3, 1.6, seed=5)
    twice, once = IncrementalPhase(recipe, RATE, 3), IncrementalPhase(recipe, RATE, 3)
    for front in (twice, once):
        _stream(front, audio[:, :48000], [4800])
    twice.set_clocks(clocks([0.0, 3e-4, -2e-4], [0.0, 50.0, 0.0]))
    twice.set_clocks(clocks([0.0, 1e-4, 2e-4], [0.0, 0.0, 20.0]))
    once.set_clocks(clocks([0.0, 1e-4, 2e-4], [0.0, 0.0, 20.0]))
    np.testing.assert_allclose(twice.mean.numpy(), once.mean.numpy(), atol=1e-6)
    for front in (twice, once):
        _stream(front, audio[:, 48000:], [4800])
    np.testing.assert_allclose(twice.features().numpy(), once.features().numpy(), atol=1e-5)
