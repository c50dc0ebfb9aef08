"""The phase recipe and the SRP-PHAT localiser on synthetic free-field sources."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from datamodules.features import PhaseWindows, mic_pairs, phase_features, phase_recipe
from datamodules.recording import ArrayAudio, RecordingError
from datamodules.simulate.microphones import distributed4
from zoo.nets.phase.gate import WINDOW_STATES
from zoo.nets.phase.steering import gather, pooled
from zoo.registry import get_model

RATE = 48000.0
SPEED = 349.0
RECIPE = phase_recipe("gcc_phat")


def _render(source: np.ndarray, mics: np.ndarray, seconds: float, snr_db: float = 30.0, seed: int = 0) -> np.ndarray:
    """White noise from ``source`` reaching each microphone after its own delay (fractional, by FFT), 1/r."""
    rng = np.random.default_rng(seed)
    n = int(round(seconds * RATE))
    pad = 8000
    signal = rng.standard_normal(n + 2 * pad)
    spectrum = np.fft.rfft(signal)
    freqs = np.fft.rfftfreq(signal.size)
    out = []
    for mic in mics:
        distance = np.linalg.norm(source - mic)
        delayed = np.fft.irfft(spectrum * np.exp(-2j * np.pi * freqs * distance / SPEED * RATE), n=signal.size)
        out.append(delayed[pad:pad + n] / distance)
    audio = np.stack(out)
    return audio + rng.standard_normal(audio.shape) * audio.std() * 10 ** (-snr_db / 20)


def _locate(net, audio: np.ndarray) -> np.ndarray:
    features = phase_features(audio, RATE, RECIPE)[None]
    with torch.no_grad():
        return net({"audio_phase": features})["position"][0].numpy()


@pytest.fixture(scope="module")
def net():
    torch.set_num_threads(1)
    return get_model("srp_phat", null_windows=60)


def test_phase_recipe_peaks_at_the_geometric_delay():
    mics = np.array([[0.0, 0.0, 1.0], [3.0, 0.0, 1.0]])
    source = np.array([-4.0, 6.0, 3.0])
    audio = _render(source, mics, RECIPE.span_seconds + 0.01)
    features = phase_features(audio, RATE, RECIPE)
    assert tuple(features.shape) == RECIPE.output_shape(2) == (1, RECIPE.frames, RECIPE.num_lags())
    expected = (np.linalg.norm(source - mics[0]) - np.linalg.norm(source - mics[1])) / SPEED
    peak = RECIPE.lags()[int(features[0].mean(dim=0).argmax())]
    assert abs(peak - expected) <= 0.6 / RECIPE.lag_rate  # within the lag grid's rounding
    assert float(features.max()) > 0.7  # a coherent source scores near 1


def test_every_pair_once_and_two_microphones_at_least():
    assert mic_pairs(4) == ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
    with pytest.raises(RecordingError, match="at least 2 microphones"):
        mic_pairs(1)


def test_nan_samples_name_the_recording_and_time():
    samples = np.random.default_rng(0).standard_normal((4, int(3 * RATE))).astype(np.float32)
    samples[2, int(2.5 * RATE)] = np.nan
    audio = ArrayAudio(samples, RATE, 100.0, distributed4())
    windows = PhaseWindows(audio, RECIPE, np.array([101.0, 102.8]), source="flight.mcap")
    windows(0)
    with pytest.raises(RecordingError, match=r"flight.mcap: window ending at 102.800 s: .*NaN"):
        windows(1)


def test_static_suppression_uses_only_the_past_and_removes_a_static_source():
    """A source that never moves fades out under suppression; later audio never changes earlier windows."""
    mics = distributed4()
    audio = _render(np.array([6.0, -4.0, 1.0]), mics, 12.0, snr_db=10.0).astype(np.float32)
    times = np.arange(2.0, 12.0, 1.0)
    recipe = phase_recipe("gcc_phat_static")
    full = PhaseWindows(ArrayAudio(audio, RATE, 0.0, mics), recipe, times)
    suppressed = [full(i) for i in range(times.size)]
    plain = [phase_features(audio[:, : int(t * RATE)], RATE, RECIPE).numpy() for t in times]
    assert suppressed[-1].max() < 0.5 * plain[-1].max()
    changed = audio.copy()
    changed[:, int(7.0 * RATE):] = 0.0  # the future of the first windows
    early = PhaseWindows(ArrayAudio(changed, RATE, 0.0, mics), recipe, times)
    for i in range(4):  # windows ending at 2..5 s read nothing after 5 s
        np.testing.assert_array_equal(early(i), suppressed[i])
    with pytest.raises(ValueError, match="time order"):
        early(0)


def test_srp_phat_localises_a_free_field_source(net):
    mics = distributed4()
    source = np.array([3.0, 5.0, 3.0])
    audio = _render(source, mics, RECIPE.span_seconds + 0.01)
    assert np.linalg.norm(_locate(net, audio) - source) < 0.3


def test_srp_phat_breaks_with_wrong_microphone_positions_or_a_delayed_channel(net):
    mics = distributed4()
    source = np.array([3.0, 5.0, 3.0])
    audio = _render(source, mics, RECIPE.span_seconds + 0.01)
    swapped = audio[[1, 0, 2, 3]]  # the recording's channels no longer match their positions
    assert np.linalg.norm(_locate(net, swapped) - source) > 1.0
    late = audio.copy()
    late[2] = np.roll(late[2], 12)  # one channel 12 samples (8.7 cm of path) late
    assert np.linalg.norm(_locate(net, late) - source) > 1.0


def test_srp_phat_never_detects_in_a_window_whose_node_clocks_are_uncorrected(net):
    source = np.array([3.0, 5.0, 3.0])
    features = phase_features(_render(source, distributed4(), RECIPE.span_seconds + 0.01), RATE, RECIPE)
    with torch.no_grad():
        out = net({"audio_phase": torch.stack([features, features]),
                   "uncorrected_clocks": torch.tensor([False, True])})
    assert out["detected"].tolist() == [True, False]
    assert [WINDOW_STATES[i] for i in out["state"]] == ["detected", "uncorrected"]
    assert float(out["detection_score"][1]) == pytest.approx(float(out["detection_score"][0]))  # the peak is kept
    np.testing.assert_allclose(out["position"][1].numpy(), net.region.mean(dim=1).numpy(), atol=1e-5)


def test_srp_phat_has_no_parameters_and_gates_noise(net):
    assert list(net.parameters()) == [] and net.category == "non-learned"
    noise = np.random.default_rng(3).standard_normal((4, int(RECIPE.span_seconds * RATE) + 10))
    with torch.no_grad():
        out = net({"audio_phase": phase_features(noise, RATE, RECIPE)[None]})
    assert not bool(out["detected"][0]) and float(out["detection_score"][0]) < 1.0
    np.testing.assert_allclose(out["position"][0].numpy(), net.region.mean(dim=1).numpy(), atol=1e-5)


def test_srp_phat_holds_then_falls_back_to_the_sequence_mean(net):
    mics = distributed4()
    rng = np.random.default_rng(5)
    seen = [np.array([3.0, 5.0, 3.0]), np.array([5.0, 7.0, 2.0])]
    windows = [_render(s, mics, RECIPE.span_seconds + 0.01, seed=i) for i, s in enumerate(seen)]
    windows += [rng.standard_normal(windows[0].shape)] * 2  # nothing coherent afterwards
    features = torch.stack([phase_features(w, RATE, RECIPE) for w in windows])
    times = torch.tensor([10.0, 10.1, 11.0, 30.0], dtype=torch.float64)
    with torch.no_grad():
        out = net({"audio_phase": features, "time": times, "sequence": torch.zeros(4, dtype=torch.long)})
    position = out["position"].numpy()
    assert out["detected"].tolist() == [True, True, False, False]
    assert [WINDOW_STATES[i] for i in out["state"]] == ["detected", "detected", "held", "fallback"]
    np.testing.assert_allclose(position[2], position[1])  # held within hold_seconds
    np.testing.assert_allclose(position[3], position[:2].mean(axis=0), atol=1e-5)  # then the mean of detections


def test_srp_phat_search_groups_give_each_frame_its_own_group_candidates():
    """Frames of a window that hear one source, then another: with a group per half every frame fits
    the source of its own half."""
    net = get_model("srp_phat", null_windows=60, search_groups=2, frame_candidates=1, ground_height=None)
    mics = distributed4()
    first, second = np.array([3.0, 8.0, 4.0]), np.array([-2.0, 9.0, 6.0])
    features = [phase_features(_render(s, mics, RECIPE.span_seconds + 0.01, seed=i), RATE, RECIPE)
                for i, s in enumerate((first, second))]
    half = RECIPE.frames // 2
    window = torch.cat([features[0][:, :half], features[1][:, half:]], dim=1)  # pairs x frames x lags
    with torch.no_grad():
        points, _ = net.search.peaks(window.permute(1, 0, 2)[None].float(), torch.as_tensor(mics))
    assert np.linalg.norm(points[0, :half].numpy() - first, axis=1).max() < 0.5
    assert np.linalg.norm(points[0, half:].numpy() - second, axis=1).max() < 0.5


def test_srp_phat_counts_a_detection_only_when_the_previous_one_confirms_it():
    net = get_model("srp_phat", null_windows=60, fallback="centre", confirm_seconds=2.0, confirm_distance=5.0)
    mics = distributed4()
    near, far = np.array([3.0, 5.0, 3.0]), np.array([-1.0, 20.0, 12.0])
    windows = [_render(s, mics, RECIPE.span_seconds + 0.01, seed=i) for i, s in enumerate((near, near, far))]
    features = torch.stack([phase_features(w, RATE, RECIPE) for w in windows])
    times = torch.tensor([10.0, 10.5, 11.0], dtype=torch.float64)
    with torch.no_grad():
        out = net({"audio_phase": features, "time": times, "sequence": torch.zeros(3, dtype=torch.long)})
    position = out["position"].numpy()
    assert out["detected"].tolist() == [False, True, False]  # the first is alone, the third 16 m from the second
    np.testing.assert_allclose(position[0], net.region.mean(dim=1).numpy(), atol=1e-5)
    assert np.linalg.norm(position[1] - near) < 0.5
    np.testing.assert_allclose(position[2], position[1])  # the unconfirmed far detection is not taken: held


def test_a_region_far_from_the_microphones_is_warned_about(caplog):
    net = get_model("srp_phat", region_min=(100.0, 100.0, 0.5), region_max=(120.0, 130.0, 25.0), null_windows=10)
    noise = np.random.default_rng(3).standard_normal((4, int(RECIPE.span_seconds * RATE) + 10))
    with caplog.at_level(logging.WARNING):
        net({"audio_phase": phase_features(noise, RATE, RECIPE)[None]})
    assert "search region" in caplog.text and "microphones" in caplog.text


def test_srp_phat_steers_the_ground_image_of_a_source_over_a_hard_ground(net):
    """Direct sound plus its mirror image in z = 0 (reflection factor 0.95): the image terms confirm the
    direct peak, so the source is found; without a ground plane in the steering the pairs' extra peaks
    pull the estimate along the range."""
    mics = distributed4()
    source = np.array([2.0, 18.0, 10.0])
    image = source * np.array([1.0, 1.0, -1.0])
    seconds = RECIPE.span_seconds + 0.01
    audio = _render(source, mics, seconds, snr_db=40.0) + 0.95 * _render(image, mics, seconds, snr_db=80.0)
    assert np.linalg.norm(_locate(net, audio) - source) < 1.5
    # the free-field search alone locks onto a cross term (the delay fit of the direct peaks can rescue it)
    free_field = get_model("srp_phat", null_windows=60, ground_height=None, fit_delays=False)
    assert np.linalg.norm(_locate(free_field, audio) - source) > 2.5


def test_srp_phat_skips_the_inside_of_the_array_and_can_fall_back_to_the_region_centre():
    net = get_model("srp_phat", null_windows=60, hold_seconds=0.5, fallback="centre")
    mics = distributed4()
    rng = np.random.default_rng(7)
    window = _render(np.array([3.0, 5.0, 3.0]), mics, RECIPE.span_seconds + 0.01)
    noise = rng.standard_normal(window.shape)
    features = torch.stack([phase_features(w, RATE, RECIPE) for w in (window, noise, noise)])
    times = torch.tensor([10.0, 10.2, 11.0], dtype=torch.float64)
    with torch.no_grad():
        out = net({"audio_phase": features, "time": times, "sequence": torch.zeros(3, dtype=torch.long)})
    position = out["position"].numpy()
    np.testing.assert_allclose(position[1], position[0])  # held
    np.testing.assert_allclose(position[2], net.region.mean(dim=1).numpy(), atol=1e-5)  # then the centre
    near = torch.tensor([[[0.0, 0.0, 1.0], [8.0, 20.0, 10.0]]])
    assert net.steering.near(near, torch.as_tensor(mics)).flatten().tolist() == [True, False]
    with pytest.raises(ValueError, match="fallback"):
        get_model("srp_phat", fallback="last")


def test_test_time_smoothing_bridges_the_windows_a_net_did_not_detect():
    from zoo.smoothing import make_smoother, smooth_detected
    from zoo.task import TrajectoryTask

    task = TrajectoryTask(net="srp_phat", smooth=True, smoother={"preset": "tuned", "horizon": 3.0})
    t = np.arange(80) / 10.0
    gt = np.stack([np.linspace(0, 8, 80), np.full(80, 15.0), np.full(80, 12.0)], axis=1)
    position = gt + np.random.default_rng(0).normal(0, 0.3, gt.shape)
    detected = np.ones(80, dtype=bool)
    detected[30:50] = False
    position[30:50] = position[29]  # held
    batch = {"sequence": torch.zeros(80, dtype=torch.long), "time": torch.from_numpy(t),
             "gt": torch.from_numpy(gt), "gt_valid": torch.ones(80, dtype=torch.bool)}
    task.log = lambda *args, **kwargs: None  # no trainer attached: the logged values are not looked at
    task.on_test_epoch_start()
    task._collect(0, batch, {"position": torch.from_numpy(position), "detected": torch.from_numpy(detected)})
    task._log_smoothed()
    smoothed = task.smoothed_predictions[0][0]
    expected = smooth_detected(make_smoother(preset="tuned", horizon=3.0), t, position, detected)
    np.testing.assert_allclose(smoothed, expected)
    held_error = np.linalg.norm(position[30:50] - gt[30:50], axis=1).mean()
    assert np.linalg.norm(smoothed[30:50] - gt[30:50], axis=1).mean() < held_error / 2


def test_grid_response_equals_the_gathered_terms_and_peaks_at_the_source(net):
    """The sparse steering matrix reads what the search's gather reads, and the response map (the phase
    student's first layer) peaks in the cube holding a synthetic free-field source."""
    mics = distributed4()
    source = np.array([3.2, 9.6, 4.4])
    audio = _render(source, mics, RECIPE.span_seconds + 0.01, snr_db=20.0)
    correlation = phase_features(audio, RATE, RECIPE).mean(dim=1, keepdim=True).permute(1, 0, 2)  # 1 x P x L
    student = get_model("phase_student", input_recipes={"audio_phase": "gcc_phat"})
    points = student.grid()[0]
    geometry = torch.as_tensor(mics)
    response = net.steering.grid_response(correlation, points, geometry, 1.0)
    flat = pooled(correlation)
    columns = net.steering.columns(points, geometry, 1.0)
    weights = net.steering.terms(4).weights
    np.testing.assert_allclose(response[0, 0].numpy(), gather(flat, columns, weights)[0].numpy(), atol=1e-5)
    np.testing.assert_allclose(response[0, 1].numpy(), flat[0, columns[:, :6]].mean(dim=-1).numpy(), atol=1e-5)
    phase = phase_features(audio, RATE, RECIPE)[None]
    centre = mics.mean(axis=0)

    def bearing_error(features: torch.Tensor) -> float:
        """Degrees between the source and the best cube of the direct terms' map, seen from the array
        (1 m cubes resolve the direction; the range along the ray is the net's and the curvature's job)."""
        with torch.no_grad():
            best = points[int(student.response(features, None, points)[0, 1].argmax())].numpy() - centre
        cosine = best @ (source - centre) / np.linalg.norm(best) / np.linalg.norm(source - centre)
        return float(np.degrees(np.arccos(np.clip(cosine, -1, 1))))

    assert bearing_error(phase) < 6.0
    assert bearing_error(phase_features(audio[[1, 0, 2, 3]], RATE, RECIPE)[None]) > 10.0


def test_phase_student_reads_the_batch_geometry_and_refuses_a_wrong_one():
    student = get_model("phase_student", input_recipes={"audio_phase": "gcc_phat"})
    inputs = student.example_inputs(2)
    mics = torch.as_tensor(distributed4())[None].expand(2, -1, -1)
    with torch.no_grad():
        same = student({**inputs, "mic_positions": mics})["position"]
        default = student(inputs)["position"]
        moved = student({**inputs, "mic_positions": mics + torch.tensor([0.0, 0.0, 0.5])})["position"]
    torch.testing.assert_close(same, default)
    assert not torch.allclose(moved, default)
    with pytest.raises(ValueError, match="phase_student: 3 mic positions for phase features of 6 pairs"):
        student({**inputs, "mic_positions": mics[:, :3]})
