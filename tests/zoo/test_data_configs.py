"""Every data config in ``configs/data/`` trains and tests a model through the CLI, unmodified.

Each config is run from a folder where its own relative paths hold a small recording of its
layout, so the paths, list files and reader options the config names are the ones exercised.
A new data config needs a builder here, or this test fails.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tests.helpers.layouts import make_derived, make_ug2_sequence
from zoo.cli import main

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _simulated(cwd: Path, labelled_dir: Path) -> tuple[str, list[str]]:
    shutil.copytree(labelled_dir, cwd / "demo_out" / "data")
    split = "{train: [sim11-0000-avata], val: [sim11-0001-m300], test: [sim11-0002-mavic2]}"
    return "student", ["--data.split", split]


def _derived(cwd: Path, labelled_dir: Path) -> tuple[str, list[str]]:
    root = cwd / "data" / "Data-M"
    make_derived(root, {"0": 120, "3": 120, "7": 120}, images=False)
    (root / "annotation").mkdir()
    for name, seq in (("train", "0"), ("val", "3"), ("test", "7")):
        (root / "annotation" / f"{name}.txt").write_text("\n".join(f"{seq}/{i}.npy" for i in range(120)) + "\n")
    return "audionet", []


def _ug2(cwd: Path, labelled_dir: Path) -> tuple[str, list[str]]:
    for k in range(6):
        make_ug2_sequence(cwd / "data" / "ug2" / "train" / f"seq{k}", frames=30, class_id=k % 2 + 1, seed=k)
    return "visualnet", []


BUILDERS = {"sim": _simulated, "derived_npy": _derived, "ug2": _ug2}


@pytest.mark.parametrize("config", sorted((CONFIGS / "data").glob("*.yaml")), ids=lambda p: p.stem)
def test_data_config_runs_fit_and_test(config, labelled_dir, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    model, extra = BUILDERS[config.stem](tmp_path, labelled_dir)
    args = ["--config", str(config), "--config", str(CONFIGS / "model" / f"{model}.yaml"), *extra,
            "--data.window_seconds", "0.5", "--data.batch_size", "2", "--data.num_workers", "0",
            "--data.cache_dir", str(tmp_path / "cache"), "--trainer.default_root_dir", str(tmp_path),
            "--trainer.fast_dev_run", "true", "--trainer.enable_progress_bar", "false"]
    assert main(["fit", *args]) == 0
    assert main(["test", *args]) == 0
