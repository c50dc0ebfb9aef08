"""The zoo's commands with bad input (training; ``smooth`` asked to write over a file): one line naming the cause
and exit code 2, never a traceback; a NaN loss is never trained on silently. Each training case is a row: what
to change, the words the line must hold."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.cli import main
from datamodules.errors import ConfigError, NonFiniteLossError
from datamodules.formats import open_recording
from datamodules.formats.mcap_file import write_mcap
from datamodules.recording import ArrayAudio, ArrayPointClouds
from zoo.task import TrajectoryTask

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "model" / "student.yaml"
SPLIT = "{train: [sim11-0000-avata], val: [sim11-0001-m300], test: [sim11-0002-mavic2]}"


def tree_hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def rewrite_audio(folder: Path, change) -> None:
    """Rewrite every recording of ``folder`` with its audio replaced by ``change(audio)`` (None: no audio)."""
    for path in sorted(folder.glob("*.mcap")):
        rec = open_recording(path)
        audio = rec.audio
        rec.audio = change(ArrayAudio(audio.read(0, audio.num_samples), audio.sample_rate, audio.t0,
                                      audio.mic_positions, audio.sample_format))
        rec.lidar = {s: ArrayPointClouds(c.timestamps, [c[i] for i in range(len(c))]) for s, c in rec.lidar.items()}
        rec.frames = None
        write_mcap(rec, path, overwrite=True)


def no_audio(audio):
    return None


def three_channels(audio):
    return ArrayAudio(audio.samples[:3], audio.sample_rate, audio.t0, audio.mic_positions[:3], audio.sample_format)


#: (id, change to the data or None, extra arguments (DATA: the data folder), words of the one line)
CASES = [
    ("unknown_net", None, ["--model.net", "bogus"], ["unknown model 'bogus'", "known models:", "student"]),
    ("alpha_outside", None, ["--model.alpha", "3"], ["alpha must lie in [0, 1], got 3"]),
    ("unknown_net_argument", None, ["--model.net_kwargs", "{widths: 3}"],
     ["model 'student'", "unexpected keyword argument 'widths'", "its arguments: in_channels"]),
    ("missing_checkpoint", None, ["--ckpt_path", "DATA/missing.ckpt"], ["missing.ckpt", "not found"]),
    ("empty_split", None, ["--data.split", "{train: [nope]}"], ["not found", "nope"]),
    ("missing_data", None, ["--data.root", "DATA/nowhere"], ["nowhere", "no such file or directory"]),
    ("no_audio", no_audio, [], ["sim11_0000.mcap", "needs audio", "has none"]),
    ("three_channels", three_channels, [],
     ["needs audio_mel of shape B x 4 x 64 x 64", "got (", ", 3, 64, 64)", "sim11_0000.mcap"]),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_fit_with_bad_input_prints_one_line(case, labelled_dir, tmp_path, capsys):
    _, change, extra, words = case
    data = tmp_path / "data"
    shutil.copytree(labelled_dir, data)
    if change is not None:
        rewrite_audio(data, change)
    before = tree_hashes(data)
    args = ["fit", "--config", str(CONFIG), "--data.root", str(data), "--data.split", SPLIT,
            "--data.window_seconds", "1.0", "--data.cache_dir", str(tmp_path / "cache"),
            "--trainer.default_root_dir", str(tmp_path / "runs"), "--trainer.fast_dev_run", "true",
            "--trainer.enable_progress_bar", "false", *[w.replace("DATA", str(data)) for w in extra]]
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("aaute: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    for word in words:
        assert word in lines[0], (word, lines[0])
    assert tree_hashes(data) == before


def test_debug_shows_the_training_commands_traceback(labelled_dir, tmp_path):
    args = ["fit", "--config", str(CONFIG), "--data.root", str(labelled_dir), "--model.net", "bogus",
            "--trainer.default_root_dir", str(tmp_path), "--debug"]
    with pytest.raises(ConfigError, match="unknown model 'bogus'"):
        main(args)


def _batch(task: TrajectoryTask, batch_size: int = 3) -> dict[str, torch.Tensor]:
    batch = dict(task.net.example_inputs(batch_size))
    batch.update(gt=torch.rand(batch_size, 3) * 10, gt_valid=torch.ones(batch_size, dtype=torch.bool),
                 pseudo=torch.rand(batch_size, 3) * 10, pseudo_valid=torch.ones(batch_size, dtype=torch.bool),
                 time=1692845357.0 + torch.arange(batch_size, dtype=torch.float64),
                 sequence=torch.tensor([0, 0, 1])[:batch_size], class_id=torch.zeros(batch_size, dtype=torch.long),
                 visible=torch.ones(batch_size))
    return batch


@pytest.mark.parametrize(("what", "words"), [
    ("gt", ["training loss is nan", "labelled gt targets are NaN", "sequence 0 at t = 1692845358.000 s"]),
    ("input", ["input 'audio_mel' is NaN or infinite", "sequence 1 at t = 1692845359.000 s"]),
    ("weights", ["with finite inputs and targets", "network's positions are NaN", "lower the learning rate"]),
])
def test_a_nan_training_loss_raises_naming_the_windows(what, words):
    task = TrajectoryTask("student", alpha=0.0)
    batch = _batch(task)
    if what == "gt":
        batch["gt"][1] = float("nan")
    elif what == "input":
        batch["audio_mel"][2] = float("nan")
    else:
        with torch.no_grad():
            next(task.net.parameters()).fill_(float("nan"))
    with pytest.raises(NonFiniteLossError) as raised:
        task.training_step(batch, 0)
    for word in words:
        assert word in str(raised.value), (word, str(raised.value))


def test_invalid_nan_targets_are_masked_not_trained_on():
    task = TrajectoryTask("student", alpha=0.0)
    batch = _batch(task)
    batch["gt"][1] = float("nan")
    batch["gt_valid"][1] = False  # a missing label: masked out of the loss
    outputs = task.net(task._inputs(batch))
    loss, _ = task.objective(outputs, batch)
    assert loss is not None and np.isfinite(float(loss))
    task._check_finite(loss, outputs, batch, "training")  # no error


def test_smooth_never_writes_over_its_input_and_asks_before_replacing(tmp_path, capsys):
    t = 1692845357.0 + np.arange(50) * 0.1
    src = tmp_path / "track.csv"
    src.write_text("timestamp,x,y,z\n" + "".join(f"{v:.3f},1,2,3\n" for v in t))
    before = tree_hashes(tmp_path)
    assert main(["smooth", str(src), str(src)]) == 2
    assert main(["smooth", str(src), str(src), "--overwrite"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and all("the output is the input" in line and "track.csv" in line for line in err)
    dst = tmp_path / "smoothed.csv"
    dst.write_text("keep me\n")
    before = tree_hashes(tmp_path)
    assert main(["smooth", str(src), str(dst)]) == 2
    assert "smoothed.csv already exists; refusing to overwrite it (use --overwrite)" in capsys.readouterr().err
    assert tree_hashes(tmp_path) == before
    assert main(["smooth", str(src), str(dst), "--overwrite"]) == 0
    assert dst.read_text().startswith("timestamp,x,y,z,std_x")


def test_smooth_on_a_benchmark_predictions_file_smooths_each_flight_and_light_apart(tmp_path, capsys):
    import pandas as pd

    rng = np.random.default_rng(0)
    t = 100.0 + np.arange(40) * 0.1
    parts = []
    for sequence_id, offset in (("sim0_0001", 0.0), ("sim0_0002", 50.0)):
        for light, shift in (("ideal", 0.0), ("dark", 20.0)):  # the same times in both lights
            xyz = offset + shift + rng.normal(0, 0.5, (t.size, 3))
            parts.append(pd.DataFrame({"sequence_id": sequence_id, "recording_id": sequence_id, "drone": "avata",
                                       "light": light, "timestamp": t, "x": xyz[:, 0], "y": xyz[:, 1],
                                       "z": xyz[:, 2]}))
    predictions = pd.concat(parts, ignore_index=True)
    src = tmp_path / "predictions.csv"
    predictions.to_csv(src, index=False)
    dst = tmp_path / "smoothed.csv"
    assert main(["smooth", str(src), str(dst)]) == 0
    out = pd.read_csv(dst)
    assert list(out.columns[:3]) == ["sequence_id", "light", "timestamp"] and len(out) == len(predictions)
    for (sequence_id, light), rows in predictions.groupby(["sequence_id", "light"]):
        alone = tmp_path / f"{sequence_id}_{light}.csv"
        rows[["timestamp", "x", "y", "z"]].to_csv(alone, index=False)
        assert main(["smooth", str(alone), str(tmp_path / f"{sequence_id}_{light}_smoothed.csv")]) == 0
        expected = pd.read_csv(tmp_path / f"{sequence_id}_{light}_smoothed.csv")
        got = out[(out["sequence_id"] == sequence_id) & (out["light"] == light)]
        np.testing.assert_allclose(got[["x", "y", "z", "std_x"]].to_numpy(), expected[["x", "y", "z", "std_x"]])
    capsys.readouterr()

    plain = tmp_path / "fused.csv"  # the same rows without the columns that tell the tracks apart
    predictions[["timestamp", "x", "y", "z"]].to_csv(plain, index=False)
    assert main(["smooth", str(plain), str(tmp_path / "fused_smoothed.csv")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "fused.csv: timestamp 100.0 repeated on data row 41" in err[0]
    assert "need the columns sequence_id, light" in err[0]
    twice = predictions.iloc[[0, 1, 1, 2]]
    twice.to_csv(src, index=False)
    assert main(["smooth", str(src), str(dst), "--overwrite"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "repeated on data row 3 in track sequence_id=sim0_0001, light=ideal" in err[0]


def test_fit_on_a_folder_of_one_recording_says_which_split_is_empty_in_plain_words(labelled_dir, tmp_path, capsys):
    data = tmp_path / "data"
    data.mkdir()
    first = sorted(labelled_dir.glob("*.mcap"))[0]
    shutil.copy(first, data / first.name)
    args = ["fit", "--config", str(CONFIG), "--data.root", str(data), "--data.split", "{protocol: by_sequence}",
            "--data.window_seconds", "1.0", "--data.cache_dir", str(tmp_path / "cache"),
            "--trainer.default_root_dir", str(tmp_path / "runs"), "--trainer.fast_dev_run", "true",
            "--trainer.enable_progress_bar", "false"]
    assert main(args) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("aaute: error:")]
    assert len(lines) == 1 and lines[0].startswith("aaute: error: cannot fit: split"), lines
    assert "TrainerFn" not in lines[0]


def test_the_command_keeps_third_party_deprecation_noise_off_the_console(tmp_path):
    import os
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[2]
    src = tmp_path / "track.csv"
    src.write_text("timestamp,x,y,z\n" + "".join(f"{100 + 0.1 * i:.1f},1,2,3\n" for i in range(20)))
    env = {key: value for key, value in os.environ.items() if key not in ("PYTHONWARNINGS", "AAUTE_DEBUG")}
    env["PYTHONPATH"] = str(repo)
    done = subprocess.run([sys.executable, "-m", "benchmarks.cli", "smooth", str(src), str(tmp_path / "out.csv")],
                          capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "Warning" not in done.stderr and "deprecated" not in done.stderr, done.stderr  # gpytorch's torch.jit
    assert done.stderr.startswith("INFO aaute: smoothed 20 points")


def _detecting_track(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A detecting localiser's track (``srp_phat``'s ``aaute predict`` CSV) of a drone flying a straight line:
    detections near it, a gap held at the last detection and a stretch fallen back to a far centre."""
    import pandas as pd

    t = 100.0 + np.arange(120) * 0.1
    truth = np.stack([np.linspace(0, 6, t.size), np.full(t.size, 15.0), np.full(t.size, 10.0)], axis=1)
    raw = truth + np.random.default_rng(1).normal(0, 0.3, truth.shape)
    state = np.array(["detected"] * t.size, dtype=object)
    state[40:55] = "held"
    raw[40:55] = raw[39]
    state[90:110] = "fallback"
    raw[90:110] = [3.0, 10.0, 12.75]
    detected = (state == "detected").astype(int)
    score = np.where(detected == 1, 3.0, 0.6)
    pd.DataFrame({"timestamp": t, "x": raw[:, 0], "y": raw[:, 1], "z": raw[:, 2], "detection_score": score,
                  "detected": detected, "state": state}).to_csv(path, index=False)
    return t, truth


def test_smooth_bridges_a_detecting_localisers_held_and_fallback_rows_from_its_detections(tmp_path, capsys):
    import pandas as pd

    from zoo.smoothing import make_smoother, smooth_detected

    src = tmp_path / "sim0_0012_ideal.csv"
    t, truth = _detecting_track(src)
    table = pd.read_csv(src)
    plain = tmp_path / "plain.csv"
    table[["timestamp", "x", "y", "z"]].to_csv(plain, index=False)
    assert main(["smooth", str(src), str(tmp_path / "gated.csv"), "--preset", "tuned", "--horizon", "3"]) == 0
    assert main(["smooth", str(plain), str(tmp_path / "all.csv"), "--preset", "tuned", "--horizon", "3"]) == 0
    gated, every = pd.read_csv(tmp_path / "gated.csv"), pd.read_csv(tmp_path / "all.csv")
    xyz = table[["x", "y", "z"]].to_numpy()
    expected = smooth_detected(make_smoother("tuned", horizon=3.0), t, xyz, table["detected"].to_numpy(bool))
    np.testing.assert_allclose(gated[["x", "y", "z"]].to_numpy(), expected, atol=1e-6)  # as aaute test does it
    fallen = slice(90, 110)
    error = {name: np.linalg.norm(out[["x", "y", "z"]].to_numpy()[fallen] - truth[fallen], axis=1).mean()
             for name, out in (("gated", gated), ("every", every))}
    assert error["gated"] < 1.0 < error["every"]  # the fallback centre is no measurement to follow
    flags_only = tmp_path / "flags.csv"  # any track that says which rows were measured
    table[["timestamp", "x", "y", "z", "detected"]].to_csv(flags_only, index=False)
    assert main(["smooth", str(flags_only), str(tmp_path / "flags_out.csv"), "--preset", "tuned",
                 "--horizon", "3"]) == 0
    np.testing.assert_allclose(pd.read_csv(tmp_path / "flags_out.csv")[["x", "y", "z"]], gated[["x", "y", "z"]])

    assert main(["smooth", str(src), str(tmp_path / "live.csv"), "--preset", "srp_phat", "--lag", "1"]) == 0
    live = pd.read_csv(tmp_path / "live.csv")
    assert np.isnan(live["std_x"].to_numpy()[fallen]).all()  # aaute track's fallback rows: own position, no std
    np.testing.assert_allclose(live[["x", "y", "z"]].to_numpy()[fallen], xyz[fallen])
    assert np.isfinite(live["std_x"].to_numpy()[:90]).all()

    table["detected"] = table["detected"].astype(str)
    table.loc[7, "detected"] = "yes"
    table.to_csv(src, index=False)
    capsys.readouterr()
    assert main(["smooth", str(src), str(tmp_path / "never.csv")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "sim0_0012_ideal.csv: column 'detected' is not 0 or 1 on data row 8: 'yes'" in err[0]
    assert not (tmp_path / "never.csv").exists()
