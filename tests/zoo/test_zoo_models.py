"""Every registered network and every model config: forward, learning, round trips, the CLI.

Parametrised over ``list_models()`` and ``configs/model/*.yaml``, so a new network or config is
tested without a new test file.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
import yaml

from datamodules.features import phase_recipe
from zoo.cli import main
from zoo.registry import get_model, list_models
from zoo.task import TrajectoryTask

CONFIGS = sorted((Path(__file__).resolve().parents[2] / "configs" / "model").glob("*.yaml"))
#: image models whose fit + test through the CLI takes 15-35 s each; the forward, one-step and
#: state-dict tests still run them in the fast suite
HEAVY_CLI = {"asdnet", "avfdti", "darknet"}
CLI_CONFIGS = [pytest.param(path, marks=pytest.mark.slow) if path.stem in HEAVY_CLI else path for path in CONFIGS]
SPLIT = "{train: [sim11-0000-avata], val: [sim11-0001-m300], test: [sim11-0002-mavic2]}"


def _batch(net, batch_size: int = 2) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(1)
    batch = dict(net.example_inputs(batch_size))
    batch.update(
        gt=torch.rand(batch_size, 3, generator=generator) * torch.tensor([8.0, 20.0, 15.0]),
        gt_valid=torch.ones(batch_size, dtype=torch.bool),
        class_id=torch.arange(batch_size) % 5,
        visible=torch.ones(batch_size),
        time=torch.arange(batch_size, dtype=torch.float64),
        sequence=torch.zeros(batch_size, dtype=torch.long),
    )
    batch["pseudo"], batch["pseudo_valid"] = batch["gt"] + 0.1, batch["gt_valid"].clone()
    return batch


def test_the_zoo_holds_the_papers_models():
    assert set(list_models()) >= {"student", "audionet", "voranet", "asdnet", "avped", "avfdti", "visualnet",
                                  "darknet"}
    with pytest.raises(ValueError, match="unknown model 'bogus'; known models: .*student"):
        get_model("bogus")


@pytest.mark.parametrize("name", list_models())
def test_forward_gives_positions(name):
    torch.manual_seed(0)
    net = get_model(name).eval()
    with torch.no_grad():
        outputs = net(net.example_inputs(2))
    assert tuple(outputs["position"].shape) == (2, 3) and torch.isfinite(outputs["position"]).all()


LEARNED = [name for name in list_models() if get_model(name).category != "non-learned"]


@pytest.mark.parametrize("name", LEARNED)
def test_one_step_lowers_the_loss_on_a_fixed_batch(name):
    torch.manual_seed(0)
    task = TrajectoryTask(name, alpha=0.0, lr=1e-4)
    task.net.train()  # batch statistics in BatchNorm; dropout masks repeat with the seed below
    batch = _batch(task.net)
    optimiser = torch.optim.Adam(task.parameters(), lr=1e-4)

    def loss() -> torch.Tensor:
        torch.manual_seed(1)
        return task.objective(task.net(task._inputs(batch)), batch)[0]

    before = loss()
    optimiser.zero_grad()
    before.backward()
    optimiser.step()
    with torch.no_grad():
        after = loss()
    assert after < before


@pytest.mark.parametrize("name", list_models())
def test_state_dict_round_trip(name):
    torch.manual_seed(0)
    net = get_model(name).eval()
    torch.manual_seed(1)
    other = get_model(name).eval()
    other.load_state_dict(net.state_dict())
    inputs = net.example_inputs(1)
    with torch.no_grad():
        assert torch.equal(net(inputs)["position"], other(inputs)["position"])


def test_task_mixes_ground_truth_and_pseudo_labels_with_alpha():
    torch.manual_seed(0)
    batch = _batch(get_model("student"), 4)
    batch["pseudo"] = batch["gt"] + 1.0
    terms = {}
    for alpha in (0.0, 0.5, 1.0):
        task = TrajectoryTask("student", alpha=alpha)
        task.net.eval()
        torch.manual_seed(0)
        total, terms[alpha] = task.objective(task.net(task._inputs(batch)), batch)
        assert float(total) == pytest.approx(float(terms[alpha]["position"]))
    assert "position_pseudo" not in terms[0.0] and "position_gt" not in terms[1.0]
    assert set(terms[0.5]) >= {"position_gt", "position_pseudo"}


def test_batches_without_valid_targets_are_skipped_not_nan():
    task = TrajectoryTask("student", alpha=1.0)
    batch = _batch(task.net)
    batch["pseudo_valid"][:] = False
    total, _ = task.objective(task.net(task._inputs(batch)), batch)
    assert total is None
    assert task.training_step(batch, 0) is None and task.skipped_batches == 1


def test_missing_inputs_name_what_the_model_needs():
    task = TrajectoryTask("student")
    batch = _batch(task.net)
    del batch["audio_mel"]
    with pytest.raises(ValueError, match="needs inputs .*audio_mel.*aaute"):
        task._inputs(batch)
    wrong = _batch(task.net)
    wrong["audio_mel"] = torch.rand(2, 4, 13, 13)
    with pytest.raises(ValueError, match=r"student needs audio_mel of shape B x 4 x 64 x 64 .*got \(2, 4, 13, 13\)"):
        task._inputs(wrong)


def _short_window(config: Path) -> float:
    """1 s windows keep the round trip fast, longer only where the config's phase recipe reads more."""
    inputs = yaml.safe_load(config.read_text())["data"]["init_args"].get("inputs", {})
    recipe = inputs.get("audio_phase")
    return max(1.0, math.ceil(phase_recipe(recipe).span_seconds)) if recipe else 1.0


@pytest.mark.parametrize("config", CLI_CONFIGS, ids=lambda p: getattr(p, "stem", None))
def test_every_model_config_fits_and_tests_through_the_cli(config, labelled_dir, feature_cache, tmp_path):
    common = ["--config", str(config), "--data.root", str(labelled_dir), "--data.split", SPLIT,
              "--data.window_seconds", str(_short_window(config)), "--data.batch_size", "2",
              "--data.cache_dir", str(feature_cache),
              "--trainer.default_root_dir", str(tmp_path), "--trainer.fast_dev_run", "true",
              "--trainer.enable_progress_bar", "false"]
    assert main(["fit", *common]) == 0
    assert main(["test", *common]) == 0


def test_predict_writes_trajectories_as_csv_and_into_the_recording(labelled_dir, feature_cache, tmp_path):
    import shutil

    import pandas as pd

    from datamodules.formats.mcap_file import read_track

    data = tmp_path / "data"
    shutil.copytree(labelled_dir, data)
    out = tmp_path / "predictions"
    args = ["predict", "--config", str(CONFIGS[0].with_name("student.yaml")), "--data.root", str(data),
            "--data.split", "{test: [sim11-0002-mavic2]}", "--data.test_lights", "[ideal]",
            "--data.window_seconds", "1.0", "--data.cache_dir", str(feature_cache),
            "--model.predictions_dir", str(out), "--model.predictions_topic", "/prediction/student",
            "--trainer.default_root_dir", str(tmp_path), "--trainer.enable_progress_bar", "false"]
    assert main(args) == 0
    table = pd.read_csv(out / "sim11-0002-mavic2_ideal.csv")
    assert list(table.columns) == ["timestamp", "x", "y", "z"] and len(table) == 30
    assert table["timestamp"].is_monotonic_increasing
    stored = read_track(next(data.glob("*0002.mcap")), "/prediction/student")
    assert len(stored) == 30 and abs(stored.xyz - table[["x", "y", "z"]].to_numpy()).max() < 1e-5


def test_smooth_command_writes_std_columns(tmp_path):
    import numpy as np
    import pandas as pd

    t = 1692845357.0 + np.arange(200) * 0.1
    truth = np.column_stack([np.sin(t / 5), np.cos(t / 7), 5 + 0 * t])
    noisy = truth + np.random.default_rng(0).normal(0, 0.5, truth.shape)
    src = tmp_path / "track.csv"
    pd.DataFrame({"timestamp": t, "x": noisy[:, 0], "y": noisy[:, 1], "z": noisy[:, 2]}).to_csv(src, index=False)
    assert main(["smooth", str(src), str(tmp_path / "smooth.csv")]) == 0
    out = pd.read_csv(tmp_path / "smooth.csv")
    assert list(out.columns) == ["timestamp", "x", "y", "z", "std_x", "std_y", "std_z"]
    smoothed_error = np.linalg.norm(out[["x", "y", "z"]].to_numpy() - truth, axis=1).mean()
    assert smoothed_error < 0.5 * np.linalg.norm(noisy - truth, axis=1).mean()
    assert main(["smooth", str(tmp_path / "missing.csv"), str(tmp_path / "never.csv")]) == 2
    assert not (tmp_path / "never.csv").exists()


def test_predict_from_a_checkpoint_keeps_this_runs_output_settings(labelled_dir, feature_cache, tmp_path):
    """A checkpoint's hyperparameters (predictions_dir None) must not override where this run writes."""
    common = ["--config", str(CONFIGS[0].with_name("student.yaml")), "--data.root", str(labelled_dir),
              "--data.split", SPLIT, "--data.window_seconds", "1.0", "--data.cache_dir", str(feature_cache),
              "--trainer.default_root_dir", str(tmp_path), "--trainer.enable_progress_bar", "false"]
    assert main(["fit", *common, "--trainer.max_epochs", "1", "--trainer.limit_train_batches", "1",
                 "--trainer.limit_val_batches", "1"]) == 0
    checkpoint = next(tmp_path.rglob("*.ckpt"))
    out = tmp_path / "predictions"
    assert main(["predict", *common, "--ckpt_path", str(checkpoint), "--model.predictions_dir", str(out),
                 "--data.test_lights", "[ideal]"]) == 0
    assert (out / "sim11-0002-mavic2_ideal.csv").is_file()
