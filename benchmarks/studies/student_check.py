"""Does the student learn? Self-supervised (alpha = 1) vs supervised (alpha = 0) vs a constant.

Trains the AAUTE student on one or more folders of recordings (which must carry pseudo-labels for
alpha = 1: ``aaute label``), keeps the checkpoint with the lowest ``val_loss`` (the training
objective on the validation sequences, so alpha = 1 never looks at ground truth), tests it on
held-out sequences against ground truth, and prints E (mean Euclidean error, m) next to the
constant-position predictor (the mean training target) with a per-axis breakdown.
Run: ``python -m benchmarks.studies.student_check --data DIR [DIR ...]``.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import ModelCheckpoint

from benchmarks.studies.common import held_out_split
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


def run(data: list[Path], alpha: float, epochs: int, seed: int, cache: Path | None, out: Path,
        recipe: str = "aaute", batch_size: int = 32, split: dict | None = None) -> dict[str, float]:
    """Train, select by ``val_loss``, test; metrics plus ``constant_E``, ``best_epoch``, timings.

    ``split``: the DataModule's split (default: :func:`benchmarks.studies.common.held_out_split`).
    """
    L.seed_everything(seed, workers=True)
    module = MMAUDDataModule([str(d) for d in data], split=split or held_out_split(seed),
                             inputs={"audio_mel": recipe}, test_lights=["ideal"], batch_size=batch_size,
                             cache_dir=None if cache is None else str(cache))
    task = TrajectoryTask("student", alpha=alpha)
    best = ModelCheckpoint(dirpath=out / f"alpha{alpha:g}", monitor="val_loss", mode="min", save_top_k=1,
                           filename="best-{epoch}")
    trainer = L.Trainer(max_epochs=epochs, accelerator="cpu", devices=1, logger=False, callbacks=[best],
                        enable_progress_bar=False, default_root_dir=str(out))
    start = time.perf_counter()
    trainer.fit(task, module)
    seconds = time.perf_counter() - start
    metrics = trainer.test(task, module, ckpt_path="best", verbose=False)[0]
    result = {k: float(v) for k, v in metrics.items()}
    result["constant_E"] = constant_error(module, "pseudo" if alpha >= 0.5 else "gt")
    result["best_epoch"] = float(torch.load(best.best_model_path, map_location="cpu", weights_only=False)["epoch"])
    result["seconds_per_epoch"] = seconds / max(trainer.current_epoch, 1)
    result["train_sequences"] = float(len(module.sequences["train"]))
    result["test_sequences"] = float(len(module.sequences["test"]))
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, nargs="+", required=True, help="one or more folders of recordings")
    parser.add_argument("--epochs", type=int, default=30)
    parser.add_argument("--alphas", type=float, nargs="+", default=[1.0, 0.0])
    parser.add_argument("--recipe", default="aaute", help="mel recipe: aaute (the paper's) or aaute_joint")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=Path("student_check"))
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(args.threads)
    rows = [(alpha, run(args.data, alpha, args.epochs, args.seed, args.cache, args.out, args.recipe))
            for alpha in args.alphas]
    first = rows[0][1]
    print(f"recipe {args.recipe}: {first['train_sequences']:.0f} training and {first['test_sequences']:.0f} test "
          f"sequences, up to {args.epochs} epochs, checkpoint with the lowest val_loss")
    print(f"{'alpha':>5}  {'E':>6}  {'Dx':>6}  {'Dy':>6}  {'Dz':>6}  {'constant E':>10}  {'best epoch':>10}  "
          f"{'s/epoch':>7}")
    for alpha, r in rows:
        print(f"{alpha:5.2f}  {r['test_E_ideal']:6.2f}  {r['test_Dx_ideal']:6.2f}  {r['test_Dy_ideal']:6.2f}  "
              f"{r['test_Dz_ideal']:6.2f}  {r['constant_E']:10.2f}  {r['best_epoch']:10.0f}  "
              f"{r['seconds_per_epoch']:7.1f}")


if __name__ == "__main__":
    main()
