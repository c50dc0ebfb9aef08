"""Writing a run's trajectories: Lightning prediction writers, added by the task for its output settings.

:class:`PredictionCsvWriter` writes ``<predictions_dir>/<sequence id>_<light>.csv`` (``timestamp, x,
y, z``, six decimals, written atomically; a net that detects, SRP-PHAT, adds ``detection_score, detected,
state`` as ``aaute track`` does) for every sequence of every loader at the end of a test or predict
epoch; :class:`PredictionTopicWriter` stores the first loader's trajectories in each sequence's MCAP
recording under a track topic at the end of a predict epoch. Both read what the task collected
(:class:`PredictionSource`), per sequence and sorted by time, and name sequences and loaders by the
task's :class:`~zoo.catalog.CatalogSnapshot`. Under DDP every process writes the sequences it collected
(no rank is singled out).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Protocol

import lightning as L
import numpy as np
from lightning.pytorch.callbacks import BasePredictionWriter

from datamodules.atomic import atomic_write
from zoo.catalog import CatalogSnapshot
from zoo.nets.phase.gate import WINDOW_STATES

log = logging.getLogger(__name__)


class PredictionSource(Protocol):
    """What the writers read from the LightningModule (:class:`~zoo.task.TrajectoryTask` is one)."""

    catalog: CatalogSnapshot

    def collected_loaders(self) -> list[int]:
        """The indices of the loaders with collected predictions, in order."""
        ...

    def sequence_predictions(self, dataloader_idx: int = 0) -> dict[int, dict[str, np.ndarray]]:
        """One loader's predictions: sequence index -> ``time``, ``position`` (N x 3), ... sorted by time."""
        ...


def detection_columns(sequence: dict[str, np.ndarray]) -> dict[str, Any]:
    """``detection_score``, ``detected`` (0 / 1) and ``state`` of a sequence's collected predictions when its net
    detects (SRP-PHAT: the columns ``aaute track`` writes for it), else nothing."""
    if "state" not in sequence:
        return {}
    return {"detection_score": sequence["detection_score"], "detected": sequence["detected"].astype(int),
            "state": [WINDOW_STATES[i] for i in sequence["state"]]}


class PredictionCsvWriter(BasePredictionWriter):
    """One CSV of predicted positions per sequence and light condition, at the end of test and predict.

    Args:
        output_dir: the folder to write to (created if missing).
    """

    def __init__(self, output_dir: str | Path):
        super().__init__(write_interval="epoch")
        self.output_dir = Path(output_dir)

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.write(pl_module, "test")

    def write_on_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, predictions: Sequence[Any],
                           batch_indices: Sequence[Any]) -> None:
        self.write(pl_module, "predict")

    def write(self, source: PredictionSource, stage: str) -> None:
        """Write every collected sequence of ``source`` as ``<sequence id>_<light>.csv``."""
        import pandas as pd

        names = source.catalog.sequence_ids
        out = self.output_dir
        out.mkdir(parents=True, exist_ok=True)
        for dataloader_idx in source.collected_loaders():
            light = source.catalog.test_light(dataloader_idx)
            for index, sequence in source.sequence_predictions(dataloader_idx).items():
                name = names[index] if index < len(names) else f"sequence{index}"
                frame = pd.DataFrame({"timestamp": sequence["time"], "x": sequence["position"][:, 0],
                                      "y": sequence["position"][:, 1], "z": sequence["position"][:, 2]})
                for column, values in detection_columns(sequence).items():
                    frame[column] = values
                with atomic_write(out / f"{name}_{light}.csv") as tmp:
                    frame.to_csv(tmp, index=False, float_format="%.6f")
        log.info("%s predictions written to %s", stage, out)


class PredictionTopicWriter(BasePredictionWriter):
    """The first loader's trajectories stored in each sequence's MCAP recording, at the end of predict.

    Args:
        topic: the track topic to write (e.g. ``/prediction/student``), replacing one of that name.
    """

    def __init__(self, topic: str):
        super().__init__(write_interval="epoch")
        self.topic = topic

    def write_on_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, predictions: Sequence[Any],
                           batch_indices: Sequence[Any]) -> None:
        self.write(pl_module)

    def write(self, source: PredictionSource) -> None:
        """Replace the topic in every recording with a sequence in ``source``'s first loader.

        Raises:
            ValueError: a sequence whose recording is not an MCAP file (or unknown).
        """
        from datamodules.formats.mcap_file import replace_track
        from datamodules.recording import Track

        paths = source.catalog.sequence_paths
        for index, sequence in source.sequence_predictions(0).items():
            path = paths[index] if index < len(paths) else None
            if path is None or Path(path).suffix != ".mcap":
                raise ValueError(f"predictions_topic needs MCAP recordings; sequence {index} is {path}")
            replace_track(path, self.topic, Track(sequence["time"], sequence["position"]))
        log.info("predictions stored under %s in %d recording(s)", self.topic, len(paths))
