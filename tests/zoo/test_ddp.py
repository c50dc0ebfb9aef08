"""Training under Lightning DDP on two CPU processes (gloo), with metrics synchronised across them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "model" / "student.yaml"
SPLIT = "{train: [sim11-0000-avata], val: [sim11-0001-m300], test: [sim11-0002-mavic2]}"


def _aaute() -> str:
    script = Path(sys.executable).with_name("aaute")
    if not script.exists():
        pytest.skip("the aaute console script is not installed next to this interpreter")
    return str(script)


def _run(args: list[str], cwd: Path) -> None:
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    result = subprocess.run([_aaute(), *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]


def _metrics(root: Path) -> pd.DataFrame:
    files = sorted(root.rglob("metrics.csv"))
    assert files, f"no metrics.csv under {root}"
    return pd.read_csv(files[-1])


@pytest.mark.slow  # two training processes: about 40 s on an idle 2-core machine
def test_ddp_fit_on_two_cpu_processes_synchronises_validation_metrics(labelled_dir, feature_cache, tmp_path):
    common = ["--config", str(CONFIG), "--data.root", str(labelled_dir), "--data.split", SPLIT,
              "--data.window_seconds", "1.0", "--data.batch_size", "4", "--data.cache_dir", str(feature_cache),
              "--trainer.accelerator", "cpu", "--trainer.enable_progress_bar", "false"]
    ddp_root = tmp_path / "ddp"
    _run(["fit", *common, "--trainer.strategy", "ddp", "--trainer.devices", "2", "--trainer.max_epochs", "1",
          "--trainer.limit_train_batches", "2", "--trainer.default_root_dir", str(ddp_root)], tmp_path)
    ddp = _metrics(ddp_root)
    ddp_e = ddp["val_E"].dropna().iloc[-1]
    checkpoint = sorted(ddp_root.rglob("*.ckpt"))[-1]

    single_root = tmp_path / "single"
    _run(["validate", *common, "--trainer.devices", "1", "--ckpt_path", str(checkpoint),
          "--trainer.default_root_dir", str(single_root)], tmp_path)
    single_e = _metrics(single_root)["val_E"].dropna().iloc[-1]
    # 30 validation windows split 15 / 15 between the ranks: the synchronised mean equals the
    # single-process mean over all 30 (an unsynchronised rank would report its own half)
    assert ddp_e == pytest.approx(single_e, rel=1e-5)
