"""Clock self-calibration: offsets found from the audio alone, applied to the phase features, bad input refused."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from datamodules.errors import ConfigError
from datamodules.features import PhaseWindows, phase_recipe
from datamodules.features.clock_calibration import (
    ClockCalibration,
    ClockCalibrationConfig,
    ClockCalibrationError,
    check_mode,
    estimate_clock_offsets,
    wants_calibration,
)
from datamodules.features.clock_following import combine_clock_estimates, consistent_estimates
from datamodules.recording import ArrayAudio
from datamodules.simulate.clocks import resample_at_clock
from datamodules.simulate.simulator import simulate_recording
from tests.helpers.flights import flying_m300

OFFSETS = np.array([0.0, 0.0, 0.8e-3, 0.0])  #: node 2 samples 0.8 ms late
TOLERANCE = 5e-5  #: 0.05 ms
CONFIG = ClockCalibrationConfig(jackknife_blocks=3)


@pytest.fixture(scope="module")
def shared_recording():
    """12 s of a loud drone flying (no hover: the calibration needs the geometry to change) in quiet air, all
    nodes on one clock."""
    return simulate_recording(flying_m300(12.0), seed=6)


def late(audio: ArrayAudio, offsets: np.ndarray) -> ArrayAudio:
    samples = resample_at_clock(audio.read(0, audio.num_samples), audio.sample_rate, offsets, np.zeros(len(offsets)))
    return ArrayAudio(samples, audio.sample_rate, audio.t0, audio.mic_positions)


def test_an_offset_on_one_node_is_found(shared_recording):
    found = estimate_clock_offsets(late(shared_recording.audio, OFFSETS), CONFIG)
    assert found.offsets_s[0] == 0.0
    assert np.abs(found.offsets_s - OFFSETS).max() < TOLERANCE, found.summary()
    assert np.all(np.isfinite(found.offsets_std_s)) and found.offsets_std_s.max() < TOLERANCE
    assert found.frames >= 10 and "clock offsets (ms, node 0 = 0): +0.000" in found.summary()
    again = ClockCalibration.from_array(found.to_array())
    assert np.array_equal(again.offsets_s, found.offsets_s) and again.key() == found.key()


def test_one_clock_gives_offsets_near_zero(shared_recording):
    found = estimate_clock_offsets(shared_recording.audio, CONFIG)
    assert np.abs(found.offsets_s).max() < TOLERANCE, found.summary()


def test_the_correction_undoes_the_offset(shared_recording):
    recipe = phase_recipe("gcc_phat")
    audio = shared_recording.audio
    times = audio.t0 + np.array([4.0, 8.0])
    truth = ClockCalibration(OFFSETS, np.zeros(4), np.zeros(4), np.zeros(4), frames=0, residual_rms_s=0.0)
    shared = np.stack([PhaseWindows(audio, recipe, times)(i) for i in range(2)])
    moved = late(audio, OFFSETS)
    raw = np.stack([PhaseWindows(moved, recipe, times)(i) for i in range(2)])
    corrected = np.stack([PhaseWindows(moved, recipe, times, clocks=truth)(i) for i in range(2)])
    assert np.abs(raw - shared).max() > 0.1  # the offset moves the pairs with node 2
    assert np.abs(corrected - shared).max() < 0.1 * np.abs(raw - shared).max()


def test_the_datamodule_switch_corrects_recordings_on_separate_clocks(shared_recording, tmp_path):
    from datamodules.formats.mcap_file import write_mcap
    from datamodules.mmaud import MMAUDDataModule

    recording = dataclasses.replace(shared_recording, audio=late(shared_recording.audio, OFFSETS),
                                    meta={**shared_recording.meta, "nodes_share_clock": False})
    write_mcap(recording, tmp_path / "data" / "late.mcap")
    write_mcap(shared_recording, tmp_path / "shared" / "shared.mcap")

    estimates = {}

    def features(stem: str, mode: str) -> tuple[np.ndarray, str]:
        folder = tmp_path / ("shared" if stem == "shared" else "data")
        module = MMAUDDataModule([str(folder)], split={"train": [], "val": [], "test": [stem]},
                                 inputs={"audio_phase": "gcc_phat"}, test_lights=["ideal"],
                                 cache_dir=str(tmp_path / "cache"), clock_calibration=mode)
        module.setup("test")
        estimates[(stem, mode)] = module.clock_estimates
        assert not module.sequences["test"][0].uncorrected_clocks  # corrected, on one clock, or off by choice
        key = module.sequences["test"][0].feature_keys["audio_phase"]
        return np.asarray(module.cache.open(key), dtype=np.float32), key

    reference, _ = features("shared", "auto")  # one clock: auto leaves it as it is
    raw, raw_key = features("late", "off")
    corrected, key = features("late", "auto")
    assert "-clk" in key and "-clk" not in raw_key
    assert estimates[("shared", "auto")] == {} and estimates[("late", "off")] == {}
    (found,) = estimates[("late", "auto")].values()
    assert isinstance(found, ClockCalibration) and abs(found.offsets_s[2] - 0.8e-3) < TOLERANCE

    def peak_lags(features: np.ndarray) -> np.ndarray:  # each window's strongest lag per pair (frames averaged)
        return features.mean(axis=2).argmax(axis=-1)

    moved = [1, 3, 5]  # the pairs with node 2: (0, 2), (1, 2), (2, 3)
    shift = 0.8e-3 * phase_recipe("gcc_phat").lag_rate  # 19.2 lags
    raw_moves = np.abs(peak_lags(raw) - peak_lags(reference))[:, moved]
    assert np.median(raw_moves) == pytest.approx(shift, abs=1.5)
    assert np.median(np.abs(peak_lags(corrected) - peak_lags(reference))[:, moved]) <= 1
    with pytest.raises(ConfigError, match="clock_calibration must be one of"):
        MMAUDDataModule([str(tmp_path / "data")], inputs={"audio_phase": "gcc_phat"}, clock_calibration="yes")


def test_modes():
    assert wants_calibration("auto", {"nodes_share_clock": False}) and not wants_calibration("auto", {})
    assert wants_calibration("on", {}) and not wants_calibration("off", {"nodes_share_clock": False})
    assert check_mode("auto") == "auto"
    with pytest.raises(ConfigError, match="clock_calibration must be one of"):
        check_mode("maybe")


def test_an_unreliable_fit_is_refused(shared_recording):
    strict = dataclasses.replace(CONFIG, max_residual=1e-9)  # no fit explains its measurements that well
    with pytest.raises(ClockCalibrationError, match=r"unreliable \(residual RMS .* clock offsets") as error:
        estimate_clock_offsets(late(shared_recording.audio, OFFSETS), strict)
    assert "\n" not in str(error.value)


def test_a_recording_that_cannot_be_calibrated_stays_uncorrected_and_says_so(shared_recording, tmp_path, caplog):
    from datamodules.formats.mcap_file import write_mcap
    from datamodules.mmaud import MMAUDDataModule

    audio = shared_recording.audio
    short = ArrayAudio(audio.read(0, int(1.5 * audio.sample_rate)), audio.sample_rate, audio.t0, audio.mic_positions)
    recording = dataclasses.replace(shared_recording, audio=short, meta={**shared_recording.meta,
                                                                          "nodes_share_clock": False})
    write_mcap(recording, tmp_path / "data" / "short.mcap")

    def module(mode: str) -> MMAUDDataModule:
        return MMAUDDataModule([str(tmp_path / "data")], split={"train": [], "val": [], "test": ["short"]},
                               inputs={"audio_phase": "gcc_phat"}, test_lights=["ideal"], window_seconds=1.0,
                               cache_dir=str(tmp_path / "cache"), clock_calibration=mode)

    auto = module("auto")
    with caplog.at_level("WARNING"):
        auto.setup("test")
    (reason,) = auto.clock_estimates.values()
    assert isinstance(reason, str) and "needs at least 10 blocks" in reason
    assert "NOT corrected" in caplog.text and "short.mcap" in caplog.text
    assert "-clk" not in auto.sequences["test"][0].feature_keys["audio_phase"]
    batch = next(iter(auto.test_dataloader()[0]))  # srp_phat reads this: no detection from such time differences
    assert batch["uncorrected_clocks"].all()
    with pytest.raises(ClockCalibrationError, match="short.mcap: clock calibration needs at least 10 blocks"):
        module("on").setup("test")


def test_bad_input_gives_one_line(shared_recording):
    audio = shared_recording.audio
    nowhere = ArrayAudio(audio.read(0, audio.num_samples), audio.sample_rate, audio.t0, np.zeros((4, 3)))
    with pytest.raises(ClockCalibrationError, match="needs the microphone positions") as error:
        estimate_clock_offsets(nowhere, CONFIG)
    assert "\n" not in str(error.value)
    short = ArrayAudio(audio.read(0, int(1 * audio.sample_rate)), audio.sample_rate, audio.t0, audio.mic_positions)
    with pytest.raises(ClockCalibrationError, match=r"needs at least 10 blocks .* gives 5") as error:
        estimate_clock_offsets(short, CONFIG)
    assert "\n" not in str(error.value)


def test_info_shows_the_estimated_offsets_of_separate_clocks_when_asked(shared_recording, tmp_path, capsys):
    from datamodules.cli import main
    from datamodules.formats.mcap_file import write_mcap

    late_recording = dataclasses.replace(shared_recording, audio=late(shared_recording.audio, OFFSETS),
                                         meta={**shared_recording.meta, "nodes_share_clock": False})
    write_mcap(late_recording, tmp_path / "late.mcap")
    write_mcap(shared_recording, tmp_path / "shared.mcap")
    capsys.readouterr()
    assert main(["info", str(tmp_path / "late.mcap"), str(tmp_path / "shared.mcap")]) == 0
    assert "clock offsets" not in capsys.readouterr().out  # costly: only with --clocks
    assert main(["info", str(tmp_path / "late.mcap"), str(tmp_path / "shared.mcap"), "--clocks"]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if "clock offsets" in line]
    assert len(lines) == 1 and lines[0].startswith("late.mcap: clock offsets (ms, node 0 = 0): +0.000 +- 0.000, ")
    node2 = float(lines[0].split("): ")[1].split(", ")[2].split(" +- ")[0])
    assert abs(node2 - 0.8) < 1e3 * TOLERANCE


def _synthetic(rng: np.random.Generator, offsets: np.ndarray, noise: float, frames: int = 60,
               drifts_ppm: np.ndarray | None = None, source: np.ndarray | None = None, outliers: float = 0.0):
    """Measurements of a drone (by default on a circle over the rig), offsets (and drifts) on the nodes,
    Gaussian noise of ``noise`` s, and in a share ``outliers`` of the time differences errors of 0.3 ms."""
    from datamodules.features.clock_calibration import FrameMeasurements, _ground_images
    from datamodules.features.phase import SPEED_OF_SOUND, mic_pairs

    mics = np.array([[0.0, 0.0, 0.2], [3.0, 0.0, 0.7], [3.0, 3.0, 1.2], [0.0, 3.0, 1.7]])
    times = np.arange(frames) * 0.17
    if source is None:
        angle = np.linspace(0, 2 * np.pi, frames, endpoint=False)
        source = np.stack([1.5 + 6 * np.cos(angle), 8 + 6 * np.sin(angle), 6 + 2 * np.sin(2 * angle)], axis=1)
    direct = np.linalg.norm(source[:, None] - mics[None], axis=-1) / SPEED_OF_SOUND
    image = np.linalg.norm(source[:, None] - _ground_images(mics, 0.0)[None], axis=-1) / SPEED_OF_SOUND
    drifts = np.zeros_like(offsets) if drifts_ppm is None else drifts_ppm
    apparent = direct - (offsets[None] + drifts[None] * 1e-6 * times[:, None])
    pairs = mic_pairs(4)
    tdoa = np.stack([apparent[:, i] - apparent[:, j] for i, j in pairs], axis=1)
    tdoa += rng.normal(0, noise, tdoa.shape) + (rng.random(tdoa.shape) < outliers) * rng.normal(0, 3e-4, tdoa.shape)
    measured = FrameMeasurements(times, image - direct + rng.normal(0, noise, (frames, 4)), tdoa,
                                 np.full(frames, 10.0))
    return mics, measured, source


def test_the_jacobian_is_that_of_the_residuals():
    from datamodules.features.clock_calibration import _Model

    mics, measured, source = _synthetic(np.random.default_rng(0), np.array([0.0, 3e-4, -2e-4, 1e-4]), 5e-6, 8)
    for drift in (False, True):
        model = _Model(mics, measured, dataclasses.replace(CONFIG, fit_drift=drift))
        frames = np.arange(8)
        theta = np.concatenate([np.full(model.clock_params, 1e-4), (source + 0.3).ravel()])
        jac = model.jacobian(theta, frames)
        step = np.where(np.arange(theta.size) < model.clock_params, 1e-7, 1e-4)
        numeric = np.stack([(model.residuals(theta + np.eye(theta.size)[k] * step[k], frames)
                             - model.residuals(theta - np.eye(theta.size)[k] * step[k], frames)) / (2 * step[k])
                            for k in range(theta.size)], axis=1)
        assert np.allclose(jac, numeric, rtol=1e-4, atol=1e-3 * np.abs(numeric).max())


def test_the_fit_reaches_the_same_clocks_from_far_and_from_the_truth():
    """A 10 s straight pass far from the rig with heavy-tailed time differences: the offsets and drifts lie in a
    long flat valley of the cost, along which iterative steps stopped short (up to 0.04 ms apart here, 0.4 ms
    on development flights)."""
    from datamodules.features.clock_calibration import _Model

    offsets, drifts = np.array([0.0, 3e-4, -2e-4, 1e-4]), np.array([0.0, -2.5, -12.0, 3.0])
    times = np.arange(58) * 0.17
    path = np.stack([-10 + 2.0 * times, 40 + 0.5 * times, 12 - 0.2 * times], axis=1)
    for seed in range(5):
        rng = np.random.default_rng(seed)
        mics, measured, source = _synthetic(rng, offsets, 3e-5, 58, drifts, path, outliers=0.3)
        model = _Model(mics, measured, CONFIG)
        assert CONFIG.fit_drift and model.clock_params == 6
        frames = np.arange(58)
        guess = source + rng.normal(0, 2.0, source.shape)
        far = model.solve(frames, np.concatenate([np.zeros(6), guess.ravel()]))
        near = model.solve(frames, np.concatenate([offsets[1:], drifts[1:], source.ravel()]))
        assert far.status > 0 and near.status > 0  # converged, not stopped by the evaluation limit
        np.testing.assert_allclose(far.x[:3], near.x[:3], rtol=0, atol=3e-6)


def test_the_sandwich_std_matches_the_spread_of_repeated_fits():
    from datamodules.features.clock_calibration import _Model, _sandwich

    offsets, noise = np.array([0.0, 3e-4, -2e-4, 1e-4]), 5e-6
    config = dataclasses.replace(CONFIG, fit_drift=False)
    estimates, stds = [], []
    for seed in range(25):
        mics, measured, source = _synthetic(np.random.default_rng(seed), offsets, noise)
        model = _Model(mics, measured, config)
        frames = np.arange(source.shape[0])
        fit = model.solve(frames, np.concatenate([np.zeros(3), source.ravel()]))
        estimates.append(fit.x[:3])
        stds.append(_sandwich(model, frames, fit.x, fit.fun, cluster_seconds=0.5))
    spread, predicted = np.std(estimates, axis=0), np.sqrt(np.mean(np.square(stds), axis=0))
    assert np.all(predicted > 0.6 * spread) and np.all(predicted < 1.6 * spread)
    assert np.abs(np.mean(estimates, axis=0) - offsets[1:]).max() < 3 * spread.max()


def test_the_offsets_std_holds_the_floor_no_spread_over_the_frames_shows():
    from datamodules.features.clock_calibration import _fit

    mics, measured, source = _synthetic(np.random.default_rng(3), np.array([0.0, 3e-4, -2e-4, 1e-4]), 5e-6)
    frames = np.arange(source.shape[0])
    config = dataclasses.replace(CONFIG, fit_drift=False)
    spread = _fit(mics, measured, frames, source, dataclasses.replace(config, std_floor=0.0)).offsets_std_s
    reported = _fit(mics, measured, frames, source, config).offsets_std_s
    assert reported[0] == 0.0 and spread[0] == 0.0  # node 0 is the reference
    assert np.all(spread[1:] < config.std_floor)  # 5 us of noise over the frames: the floor dominates
    assert reported[1:] == pytest.approx(np.hypot(spread[1:], config.std_floor))


def _piece(start: float, duration: float, offset_at_centre: float, std: float, drift_ppm: float = 0.0):
    """One stretch's estimate (two nodes) whose node-1 offset at the stretch's centre is ``offset_at_centre``."""
    offset = offset_at_centre - drift_ppm * 1e-6 * duration / 2
    return start, duration, ClockCalibration(np.array([0.0, offset]), np.array([0.0, std]), np.array([0.0, drift_ppm]),
                                             np.zeros(2), frames=40, residual_rms_s=1e-5)


def test_estimates_of_successive_stretches_give_the_drift_over_their_whole_span():
    line = 1e-3 + 20e-6 * np.arange(5, 60, 10)  # 1 ms + 20 ppm, at the centres of six 10 s stretches
    pieces = [_piece(10.0 * k, 10.0, value, 1e-5) for k, value in enumerate(line)]
    combined = combine_clock_estimates(pieces)
    assert combined.drifts_ppm[1] == pytest.approx(20.0, abs=1e-6) and combined.offsets_s[1] == pytest.approx(1e-3)
    assert combined.offsets_at(30.0)[1] == pytest.approx(1e-3 + 20e-6 * 30.0)
    # the std of the drift: 1e-5 s over a 50 s span of six points
    assert 0.1 < combined.drifts_std_ppm[1] < 0.5 and combined.frames == 240
    # measurements scattered more widely than their stds say: the standard errors grow with the scatter
    noisy = [_piece(s, d, e.offsets_at(d / 2)[1] + (3e-5 if k % 2 else -3e-5), 1e-5)
             for k, (s, d, e) in enumerate(pieces)]
    assert combine_clock_estimates(noisy).drifts_std_ppm[1] > 2 * combined.drifts_std_ppm[1]


def test_stretch_estimates_that_disagree_with_the_line_of_the_others_are_left_out():
    """A stretch whose fit went wrong (tenths of a millisecond off with a std of hundredths) does not bend the line;
    with half the stretches wrong in different ways the ones that agree still win."""
    line = 1e-3 + 20e-6 * np.arange(5, 60, 10)
    good = [_piece(10.0 * k, 10.0, value, 1e-5) for k, value in enumerate(line)]
    one_wrong = [*good[:1], _piece(10.0, 10.0, line[1] + 0.7e-3, 1e-5), *good[2:]]
    assert consistent_estimates(one_wrong) == [True, False, True, True, True, True]
    expected = combine_clock_estimates(good[:1] + good[2:])
    np.testing.assert_allclose(combine_clock_estimates(one_wrong).offsets_at(55.0), expected.offsets_at(55.0))
    assert combine_clock_estimates(one_wrong).drifts_ppm[1] == pytest.approx(20.0, abs=1e-6)
    half_wrong = [good[0], _piece(10.0, 10.0, line[1] + 0.7e-3, 1e-5), good[2],
                  _piece(30.0, 10.0, line[3] + 0.3e-3, 1e-5), good[4], _piece(50.0, 10.0, line[5] - 0.4e-3, 1e-5)]
    assert consistent_estimates(half_wrong) == [True, False, True, False, True, False]
    assert consistent_estimates(good) == [True] * 6
    assert consistent_estimates(one_wrong[:2]) == [True, True]  # two cannot tell which one is wrong
    # a line only a drift no crystal has would explain is no support
    fast = [_piece(0.0, 10.0, 0.0, 1e-5), _piece(10.0, 10.0, 3e-3, 1e-5), _piece(20.0, 10.0, 6e-3, 1e-5)]
    assert consistent_estimates(fast) == [True, True, True]  # no plausible pair: nothing is judged
    # an hour of 10 s stretches: lines through pairs of a few of them, spread over the stream
    hour = [_piece(10.0 * k, 10.0, 1e-3 + 20e-6 * (10.0 * k + 5), 1e-5) for k in range(360)]
    wrong = {7, 100, 101, 250, 359}
    hour = [_piece(s, d, e.offsets_at(d / 2)[1] + 0.5e-3, 1e-5) if k in wrong else (s, d, e)
            for k, (s, d, e) in enumerate(hour)]
    assert [k for k, kept in enumerate(consistent_estimates(hour)) if not kept] == sorted(wrong)


def test_a_fit_with_a_drift_no_crystal_has_is_refused(monkeypatch):
    import datamodules.features.clock_calibration as calibration

    frames = 20
    measured = calibration.FrameMeasurements(np.arange(frames, dtype=float), np.full((frames, 4), 1e-3),
                                             np.zeros((frames, 6)), np.full(frames, 10.0))
    fitted = ClockCalibration(np.array([0.0, 1e-3, 0.0, 0.0]), np.full(4, 1e-5), np.array([0.0, 300.0, 0.0, 0.0]),
                              np.ones(4), frames=frames, residual_rms_s=1e-5)
    monkeypatch.setattr(calibration, "measure", lambda audio, config, drifts_ppm=None: measured)
    monkeypatch.setattr(calibration, "_initial_positions", lambda mics, m, used, config: np.zeros((used.size, 3)))
    monkeypatch.setattr(calibration, "_fit", lambda *args: fitted)
    mics = np.array([[1.5, 1.5, 0.2], [-1.5, 1.5, 0.7], [-1.5, -1.5, 1.2], [1.5, -1.5, 1.7]])
    audio = ArrayAudio(np.zeros((4, 48000), dtype=np.float32), 48000.0, 0.0, mics)
    with pytest.raises(ClockCalibrationError, match="beyond the plausible"):
        estimate_clock_offsets(audio)
    fitted.drifts_ppm[1] = 30.0
    assert estimate_clock_offsets(audio) is fitted


def test_a_drift_not_told_from_zero_leaves_a_weighted_mean_and_one_estimate_is_shifted_to_the_stream():
    pieces = [_piece(0.0, 10.0, 1.00e-3, 1e-5), _piece(10.0, 10.0, 1.01e-3, 2e-5), _piece(20.0, 10.0, 0.99e-3, 1e-5)]
    combined = combine_clock_estimates(pieces)
    assert combined.drifts_ppm[1] == 0.0
    assert combined.offsets_s[1] == pytest.approx((1.00e-3 * 4 + 1.01e-3 + 0.99e-3 * 4) / 9)  # weights 1 / std^2
    # the fits' own spread weights them; the std reported holds the estimator's floor as well
    floor = ClockCalibrationConfig.std_floor
    assert combined.offsets_std_s[0] == 0.0
    assert combined.offsets_std_s[1] == pytest.approx(np.hypot(1e-5 / 9 ** 0.5 * 2, floor))
    start, duration, only = _piece(20.0, 10.0, 1e-3, 1e-5, drift_ppm=5.0)
    alone = combine_clock_estimates([(start, duration, only)])
    assert alone.offsets_at(27.0)[1] == pytest.approx(only.offsets_at(7.0)[1])
    assert alone.offsets_std_s[1] == pytest.approx(np.hypot(1e-5, floor))
    # two estimates far apart for their stds: a line through both
    two = combine_clock_estimates([_piece(0.0, 10.0, 1.0e-3, 1e-5), _piece(10.0, 10.0, 1.2e-3, 1e-5)])
    assert two.drifts_ppm[1] == pytest.approx(20.0) and two.offsets_at(5.0)[1] == pytest.approx(1.0e-3)
    with pytest.raises(ValueError):
        combine_clock_estimates([])
