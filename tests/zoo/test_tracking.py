"""aaute track: equality with offline predict + causal smoothing, the audio sources, and bad input."""

from __future__ import annotations

import io
import math
import os
import threading

import numpy as np
import pytest
import torch

from datamodules.features import mel_features
from datamodules.formats import open_recording
from datamodules.recording import RecordingError
from datamodules.streams import PcmSource, RecordingSource, StreamError
from zoo.deploy.tracking import Tracker, TrackingError, load_tracking_model


class Rows:
    """A writer that keeps the rows."""

    def __init__(self):
        self.rows = []

    def write(self, row) -> None:
        self.rows.append(row)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return (np.array([r.timestamp for r in self.rows]), np.array([r.mean for r in self.rows]),
                np.array([r.std for r in self.rows]))


@pytest.fixture(scope="module")
def recording_path(simulated_dir):
    return sorted(simulated_dir.glob("*.mcap"))[0]


@pytest.fixture(scope="module")
def student_weights(tmp_path_factory):
    """A student with fixed random weights (seed 0) in a self-describing weights file."""
    from zoo.registry import get_model
    from zoo.weights import save_weights_file

    torch.manual_seed(0)
    net = get_model("student")
    return save_weights_file(net, tmp_path_factory.mktemp("track") / "student_random.pt", net_kwargs={})


@pytest.fixture(scope="module")
def offline_track(recording_path, student_weights, feature_cache):
    """The predict path on the recording's label times (DataModule windows, TrajectoryTask.predict_step),
    then the causal smoother over the whole track."""
    from datamodules.mmaud import MMAUDDataModule
    from zoo.smoothing import smooth_online
    from zoo.weights import load_task

    task = load_task(student_weights)
    data = MMAUDDataModule(root=str(recording_path), split={"test": [recording_path.stem]},
                           inputs={"audio_mel": "aaute"}, cache_dir=str(feature_cache), test_lights=["ideal"])
    data.setup("predict")
    times, positions = [], []
    with torch.no_grad():
        for i, batch in enumerate(data.predict_dataloader()[0]):
            out = task.predict_step(batch, i)
            times.append(out["time"].numpy())
            positions.append(out["position"].double().numpy())
    t, xyz = np.concatenate(times), np.concatenate(positions)
    smoothed = smooth_online(t, xyz, "robust", lag=0.0)
    return smoothed


def _matched(tracked: tuple, offline) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Tracked and offline rows at the same times (within 1 us); every offline time must be tracked."""
    t, mean, std = tracked
    index = np.searchsorted(t, offline.timestamps - 1e-6)
    assert np.all(np.abs(t[index] - offline.timestamps) < 1e-6), "a label time without a tracked position"
    return mean[index], std[index], np.asarray(offline.mean), np.asarray(offline.std)


# ---------------------------------------------------------------------------------------------- equality


@pytest.mark.parametrize("batch", [1, 4])
def test_track_from_mcap_equals_offline_predict_and_causal_smoothing(recording_path, student_weights, offline_track,
                                                                    batch):
    model = load_tracking_model(weights=student_weights)
    assert model.recipe.name == "aaute" and model.window_seconds == 2.0
    rows = Rows()
    report = Tracker(model, RecordingSource(recording_path), [rows], batch=batch).run()
    assert report.updates == len(rows.rows) == 21 and report.skipped_windows == 0
    mean, std, offline_mean, offline_std = _matched(rows.arrays(), offline_track)
    assert np.abs(mean - offline_mean).max() < 1e-4
    assert np.abs(std - offline_std).max() < 1e-4
    assert np.isfinite(report.latencies).all() and report.audio_seconds == pytest.approx(4.0)


def _pcm(recording_path, seconds: float | None = None) -> tuple[bytes, float, float]:
    """The recording's audio as interleaved s16le bytes (exact: the simulator writes S16LE), its rate and t0."""
    audio = open_recording(recording_path).audio
    stop = audio.num_samples if seconds is None else int(seconds * audio.sample_rate)
    samples = audio.read(0, stop).astype(np.float64) * 32768.0
    assert np.array_equal(samples, np.rint(samples))
    return samples.T.astype("<i2").tobytes(), audio.sample_rate, audio.t0


def test_track_from_stdin_pcm_equals_offline(recording_path, student_weights, offline_track):
    data, rate, t0 = _pcm(recording_path)
    model = load_tracking_model(ckpt_path=None, weights=str(student_weights))
    rows = Rows()
    Tracker(model, PcmSource(io.BytesIO(data), 4, rate, "s16le", t0=t0), [rows]).run()
    mean, std, offline_mean, offline_std = _matched(rows.arrays(), offline_track)
    assert np.abs(mean - offline_mean).max() < 1e-4
    assert np.abs(std - offline_std).max() < 1e-4


def test_track_from_wav_equals_offline_and_says_where_mics_come_from(recording_path, student_weights,
                                                                     offline_track, tmp_path):
    from scipy.io import wavfile

    from datamodules.streams import WavSource

    data, rate, t0 = _pcm(recording_path)
    wav = tmp_path / "audio.wav"
    wavfile.write(wav, int(rate), np.frombuffer(data, dtype="<i2").reshape(-1, 4))
    source = WavSource(wav, t0=t0)
    assert "default array 'distributed4'" in source.mic_source and source.mic_positions.shape == (4, 3)
    rows = Rows()
    Tracker(load_tracking_model(weights=student_weights), source, [rows]).run()
    mean, _, offline_mean, _ = _matched(rows.arrays(), offline_track)
    assert np.abs(mean - offline_mean).max() < 1e-4
    assert WavSource(wav, mic_positions=_mics(tmp_path, 4)).mic_source == str(_mics(tmp_path, 4))
    with pytest.raises(RecordingError, match=r"3 microphone position\(s\) for 4 audio channel"):
        WavSource(wav, mic_positions=_mics(tmp_path, 3))


def test_realtime_replay_paces_blocks(recording_path, monkeypatch):
    delays = []
    monkeypatch.setattr("datamodules.streams.time.sleep", delays.append)
    blocks = list(RecordingSource(recording_path, realtime=True).blocks(4800))
    assert len(blocks) == 40 and len(delays) >= 35  # replayed far faster than 0.1 s a block: each one waits
    assert max(delays) <= 4.0 + 1e-6


def test_track_cli_on_stdin_writes_csv_and_reports(recording_path, student_weights, offline_track, tmp_path,
                                                   monkeypatch, capsys):
    from zoo.cli import main

    data, rate, t0 = _pcm(recording_path)
    monkeypatch.setattr("sys.stdin", io.TextIOWrapper(io.BytesIO(data)))
    out = tmp_path / "track.csv"
    code = main(["track", "--weights", str(student_weights), "--audio", "-", "--channels", "4", "--rate",
                 f"{rate:g}", "--format", "s16le", "--t0", repr(t0), "--out", str(out)])
    assert code == 0
    err = capsys.readouterr().err
    assert "updates" in err and "real time" in err and "torch thread" in err and "latency" in err
    table = np.loadtxt(out, delimiter=",", skiprows=1)
    assert out.read_text().splitlines()[0] == "timestamp,x,y,z,std_x,std_y,std_z,raw_x,raw_y,raw_z"
    tracked = (table[:, 0], table[:, 1:4], table[:, 4:7])
    mean, _, offline_mean, _ = _matched(tracked, offline_track)
    assert np.abs(mean - offline_mean).max() < 1e-4  # the CSV's 6 decimals


def test_track_csv_keeps_the_nets_positions_so_aaute_smooth_gives_its_rows_again(recording_path, student_weights,
                                                                                 tmp_path, capsys):
    import pandas as pd

    from zoo.cli import main

    track, again = tmp_path / "track.csv", tmp_path / "again.csv"
    assert main(["track", "--weights", str(student_weights), "--audio", str(recording_path), "--out", str(track),
                 "--lag", "0.5"]) == 0
    rows = pd.read_csv(track)
    assert main(["smooth", str(track), str(again), "--preset", "robust", "--lag", "0.5"]) == 0
    smoothed = pd.read_csv(again)
    assert np.abs(smoothed[["x", "y", "z"]].to_numpy() - rows[["x", "y", "z"]].to_numpy()).max() < 1e-4
    assert np.abs(smoothed[["std_x", "std_y", "std_z"]].to_numpy()
                  - rows[["std_x", "std_y", "std_z"]].to_numpy()).max() < 1e-4
    # the raw columns are the net's positions, not the smoothed ones (a random student moves them apart)
    assert np.abs(rows[["raw_x", "raw_y", "raw_z"]].to_numpy() - rows[["x", "y", "z"]].to_numpy()).max() > 1e-3
    capsys.readouterr()


def test_track_writes_an_mcap_topic(recording_path, student_weights, tmp_path, capsys):
    import json

    from mcap.reader import make_reader

    from zoo.cli import main

    out = tmp_path / "track.mcap"
    assert main(["track", "--weights", str(student_weights), "--audio", str(recording_path), "--mcap-out", str(out),
                 "--topic", "/track/student", "--lag", "0.5"]) == 0
    with open(out, "rb") as handle:
        messages = [json.loads(m.data) for _, _, m in make_reader(handle).iter_messages(topics=["/track/student"])]
    assert len(messages) == 21  # 2.0 ... 4.0 s: the fixed-lag rows flushed at the end too
    assert set(messages[0]) == {"timestamp", "x", "y", "z", "std_x", "std_y", "std_z", "raw_x", "raw_y", "raw_z"}
    assert all(math.isfinite(v) for m in messages for v in m.values())


# ---------------------------------------------------------------------------------------------- bad input


def test_wrong_byte_count_names_channels_and_format(recording_path, student_weights):
    data, rate, _ = _pcm(recording_path, seconds=2.5)
    model = load_tracking_model(weights=student_weights)
    source = PcmSource(io.BytesIO(data[:-6]), 4, rate, "s16le")  # 3 channels' worth short of a frame
    with pytest.raises(StreamError, match="not a whole number of 4-channel s16le frames.*--channels and --format"):
        Tracker(model, source, [Rows()]).run()


def test_integer_audio_read_as_float_is_refused(recording_path, student_weights):
    data, rate, _ = _pcm(recording_path, seconds=2.5)
    model = load_tracking_model(weights=student_weights)
    source = PcmSource(io.BytesIO(data[: len(data) // 16 * 16]), 4, rate, "f32le")
    with pytest.raises(StreamError, match="float32 audio in \\[-1, 1\\].*--format"):
        Tracker(model, source, [Rows()]).run()


def test_stream_ending_mid_block_flushes_what_it_has(recording_path, student_weights, caplog):
    data, rate, _ = _pcm(recording_path, seconds=2.35)
    model = load_tracking_model(weights=student_weights)
    rows = Rows()
    report = Tracker(model, PcmSource(io.BytesIO(data), 4, rate, "s16le"), [rows], lag=1.0).run()
    times = rows.arrays()[0]
    assert np.allclose(times, [2.0, 2.1, 2.2, 2.3])  # the fixed-lag rows still pending were flushed
    assert report.rows == 4 and "0.050 s into a block" in caplog.text


def test_stalled_stream_ends_cleanly(recording_path, student_weights):
    data, rate, _ = _pcm(recording_path, seconds=2.2)
    model = load_tracking_model(weights=student_weights)
    read_end, write_end = os.pipe()
    writer = threading.Thread(target=os.write, args=(write_end, data))
    writer.start()
    try:
        with os.fdopen(read_end, "rb", buffering=0) as stream:
            source = PcmSource(stream, 4, rate, "s16le", stall_timeout=0.3)
            rows = Rows()
            report = Tracker(model, source, [rows]).run()
    finally:
        writer.join()
        os.close(write_end)
    assert source.stalled and "stall" in report.ended
    assert np.allclose(rows.arrays()[0], [2.0, 2.1, 2.2])


def test_nan_block_is_skipped_without_nan_positions(recording_path, student_weights, caplog):
    data, rate, t0 = _pcm(recording_path)
    samples = np.frombuffer(data, dtype="<i2").reshape(-1, 4).astype(np.float32) / 32768.0
    samples[int(2.5 * rate) + 10: int(2.5 * rate) + 20, 1] = np.nan
    model = load_tracking_model(weights=student_weights)
    rows, clean = Rows(), Rows()
    source = PcmSource(io.BytesIO(samples.astype("<f4").tobytes()), 4, rate, "f32le", t0=t0)
    report = Tracker(model, source, [rows]).run()
    Tracker(model, PcmSource(io.BytesIO(data), 4, rate, "s16le"), [clean]).run()
    times, mean, std = rows.arrays()
    assert np.isfinite(mean).all() and np.isfinite(std).all()
    # every window holding the block 2.5-2.6 s (those ending 2.6 ... 4.5 s) is skipped; the recording ends at 4 s
    assert np.allclose(times - t0, [2.0, 2.1, 2.2, 2.3, 2.4, 2.5])
    assert report.skipped_windows == 15 and "NaN or infinite" in caplog.text
    assert np.allclose(mean[:6], clean.arrays()[1][:6], atol=1e-9, rtol=0)  # causal: rows before the block stay


def test_too_short_stream_is_an_error(recording_path, student_weights):
    data, rate, _ = _pcm(recording_path, seconds=1.5)
    model = load_tracking_model(weights=student_weights)
    with pytest.raises(TrackingError, match="1.50 s of audio, fewer than the 2 s window"):
        Tracker(model, PcmSource(io.BytesIO(data), 4, rate, "s16le"), [Rows()]).run()


def test_wrong_channel_count_and_unstreamable_models_are_refused(recording_path, student_weights, tmp_path):
    from zoo.registry import get_model
    from zoo.weights import save_weights_file

    model = load_tracking_model(weights=student_weights)
    with pytest.raises(TrackingError, match="6 audio channels, but model 'student' takes 4"):
        Tracker(model, PcmSource(io.BytesIO(b""), 6, 48000.0, "s16le", mic_positions=_mics(tmp_path, 6)), [])
    phase = save_weights_file(get_model("phase_student"), tmp_path / "phase.pt", net_kwargs={})
    with pytest.raises(TrackingError, match="model 'phase_student' reads .*audio_mel recipes aaute"):
        load_tracking_model(weights=phase)


def _mics(tmp_path, channels: int):
    path = tmp_path / f"mics{channels}.txt"
    np.savetxt(path, np.arange(3 * channels, dtype=float).reshape(channels, 3))
    return path


def test_cli_errors_are_one_line(student_weights, capsys, monkeypatch):
    from zoo.cli import main

    monkeypatch.setattr("sys.stdin", io.TextIOWrapper(io.BytesIO(b"\x00" * 7)))
    code = main(["track", "--weights", str(student_weights), "--audio", "-", "--channels", "4", "--rate", "48000"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "7 bytes is not a whole number" in err[0]


def test_checkpoint_gives_the_recipe_and_window_of_its_data(student_weights, tmp_path):
    """A Lightning checkpoint of aaute fit: net and weights from its task, recipe and window from its DataModule."""
    from zoo.weights.files import read_checkpoint

    state = read_checkpoint(student_weights).state_dict
    checkpoint = {"state_dict": {f"net.{key}": value for key, value in state.items()},
                  "hyper_parameters": {"net": "student", "net_kwargs": {}, "alpha": 1.0},
                  "datamodule_hyper_parameters": {"inputs": {"audio_mel": "aaute_joint"}, "window_seconds": 2.0}}
    path = tmp_path / "student.ckpt"
    torch.save(checkpoint, path)
    model = load_tracking_model(ckpt_path=path)
    assert (model.name, model.recipe.name, model.window_seconds) == ("student", "aaute_joint", 2.0)
    assert load_tracking_model(ckpt_path=path, recipe="aaute").recipe.name == "aaute"
    with pytest.raises(TrackingError, match="recipe 'avfdti_13' makes \\(13, 13\\)"):
        load_tracking_model(ckpt_path=path, recipe="avfdti_13")


def test_audionet_streams_its_own_recipe(recording_path, tmp_path):
    from datamodules.features import audio_window
    from zoo.registry import get_model
    from zoo.weights import save_weights_file

    torch.manual_seed(1)
    weights = save_weights_file(get_model("audionet"), tmp_path / "audionet.pt", net_kwargs={})
    model = load_tracking_model(weights=weights)
    assert model.recipe.name == "avfdti"
    rows = Rows()
    Tracker(model, RecordingSource(recording_path), [rows]).run()
    assert len(rows.rows) == 21
    # the first row is the net on the offline features of the first window (the filter starts at the frame)
    audio = open_recording(recording_path).audio
    features = mel_features(audio_window(audio, audio.t0 + 2.0, model.recipe, 2.0), audio.sample_rate, model.recipe)
    with torch.no_grad():
        first = model.net({"audio_mel": features[None]})["position"][0].double().numpy()
    assert np.abs(rows.rows[0].mean - first).max() < 1e-4


def test_interrupt_ends_the_run_cleanly(recording_path, student_weights):
    class Interrupted(RecordingSource):
        def blocks(self, size):
            for i, block in enumerate(super().blocks(size)):
                if i == 25:
                    raise KeyboardInterrupt
                yield block

    rows = Rows()
    report = Tracker(load_tracking_model(weights=student_weights), Interrupted(recording_path), [rows], lag=0.3).run()
    assert report.ended == "an interrupt" and len(rows.rows) == 6  # 2.0 ... 2.5 s, the lagged ones flushed


def test_csv_lines_are_flushed_one_by_one():
    from zoo.deploy.tracking import CsvWriter
    from zoo.smoothing import OnlineRow

    class Counting(io.StringIO):
        flushes = 0

        def flush(self):
            self.flushes += 1
            super().flush()

    stream = Counting()
    writer = CsvWriter(stream)
    for k in range(3):
        writer.write(OnlineRow(2.0 + k / 10, np.array([1.0, 2.0, 3.0]), np.array([0.1, 0.2, 0.3]), 1.0,
                               np.array([1.5, 2.5, 3.5])))
        assert stream.flushes == k + 2 and stream.getvalue().count("\n") == k + 2  # header, then each row at once
    assert stream.getvalue().splitlines()[1] == ("2.000000,1.000000,2.000000,3.000000,0.100000,0.200000,0.300000,"
                                                 "1.500000,2.500000,3.500000")


def _checkpoint(student_weights, path, **stored):
    """A Lightning checkpoint of the student with ``stored`` added (DataModule settings and state)."""
    from zoo.weights.files import read_checkpoint

    state = read_checkpoint(student_weights).state_dict
    torch.save({"state_dict": {f"net.{key}": value for key, value in state.items()},
                "hyper_parameters": {"net": "student", "net_kwargs": {}, "alpha": 1.0}, **stored}, path)
    return path


def test_audio_at_another_rate_than_the_models_is_refused(student_weights, tmp_path, capsys, monkeypatch):
    from scipy.io import wavfile

    from zoo.cli import main

    ckpt = _checkpoint(student_weights, tmp_path / "student.ckpt", MMAUDDataModule={"audio_sample_rates": [48000.0]})
    wav = tmp_path / "phone.wav"
    wavfile.write(wav, 16000, np.zeros((16000 * 3, 4), dtype=np.int16))  # 16 kHz for a model of 48 kHz audio
    out = tmp_path / "track.csv"
    exported = tmp_path / "exported"
    assert main(["export", "--weights", str(ckpt), "--out", str(exported), "--no-onnx"]) == 0  # carries the rate
    capsys.readouterr()
    for model in (["--ckpt_path", str(ckpt)], ["--weights", str(ckpt)], ["--weights", str(exported) + ".pt"]):
        code = main(["track", *model, "--audio", str(wav), "--out", str(out)])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and not out.exists()
        assert f"{wav}: audio at 16000 Hz, but model 'student' was trained on 48000 Hz audio" in err[0]
    monkeypatch.setattr("sys.stdin", io.TextIOWrapper(io.BytesIO(b"\x00" * 8 * 48200 * 3)))
    code = main(["track", "--ckpt_path", str(ckpt), "--audio", "-", "--channels", "4", "--rate", "48200"])
    assert code == 0  # within 1 %: a sound card's clock


def test_the_expected_rate_comes_from_the_training_data_its_reader_or_the_recipe(student_weights, tmp_path,
                                                                              recording_path):
    from datamodules.mmaud import MMAUDDataModule

    data = MMAUDDataModule(root=str(recording_path), split={"test": [recording_path.stem]}, inputs={},
                           test_lights=["ideal"])
    data.prepare_data()
    assert data.state_dict() == {"audio_sample_rates": [48000.0]}  # what Lightning keeps in checkpoints
    read_at = _checkpoint(student_weights, tmp_path / "a.ckpt",
                          datamodule_hyper_parameters={"reader_options": {"sample_rate": 46080}})
    assert load_tracking_model(ckpt_path=read_at).sample_rate == 46080
    assert load_tracking_model(weights=student_weights).sample_rate is None  # the aaute recipe takes any rate
    assert load_tracking_model(weights=student_weights, recipe="avfdti").sample_rate == 48000
