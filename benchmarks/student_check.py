"""Does the student learn? Self-supervised (alpha = 1) vs supervised (alpha = 0) vs a constant.

Trains the AAUTE student on a folder of recordings (which must carry pseudo-labels for
alpha = 1: ``aaute label``), tests on held-out sequences against ground truth, and prints E
(mean Euclidean error, m) next to the constant-position predictor (the training targets' mean)
and a per-axis breakdown. Run: ``python -m benchmarks.student_check --data DIR``.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import lightning as L
import numpy as np
import torch

from datamodules.mmaud import MMAUDDataModule
from zoo.task import TrajectoryTask


def _targets(module: MMAUDDataModule, split: str, kind: str) -> tuple[np.ndarray, np.ndarray]:
    xyz = np.concatenate([getattr(s, kind) for s in module.sequences[split]])
    valid = np.concatenate([getattr(s, f"{kind}_valid") for s in module.sequences[split]])
    return xyz, valid


def constant_error(module: MMAUDDataModule, kind: str) -> float:
    """E on the test split of always predicting the mean training target of ``kind``."""
    train, train_valid = _targets(module, "train", kind)
    test, test_valid = _targets(module, "test", "gt")
    mean = train[train_valid].mean(axis=0)
    return float(np.linalg.norm(test[test_valid] - mean, axis=1).mean())


def run(data: Path, alpha: float, epochs: int, seed: int, cache: Path | None, out: Path) -> dict[str, float]:
    L.seed_everything(seed, workers=True)
    module = MMAUDDataModule(str(data), split={"seed": seed, "val": 0.15, "test": 0.2}, inputs={"audio_mel": "aaute"},
                             test_lights=["ideal"], batch_size=32, cache_dir=None if cache is None else str(cache))
    task = TrajectoryTask("student", alpha=alpha)
    trainer = L.Trainer(max_epochs=epochs, accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, default_root_dir=str(out))
    trainer.fit(task, module)
    metrics = trainer.test(task, module, verbose=False)[0]
    result = {k: float(v) for k, v in metrics.items()}
    result["constant_E"] = constant_error(module, "pseudo" if alpha >= 0.5 else "gt")
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--epochs", type=int, default=30)
    parser.add_argument("--alphas", type=float, nargs="+", default=[1.0, 0.0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=Path("student_check"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(2)
    rows = []
    for alpha in args.alphas:
        result = run(args.data, alpha, args.epochs, args.seed, args.cache, args.out)
        rows.append((alpha, result))
    print(f"{'alpha':>5}  {'E':>6}  {'Dx':>6}  {'Dy':>6}  {'Dz':>6}  {'constant E':>10}")
    for alpha, r in rows:
        print(f"{alpha:5.2f}  {r['test_E_ideal']:6.2f}  {r['test_Dx_ideal']:6.2f}  {r['test_Dy_ideal']:6.2f}  "
              f"{r['test_Dz_ideal']:6.2f}  {r['constant_E']:10.2f}")


if __name__ == "__main__":
    main()
