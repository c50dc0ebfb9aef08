"""aaute track with the phase localisers: equality with offline predict, the gate in stream order, geometry."""

from __future__ import annotations

import io
import logging
import multiprocessing
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
import yaml

from datamodules.features import PhaseWindows
from datamodules.formats import open_recording
from datamodules.streams import PcmSource, RecordingSource
from zoo.callbacks import PredictionCsvWriter
from zoo.deploy.live_phase import GatedSmoothing, PhaseRow, PhaseTracker, check_geometry, load_phase_model
from zoo.deploy.tracking import TrackingError
from zoo.smoothing import ROBUST_PRESETS, OnlineSmoother

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "model" / "srp_phat.yaml"
NULL_WINDOWS = 40  #: fewer null windows than the config's 300: the same on both sides, a faster test


class Rows:
    def __init__(self):
        self.rows = []

    def write(self, row) -> None:
        self.rows.append(row)


@pytest.fixture(scope="module")
def quiet_recording(tmp_path_factory) -> Path:
    """One 6 s flight in quiet ambient (no wind, no HVAC), so srp_phat detects it in some windows."""
    from datamodules.simulate.acoustics import AudioConfig
    from datamodules.simulate.ambient import AmbientConfig
    from datamodules.simulate.simulator import SimulationConfig, simulate_dataset

    out = tmp_path_factory.mktemp("quiet")
    ambient = AmbientConfig(level_dba=(45.0, 45.0), wind_speed=(0.0, 0.0), hvac=False)
    config = SimulationConfig(duration=6.0, camera=False, audio=AudioConfig(ambient=ambient))
    return simulate_dataset(out, 1, config, seed=3, progress=False)[0]


def _live(path: Path, **options) -> tuple[list[PhaseRow], PhaseTracker]:
    source = RecordingSource(path)
    model = load_phase_model(config=CONFIG, source=source)
    model.net.null_windows = NULL_WINDOWS
    rows = Rows()
    tracker = PhaseTracker(model, source, [rows], **options)
    tracker.run()
    return rows.rows, tracker


@pytest.fixture(scope="module")
def live_rows(quiet_recording):
    torch.set_num_threads(1)
    return _live(quiet_recording)[0]


@pytest.fixture(scope="module")
def offline(quiet_recording, tmp_path_factory):
    """``TrajectoryTask.predict_step`` of the same config over the DataModule's predict windows, with float32
    features of the offline recipe (:class:`PhaseWindows`) in place of the float16 cache's."""
    from datamodules.mmaud import MMAUDDataModule
    from zoo.task import TrajectoryTask

    config = yaml.safe_load(CONFIG.read_text())
    kwargs = dict(config["model"]["init_args"]["net_kwargs"], null_windows=NULL_WINDOWS)
    recipe_name = config["data"]["init_args"]["inputs"]["audio_phase"]
    task = TrajectoryTask(net="srp_phat", net_kwargs=kwargs)
    data = MMAUDDataModule(root=str(quiet_recording), split={"test": [quiet_recording.stem]},
                           inputs={"audio_phase": recipe_name}, test_lights=["ideal"],
                           cache_dir=str(tmp_path_factory.mktemp("cache")))
    data.setup("predict")
    task.net.set_bounds(data.bev_bounds)
    batches = list(data.predict_dataloader()[0])
    times = np.concatenate([b["time"].numpy() for b in batches])
    assert np.all(np.diff(times) > 0), "the predict loader gives one sequence's windows in time order"
    audio = open_recording(quiet_recording).audio
    windows = PhaseWindows(audio, task.net.recipe, times)
    out, index = {"time": [], "position": [], "state": []}, 0
    task.on_predict_epoch_start()
    with torch.no_grad():
        for i, batch in enumerate(batches):
            n = len(batch["time"])
            batch["audio_phase"] = torch.stack([torch.from_numpy(windows(index + k)) for k in range(n)])
            index += n
            result = task.predict_step(batch, i)
            out["time"].append(result["time"].numpy())
            out["position"].append(result["position"].double().numpy())
            out["state"] += task.net.gate.states  # the gate's verdict on each window of this batch
    result = {key: np.concatenate(value) if key != "state" else np.array(value) for key, value in out.items()}
    result["detected"] = result["state"] == "detected"
    written = tmp_path_factory.mktemp("predictions")
    PredictionCsvWriter(written).write(task, "predict")  # what aaute predict writes
    result["csv"] = pd.read_csv(next(written.glob("*.csv")))
    return result


def test_live_rows_equal_offline_predictions_of_the_same_config(live_rows, offline):
    t = np.array([r.timestamp for r in live_rows])
    index = np.searchsorted(t, offline["time"] - 1e-6)
    assert np.all(np.abs(t[index] - offline["time"]) < 1e-6), "every label time has a live row"
    live = [live_rows[i] for i in index]
    states = np.array([r.state for r in live])
    assert "detected" in states, "the quiet flight is detected in some windows"
    assert list(states) == list(offline["state"])
    assert np.array_equal([r.detected for r in live], offline["detected"])
    raw = np.array([r.raw for r in live])
    np.testing.assert_allclose(raw, offline["position"], atol=1e-4)  # float32 search, the same features


def test_the_offline_prediction_file_says_what_each_position_is_as_the_live_rows_do(live_rows, offline):
    table = offline["csv"]
    assert list(table.columns) == ["timestamp", "x", "y", "z", "detection_score", "detected", "state"]
    assert list(table["state"]) == list(offline["state"])
    assert np.array_equal(table["detected"].to_numpy(), offline["detected"].astype(int))
    t = np.array([r.timestamp for r in live_rows])
    live = [live_rows[i] for i in np.searchsorted(t, table["timestamp"].to_numpy() - 1e-5)]
    np.testing.assert_allclose(table["detection_score"], [r.score for r in live], atol=1e-4)


def test_smoothing_the_offline_predictions_gives_the_live_smoothed_rows(live_rows, offline, tmp_path):
    """``aaute predict`` then ``aaute smooth --preset srp_phat --lag 0`` is what ``aaute track`` writes."""
    from benchmarks.cli import main

    src = tmp_path / "predictions.csv"
    offline["csv"].to_csv(src, index=False)
    assert main(["smooth", str(src), str(tmp_path / "smoothed.csv"), "--preset", "srp_phat", "--lag", "0"]) == 0
    smoothed = pd.read_csv(tmp_path / "smoothed.csv")
    t = np.array([r.timestamp for r in live_rows])
    index = np.searchsorted(t, smoothed["timestamp"].to_numpy() - 1e-5)
    assert np.all(np.abs(t[index] - smoothed["timestamp"].to_numpy()) < 1e-5)
    assert len(t) - len(index) <= 1, "the live rows past the last label time are the only ones predict has not"
    live = [live_rows[i] for i in index]
    assert {r.state for r in live} >= {"detected", "fallback"}
    for columns, values in ((["x", "y", "z"], [r.mean for r in live]),
                            (["std_x", "std_y", "std_z"], [r.std for r in live])):  # fallback rows: NaN in both
        np.testing.assert_allclose(smoothed[columns].to_numpy(), np.array(values), atol=1e-4)  # raw rows' 1e-4


def test_rows_say_what_each_position_is(live_rows):
    for row in live_rows:
        assert row.state in ("detected", "held", "fallback")
        assert row.detected == (row.state == "detected")
        if row.state == "detected":
            assert np.isfinite(row.std).all() and row.score > 1.0
        if row.state == "fallback":
            assert np.isnan(row.std).all() and np.array_equal(row.mean, row.raw)
    t = np.array([r.timestamp for r in live_rows])
    assert np.all(np.diff(t) > 0)


def test_smoothing_a_live_track_file_again_reads_its_raw_positions(live_rows, tmp_path):
    """``aaute smooth`` of ``aaute track``'s own CSV smooths its ``raw_*`` (its ``x,y,z`` are smoothed already):
    with the same preset and lag it gives the same rows back."""
    from benchmarks.cli import main
    from zoo.deploy.live_phase import PhaseCsvWriter

    path = tmp_path / "track.csv"
    with open(path, "w") as stream:
        writer = PhaseCsvWriter(stream)
        for row in live_rows:
            writer.write(row)
    assert main(["smooth", str(path), str(tmp_path / "again.csv"), "--preset", "srp_phat", "--lag", "0"]) == 0
    again = pd.read_csv(tmp_path / "again.csv")
    np.testing.assert_allclose(again[["x", "y", "z"]].to_numpy(), np.array([r.mean for r in live_rows]), atol=1e-4)
    np.testing.assert_allclose(again[["std_x", "std_y", "std_z"]].to_numpy(), np.array([r.std for r in live_rows]),
                               atol=1e-4)


def test_gated_smoothing_feeds_measurements_only_and_keeps_time_order():
    """A fixed-lag smoother: a held row waits for the lag, and is written after the detection before it."""
    steps = [(0.1, "fallback"), (0.2, "detected"), (0.3, "detected"), (0.4, "held"), (0.5, "held"),
             (0.6, "held"), (0.7, "held"), (0.8, "detected")]

    def run(lag: float, last_x: float = 0.8) -> list[PhaseRow]:
        gated = GatedSmoothing(OnlineSmoother("robust", lag=lag))
        out = []
        for t, state in steps:
            x = last_x if t == 0.8 else t
            out += gated.add(PhaseRow(t, np.array([x, 0.0, 5.0]), 2.0, state == "detected", state))
            assert [r.timestamp for r in out] == sorted(r.timestamp for r in out)
        return out + gated.flush()

    for lag in (0.0, 0.3):
        out = run(lag)
        assert [r.timestamp for r in out] == [t for t, _ in steps]
        constant = [r for r in out if r.state == "held" and (lag == 0 or r.timestamp + lag < 0.8 - 1e-9)]
        assert [r.timestamp for r in constant] == ([0.4, 0.5, 0.6, 0.7] if lag == 0 else [0.4])
        assert all(np.allclose(r.mean, out[2].mean) for r in constant)  # the latest smoothed detection, 0.3 s
        stds = [r.std for r in constant]  # growing with the time since that detection
        assert all(np.all(later > earlier) for earlier, later in zip(stds, stds[1:], strict=False))
        assert np.all(stds[0] > out[2].std)
    out = run(0.3)  # held rows with the 0.8 s detection within their lag: the smoother's interpolation
    x = [r.mean[0] for r in out[3:8]]
    assert all(b > a for a, b in zip(x, x[1:], strict=False)), x  # the track moves on through the hold
    beyond = run(0.3, last_x=5.0)  # a detection beyond a row's lag does not change it
    np.testing.assert_array_equal(beyond[3].mean, out[3].mean)
    assert not np.allclose(beyond[4].mean, out[4].mean)


def test_a_held_rows_std_is_calibrated_by_the_hold_factor_and_a_detections_by_the_std_factor():
    """std_scale calibrates the detections' std, hold_scale the held rows' (extrapolated at lag 0, interpolated
    with a later detection within the lag); without hold_scale the held rows take std_scale's factor."""
    from dataclasses import replace

    steps = [(0.1 * k, "detected") for k in range(1, 11)] + [(1.1, "held"), (1.2, "held"), (1.3, "detected")]

    def run(hp, lag: float) -> list[PhaseRow]:
        gated = GatedSmoothing(OnlineSmoother(hp, lag=lag))
        out = []
        for t, state in steps:
            out += gated.add(PhaseRow(t, np.array([t, 10.0, 5.0]), 5.0, state == "detected", state))
        return out + gated.flush()

    plain = replace(ROBUST_PRESETS["srp_phat"], std_scale=(), hold_scale=())
    for lag in (0.0, 0.3):
        base = run(plain, lag)
        scaled = run(replace(plain, std_scale=((0.0, 3.0),), hold_scale=((0.0, 7.0),)), lag)
        fallback = run(replace(plain, std_scale=((0.0, 3.0),)), lag)
        for b, s, f in zip(base, scaled, fallback, strict=True):
            np.testing.assert_array_equal(s.mean, b.mean)  # the factors change stds only
            factor = 7.0 if b.state == "held" else 3.0
            np.testing.assert_allclose(s.std, factor * b.std, rtol=1e-12)
            np.testing.assert_allclose(f.std, 3.0 * b.std, rtol=1e-12)
    assert replace(plain, std_scale=((0.0, 2.0), (1.0, 4.0))).hold_scale_for(0.5) == pytest.approx(3.0)
    with pytest.raises(ValueError, match="hold_scale needs"):
        replace(plain, hold_scale=((0.0, -1.0),))


def test_the_std_score_factor_scales_a_detections_std_by_its_score_and_a_held_rows_by_the_detection_before():
    """With std_score_power the std of a detection is multiplied by (score / reference) ** power, that of a
    held row (extrapolated at lag 0, interpolated at lag 0.3 s) by its last detection's factor; the means
    do not change."""
    from dataclasses import replace

    steps = [(0.1 * k, "detected", 2.0 + k) for k in range(1, 11)] + [(1.1, "held", 0.5), (1.2, "held", 0.7),
                                                                       (1.3, "detected", 9.0)]

    def run(hp, lag: float) -> list[PhaseRow]:
        gated = GatedSmoothing(OnlineSmoother(hp, lag=lag))
        out = []
        for t, state, score in steps:
            out += gated.add(PhaseRow(t, np.array([t, 10.0, 5.0]), score, state == "detected", state))
        return out + gated.flush()

    plain = replace(ROBUST_PRESETS["srp_phat"], score_power=0.0, std_score_power=0.0)
    for lag in (0.0, 0.3):
        base, scaled = run(plain, lag), run(replace(plain, std_score_power=2.0, score_reference=4.0), lag)
        assert [r.state for r in base] == [s for _, s, _ in steps]
        for b, s, (_, state, score) in zip(base, scaled, steps, strict=True):
            np.testing.assert_array_equal(s.mean, b.mean)
            basis = score if state == "detected" else 12.0  # the held rows: the 1.0 s detection's score
            np.testing.assert_allclose(s.std, (basis / 4.0) ** 2 * b.std, rtol=1e-12)


def test_a_weak_detection_moves_the_smoothed_track_less_when_the_preset_scales_noise_by_score():
    """The gated smoother hands each detection's score to the smoother as a noise scale."""
    from dataclasses import replace

    plain = replace(ROBUST_PRESETS["srp_phat"], score_power=0.0)
    scored = replace(plain, score_power=4.0, score_reference=5.0)

    def last_mean(hp, score: float) -> np.ndarray:
        gated = GatedSmoothing(OnlineSmoother(hp, lag=0.0))
        out = []
        for k in range(20):  # a steady track of typical detections, then one off it
            out += gated.add(PhaseRow(0.1 * k, np.array([2.0, 10.0, 5.0]), 5.0, True, "detected"))
        out += gated.add(PhaseRow(2.0, np.array([2.1, 10.1, 5.1]), score, True, "detected"))  # within the noise
        return out[-1].mean

    np.testing.assert_array_equal(last_mean(scored, 5.0), last_mean(plain, 5.0))  # a typical score: no change
    weak, typical = last_mean(scored, 1.2), last_mean(plain, 1.2)
    assert np.linalg.norm(weak - [2.0, 10.0, 5.0]) < 0.5 * np.linalg.norm(typical - [2.0, 10.0, 5.0])


def test_a_phase_model_refuses_a_source_without_positions(quiet_recording):
    audio = open_recording(quiet_recording).audio
    pcm = (audio.read(0, 48000).T * 32767).astype("<i2").tobytes()
    source = PcmSource(io.BytesIO(pcm), 4, 48000.0, "s16le")  # no --mic-positions: the default array stands in
    with pytest.raises(TrackingError, match="pass --mic-positions FILE"):
        load_phase_model(config=CONFIG, source=source)


def test_nodes_on_separate_clocks_are_calibrated_from_the_stream_start(tmp_path, caplog):
    from datamodules.simulate.acoustics import AudioConfig
    from datamodules.simulate.ambient import AmbientConfig
    from datamodules.simulate.clocks import ClockConfig
    from datamodules.simulate.simulator import SimulationConfig, simulate_dataset
    from datamodules.simulate.trajectory import TrajectoryConfig
    from zoo.deploy.live_phase import CalibratingPhase

    quiet = AmbientConfig(level_dba=(45.0, 45.0), wind_speed=(0.0, 0.0), hvac=False)
    flying = TrajectoryConfig(hover_probability=0.0, cruise_speed_median=3.0, cruise_speed_sigma=0.1)
    config = SimulationConfig(duration=12.0, drone="m300", camera=False, lidar_sensors=(), trajectory=flying,
                              audio=AudioConfig(ambient=quiet), clocks=ClockConfig(offset_ms=[0.0, 0.0, 0.8, 0.0]))
    path = simulate_dataset(tmp_path / "nodes", 1, config, seed=6, progress=False)[0]

    def tracker(clock_seconds: float, rows: Rows | None = None) -> PhaseTracker:
        source = RecordingSource(path)
        model = load_phase_model(config=CONFIG, source=source)
        model.net.null_windows = NULL_WINDOWS
        return PhaseTracker(model, source, [rows or Rows()], clock_seconds=clock_seconds)

    written = Rows()
    with caplog.at_level(logging.WARNING):
        live = tracker(8.0, written)
        live.front.background = False  # the block that completes the 8 s waits for the estimate
        live.run()
    front = live.front
    assert isinstance(front, CalibratingPhase) and front.calibrated_at == pytest.approx(8.0, abs=0.1)
    # rows from uncorrected time differences say so and are never detections; none is held after them
    t0 = open_recording(path).audio.t0
    before = [r for r in written.rows if r.timestamp - t0 < front.calibrated_at - 1e-6]
    after = [r for r in written.rows if r.timestamp - t0 >= front.calibrated_at - 1e-6]
    assert before and after and {r.state for r in before} == {"uncorrected"}
    assert not any(r.detected for r in before) and all(np.isnan(r.std).all() for r in before)
    assert max(r.score for r in before) > 1  # the net found a peak there: only the clocks keep it from counting
    assert "uncorrected" not in {r.state for r in after}
    first = next(i for i, r in enumerate(after) if r.state == "detected")
    assert {r.state for r in after[:first]} == {"fallback"}  # nothing held from before the correction
    assert front.estimate_cpu_seconds > 0 and front.estimate_seconds > 0
    offsets = front.calibration.offsets_s
    assert abs(offsets[2] - 0.8e-3) < 5e-5 and np.abs(offsets[[1, 3]]).max() < 5e-5
    assert "estimated from the first 8 s" in caplog.text
    assert "phase features corrected by the clock offsets" in caplog.text
    # the last window's features: those of the offline recipe corrected by the same clocks, not the raw ones
    audio = open_recording(path).audio
    t_end = np.array([audio.t0 + front.end / audio.sample_rate])
    features = front.features().numpy()
    corrected = PhaseWindows(audio, front.recipe, t_end, clocks=front.calibration)(0)
    raw = PhaseWindows(audio, front.recipe, t_end)(0)
    assert np.abs(features - corrected).max() < 0.1 * np.abs(features - raw).max()
    # in the background (the default: a worker process) the same estimate arrives later, and the blocks
    # meanwhile are not held up
    background = CalibratingPhase(front.recipe, audio.sample_rate, audio.mic_positions, 8.0, "background")
    block = 4800
    for stop in range(block, 8 * 48000 + 1, block):
        background.push(audio.read(stop - block, stop))
    assert background.calibration is None  # the estimate is under way; only a later block applies it
    assert background.wait(timeout=300)
    background.push(audio.read(8 * 48000, 8 * 48000 + block))
    assert background.calibrated_at == pytest.approx(8.1)
    # the same estimate (the worker runs one torch thread: equal to the bit when this process does too)
    np.testing.assert_allclose(background.calibration.offsets_s, front.calibration.offsets_s, rtol=0, atol=1e-12)
    background.close()  # the worker process ends; closing twice is harmless
    background.close()
    assert not multiprocessing.active_children()
    tracker(8.0).run()  # the stream ends while the worker estimates: the run ends the worker
    assert not multiprocessing.active_children()
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        plain = tracker(0.0)
    assert type(plain.front) is not CalibratingPhase and "offsets between the nodes are not calibrated" in caplog.text


def test_positions_file_serves_pcm_and_a_wrong_rate_is_refused(quiet_recording, tmp_path, caplog):
    audio = open_recording(quiet_recording).audio
    mics = tmp_path / "mics.txt"
    np.savetxt(mics, audio.mic_positions)
    pcm = (audio.read(0, 16000).T * 32767).astype("<i2").tobytes()
    source = PcmSource(io.BytesIO(pcm), 4, 16000.0, "s16le", mic_positions=mics)
    model = load_phase_model(config=CONFIG, source=source)
    with pytest.raises(TrackingError, match="16000 Hz.*at least 16000|needs at least"):
        check_geometry(model, PcmSource(io.BytesIO(pcm), 4, 12000.0, "s16le", mic_positions=mics))
    small = tmp_path / "small.txt"
    np.savetxt(small, audio.mic_positions * 0.02)  # a 9 cm array
    with caplog.at_level(logging.WARNING):
        check_geometry(model, PcmSource(io.BytesIO(pcm), 4, 48000.0, "s16le", mic_positions=small))
    assert "cannot resolve range" in caplog.text


def test_any_channel_count_from_a_config(quiet_recording, tmp_path):
    """srp_phat steers the array it is given: three of the four microphones track too."""
    audio = open_recording(quiet_recording).audio
    mics = tmp_path / "mics3.txt"
    np.savetxt(mics, audio.mic_positions[:3])
    samples = audio.read(0, int(2.5 * 48000))[:3]
    source = PcmSource(io.BytesIO((samples.T * 32767).astype("<i2").tobytes()), 3, 48000.0, "s16le",
                       mic_positions=mics)
    model = load_phase_model(config=CONFIG, source=source)
    model.net.null_windows = 20
    rows = Rows()
    PhaseTracker(model, source, [rows]).run()
    assert len(rows.rows) == 6 and all(np.isfinite(r.raw).all() for r in rows.rows)


def _small_config(tmp_path: Path) -> Path:
    config = yaml.safe_load(CONFIG.read_text())
    config["model"]["init_args"]["net_kwargs"]["null_windows"] = 20
    path = tmp_path / "srp_phat_small.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def test_a_nan_block_skips_exactly_the_windows_that_contain_it(quiet_recording, tmp_path, caplog):
    audio = open_recording(quiet_recording).audio
    mics = tmp_path / "mics.txt"
    np.savetxt(mics, audio.mic_positions)
    samples = audio.read(0, int(3.0 * 48000)).copy()
    samples[:, 24000:28800] = np.nan  # the block 0.5-0.6 s
    source = PcmSource(io.BytesIO(samples.T.astype("<f4").tobytes()), 4, 48000.0, "f32le", mic_positions=mics)
    model = load_phase_model(config=_small_config(tmp_path), source=source)
    rows = Rows()
    tracker = PhaseTracker(model, source, [rows])
    assert tracker.smoother.hyperparameters == ROBUST_PRESETS["srp_phat"]  # the config's live_smoother
    with caplog.at_level(logging.WARNING):
        report = tracker.run()
    window = 23 * 4096
    stops = np.arange(4800, samples.shape[1] + 1, 4800)
    stops = stops[stops >= window]
    spoiled = (stops - window < 28800) & (stops > 24000)
    assert report.skipped_windows == int(spoiled.sum()) > 0
    assert [round(r.timestamp, 3) for r in rows.rows] == [round(s / 48000, 3) for s in stops[~spoiled]]
    assert all(np.isfinite(r.raw).all() for r in rows.rows)


def test_track_cli_with_a_config_and_a_positions_file(quiet_recording, tmp_path, capsys, caplog):
    from scipy.io import wavfile

    from zoo.cli import main

    audio = open_recording(quiet_recording).audio
    wav, mics, wrong = tmp_path / "flight.wav", tmp_path / "mics.txt", tmp_path / "mics3.txt"
    wavfile.write(wav, 48000, audio.read(0, int(2.5 * 48000)).T.copy())
    np.savetxt(mics, audio.mic_positions)
    np.savetxt(wrong, audio.mic_positions[:3])
    config = _small_config(tmp_path)
    assert main(["track", "--config", str(config), "--audio", str(wav), "--mic-positions", str(mics)]) == 0
    captured = capsys.readouterr()
    out = captured.out.strip().splitlines()
    assert "GCC-PHAT frames computed" in captured.err  # the end-of-run report names the phase front end's frames
    assert out[0] == "timestamp,x,y,z,std_x,std_y,std_z,raw_x,raw_y,raw_z,detection_score,detected,state"
    assert len(out) == 1 + 6 and out[1].split(",")[-1] in ("detected", "held", "fallback")
    # channels from nodes on separate clocks (a WAV says nothing of clocks): calibrated from the first 2 s
    with caplog.at_level(logging.INFO):
        assert main(["track", "--config", str(config), "--audio", str(wav), "--mic-positions", str(mics),
                     "--separate-clocks", "--clock-seconds", "2"]) == 0
    assert "nodes on separate clocks: their offsets are estimated from the first 2 s" in caplog.text
    capsys.readouterr()
    miscounted = "3 microphone position(s) for 4 audio channel(s)"
    for args, message in (([], "pass --mic-positions FILE"), (["--mic-positions", str(wrong)], miscounted)):
        assert main(["track", "--config", str(config), "--audio", str(wav), *args]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0]


def test_the_threshold_is_computed_once_per_geometry_and_settings(quiet_recording, tmp_path):
    from zoo.deploy.live_phase import prepare_threshold

    source = RecordingSource(quiet_recording)
    mics = torch.from_numpy(source.mic_positions.astype(np.float32)).double()
    path = tmp_path / "thresholds.json"
    first = load_phase_model(config=CONFIG, source=source).net
    first.null_windows = 10
    prepare_threshold(first, mics, path)
    value = first.known_threshold(mics)
    second = load_phase_model(config=CONFIG, source=source).net
    second.null_windows = 10
    second.threshold = None  # a second computation would fail: the stored value must serve
    prepare_threshold(second, mics, path)
    assert second.known_threshold(mics) == value
    third = load_phase_model(config=CONFIG, source=source).net
    third.null_windows, third.false_alarm = 10, 0.2  # other settings: computed afresh, stored beside
    prepare_threshold(third, mics, path)
    assert third.known_threshold(mics) != value and len(yaml.safe_load(path.read_text())) == 2


def test_phase_student_weights_stream_with_estimate_rows(quiet_recording, tmp_path):
    from zoo.deploy.live_phase import is_phase_model
    from zoo.registry import get_model
    from zoo.weights import save_weights_file

    torch.manual_seed(0)
    weights = save_weights_file(get_model("phase_student", channels=4), tmp_path / "phase_student.pt",
                                net_kwargs={"channels": 4})
    assert is_phase_model(None, None, weights)
    source = RecordingSource(quiet_recording)
    model = load_phase_model(weights=weights, source=source)
    rows = Rows()
    PhaseTracker(model, source, [rows]).run()
    assert len(rows.rows) > 10 and {r.state for r in rows.rows} == {"estimate"}
    assert all(np.isfinite(r.std).all() for r in rows.rows)


def test_an_unknown_live_smoother_preset_is_refused(tmp_path):
    from datamodules.errors import ConfigError

    config = yaml.safe_load(CONFIG.read_text())
    config["model"]["init_args"]["live_smoother"] = {"preset": "no_such_preset"}
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(config))
    mics = tmp_path / "mics.txt"
    np.savetxt(mics, np.array([[1.5, 1.5, 0.2], [-1.5, 1.5, 0.7], [-1.5, -1.5, 1.2], [1.5, -1.5, 1.7]]))
    source = PcmSource(io.BytesIO(b""), 4, 48000.0, "s16le", mic_positions=mics)
    with pytest.raises(ConfigError, match="live_smoother preset 'no_such_preset'"):
        load_phase_model(config=path, source=source)
