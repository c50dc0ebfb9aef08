"""TrajectoryTask: the one LightningModule that trains and evaluates every zoo network.

Loss (the paper's equation): ``(1 - alpha) * L(P, ground truth) + alpha * L(P, pseudo-label)``,
each term averaged over the samples whose target is valid (alpha = 1: fully self-supervised,
alpha = 0: supervised). L is the squared error by default ('mse': mean over x, y, z), or 'l1' as
in the released code. The network's own auxiliary losses (class, visibility, heat map, ...) are
added, computed against the same kind of target (pseudo-labels when alpha >= 0.5, else ground
truth). A batch where no term has a valid target is skipped and counted, never turned into NaN.

Metrics (:class:`zoo.metrics.TrajectoryMetrics`, named by :class:`zoo.metrics.MetricKey`) are
logged per stage and light condition: ``val_E``, ``val_Dx``, ... (the validation loader),
``test_E_ideal``, ``test_E_dark``, ...; errors against pseudo-labels get a ``_pseudo`` suffix.
``val_loss`` is the training objective on the validation split, so model selection under alpha = 1
never looks at ground truth. At test time predictions are collected per sequence and optionally
smoothed; the writers of :mod:`zoo.callbacks` write them to ``predictions_dir`` (and at predict
time into the recordings under ``predictions_topic``). What the task knows of its DataModule (sequence
names and files, test lights, bird's-eye bounds) is a :class:`zoo.catalog.SequenceCatalog` read at setup.
"""

from __future__ import annotations

import logging
from typing import Any

import lightning as L
import numpy as np
import torch
from torch import nn

from datamodules.errors import ConfigError, NonFiniteLossError
from zoo.callbacks import PredictionCsvWriter, PredictionTopicWriter
from zoo.catalog import CatalogSnapshot, read_catalog
from zoo.metrics import MetricKey, TrajectoryMetrics
from zoo.nets.base import TrajectoryNet
from zoo.registry import get_model

log = logging.getLogger(__name__)

LOSSES = ("mse", "l1")


def position_loss(prediction: torch.Tensor, target: torch.Tensor, kind: str) -> torch.Tensor:
    """Per-sample loss (B,) between predicted and target positions."""
    error = prediction - target
    return (error**2).mean(dim=1) if kind == "mse" else error.abs().mean(dim=1)


class TrajectoryTask(L.LightningModule):
    """Train / evaluate a zoo network on MMAUD windows.

    Args:
        net: registered network name (see ``zoo.registry.list_models``).
        net_kwargs: keyword arguments of the network.
        alpha: weight of the pseudo-label term (1 = self-supervised, 0 = supervised).
        loss: 'mse' (squared error, the paper's equation) or 'l1' (the released code).
        lr, weight_decay, betas: Adam settings (the papers use lr 1e-4, betas (0.9, 0.999)).
        smooth: smooth each test sequence's predictions and report both.
        smoother: keyword arguments of :func:`zoo.smoothing.make_smoother`: ``preset`` (default ``robust``,
            the Student-t state-space smoother; ``paper`` the paper's GP) and that smoother's options.
        predictions_dir: write per-sequence prediction CSVs there at test/predict time
            (:class:`~zoo.callbacks.PredictionCsvWriter`).
        predictions_topic: also store each sequence's predictions in its MCAP recording under this
            topic (e.g. ``/prediction/student``) at predict time (:class:`~zoo.callbacks.PredictionTopicWriter`).
        live_smoother: the online smoother ``aaute track`` uses for this model (``{"preset": name}``, a name of
            :data:`zoo.smoothing.ROBUST_PRESETS`); stored with the model, unused by training and testing.
    """

    def __init__(
        self,
        net: str = "student",
        net_kwargs: dict[str, Any] | None = None,
        alpha: float = 1.0,
        loss: str = "mse",
        lr: float = 1e-4,
        weight_decay: float = 0.0,
        betas: tuple[float, float] = (0.9, 0.999),
        smooth: bool = False,
        smoother: dict[str, Any] | None = None,
        predictions_dir: str | None = None,
        predictions_topic: str | None = None,
        live_smoother: dict[str, Any] | None = None,
    ):
        super().__init__()
        if not 0.0 <= alpha <= 1.0:
            raise ConfigError(f"alpha must lie in [0, 1], got {alpha}")
        if loss not in LOSSES:
            raise ConfigError(f"loss must be one of {LOSSES}, got {loss!r}")
        self.save_hyperparameters()
        self.net: TrajectoryNet = get_model(net, **(net_kwargs or {}))
        self.metrics = nn.ModuleDict()  #: MetricKey.slot -> TrajectoryMetrics
        self._metric_keys: dict[str, MetricKey] = {}
        #: the DataModule's sequences and loaders, read at setup (the defaults without a DataModule)
        self.catalog = CatalogSnapshot()
        self.skipped_batches = 0
        self._checked_inputs = False
        self._predictions: dict[int, list[dict[str, np.ndarray]]] = {}
        #: smoothed test positions of the last test run: loader index -> sequence index -> N x 3
        self.smoothed_predictions: dict[int, dict[int, np.ndarray]] = {}

    # ------------------------------------------------------------------------------ helpers

    def setup(self, stage: str) -> None:
        self.catalog = read_catalog(self.trainer.datamodule if self._trainer is not None else None)
        if self.catalog.bev_bounds is not None:
            self.net.set_bounds(self.catalog.bev_bounds)

    def configure_callbacks(self) -> list[L.Callback]:
        """The prediction writers that ``predictions_dir`` and ``predictions_topic`` ask for."""
        callbacks: list[L.Callback] = []
        if self.hparams.predictions_dir:
            callbacks.append(PredictionCsvWriter(self.hparams.predictions_dir))
        if self.hparams.predictions_topic:
            callbacks.append(PredictionTopicWriter(self.hparams.predictions_topic))
        return callbacks

    @property
    def learns(self) -> bool:
        """Whether the net has trainable parameters (a non-learned net such as ``srp_phat`` has none)."""
        return any(parameter.requires_grad for parameter in self.net.parameters())

    def on_fit_start(self) -> None:
        if not self.learns:  # nothing to train: fit ends at once, the net is ready for test/predict
            log.info("%s has no trainable parameters: fit does nothing; run 'aaute test' with the same config",
                     self.hparams.net)
            self.trainer.should_stop = True

    def _inputs(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        wanted = dict(self.net.inputs)
        missing = sorted(set(wanted) - set(batch))
        if missing:
            raise ConfigError(
                f"model {self.hparams.net!r} needs inputs {wanted}; the batch lacks {missing}: "
                f"set data inputs to {wanted}"
            )
        if not self._checked_inputs:
            try:
                self.net.check_inputs(batch)
            except ConfigError as error:
                every = torch.ones(len(batch["gt"]), dtype=torch.bool) if "gt" in batch else None
                source = f" (batch from {self._where(batch, every)})" if every is not None else ""
                raise ConfigError(f"{error}{source}") from None
            self._checked_inputs = True
        context = [name for name in self.net.context_keys if name in batch]
        return {name: batch[name] for name in (*wanted, *context)}

    def _training_target(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """The target of the auxiliary losses: pseudo-labels if alpha >= 0.5, else ground truth."""
        if self.hparams.alpha >= 0.5:
            return batch["pseudo"], batch["pseudo_valid"]
        return batch["gt"], batch["gt_valid"]

    def objective(self, outputs: dict[str, torch.Tensor], batch: dict[str, torch.Tensor]
                  ) -> tuple[torch.Tensor | None, dict[str, torch.Tensor]]:
        """Total loss and its terms; None when no term has a valid target, or the net has no term to train."""
        alpha, kind = self.hparams.alpha, self.hparams.loss
        terms: dict[str, torch.Tensor] = {}
        if self.net.trains_position:
            position = outputs["position"]
            weighted = []
            for weight, target, valid, name in ((1.0 - alpha, batch["gt"], batch["gt_valid"], "gt"),
                                                (alpha, batch["pseudo"], batch["pseudo_valid"], "pseudo")):
                if weight > 0 and valid.any():
                    value = position_loss(position[valid], target[valid], kind).mean()
                    terms[f"position_{name}"] = value
                    weighted.append(weight * value)
            if not weighted:
                return None, terms
            terms["position"] = torch.stack(weighted).sum()
        target, valid = self._training_target(batch)
        if not self.net.trains_position and not valid.any():
            return None, terms
        terms.update(self.net.auxiliary_losses(outputs, batch, target, valid))
        contributing = [value for name, value in terms.items() if not name.startswith("position_")]
        if not contributing:  # a net with nothing to train (srp_phat) has no objective
            return None, terms
        return sum(contributing), terms

    def _metric(self, key: MetricKey) -> TrajectoryMetrics:
        if key.slot not in self.metrics:
            self.metrics[key.slot] = TrajectoryMetrics().to(self.device)
            self._metric_keys[key.slot] = key
        return self.metrics[key.slot]

    def _log_values(self, key: MetricKey, metric: TrajectoryMetrics) -> None:
        for name, value in metric.compute().items():
            self.log(key.logged_name(name), value.float(), add_dataloader_idx=False)

    def _log_metrics(self, stage: str) -> None:
        for slot, key in self._metric_keys.items():
            if key.stage == stage:
                self._log_values(key, self.metrics[slot])
                self.metrics[slot].reset()

    def _where(self, batch: dict[str, torch.Tensor], rows: torch.Tensor) -> str:
        """The recordings and times of batch ``rows`` (a boolean mask), for error messages."""
        names, paths = self.catalog.sequence_ids, self.catalog.sequence_paths
        found = torch.nonzero(rows).flatten().tolist()
        times: dict[str, list[str]] = {}
        for i in found:
            index = int(batch["sequence"][i]) if "sequence" in batch else -1
            name = names[index] if 0 <= index < len(names) else f"sequence {index}"
            if 0 <= index < len(paths):
                name += f" ({paths[index]})"
            times.setdefault(name, [])
            if "time" in batch and len(times[name]) < 3:
                times[name].append(f"{float(batch['time'][i]):.3f}")
        return "; ".join(f"{name} at t = {', '.join(t)}{' ...' if len(t) == 3 else ''} s" if t else name
                         for name, t in times.items())

    def _check_finite(self, total: torch.Tensor, outputs: dict[str, torch.Tensor], batch: dict[str, torch.Tensor],
                      stage: str) -> None:
        """Raise :class:`NonFiniteLossError` naming the windows behind a NaN or infinite loss."""
        if bool(torch.isfinite(total)):
            return
        total = total.detach()
        for name in ("gt", "pseudo"):
            rows = batch[f"{name}_valid"] & ~torch.isfinite(batch[name]).all(dim=1)
            if rows.any():
                raise NonFiniteLossError(f"{stage} loss is {float(total)}: labelled {name} targets are NaN or "
                                         f"infinite at {self._where(batch, rows)}; expected finite positions")
        for name in self.net.inputs:
            values = batch[name]
            if values.is_floating_point():
                rows = ~torch.isfinite(values.reshape(len(values), -1)).all(dim=1)
                if rows.any():
                    raise NonFiniteLossError(f"{stage} loss is {float(total)}: input {name!r} is NaN or infinite "
                                             f"at {self._where(batch, rows)}; expected finite features")
        rows = ~torch.isfinite(outputs["position"].detach()).all(dim=1)
        cause = f"the network's positions are NaN or infinite at {self._where(batch, rows)}" if rows.any() \
            else "the auxiliary losses are not finite"
        raise NonFiniteLossError(f"{stage} loss is {float(total)} with finite inputs and targets: {cause} "
                                 f"(diverged: lower the learning rate, now {self.hparams.lr:g})")

    # ------------------------------------------------------------------------------ steps

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return self.net(inputs)

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor | None:
        outputs = self.net(self._inputs(batch))
        total, terms = self.objective(outputs, batch)
        if total is None:
            self.skipped_batches += 1
            if self.skipped_batches in (1, 10, 100, 1000):
                log.warning("skipped %d training batch(es) with no valid target", self.skipped_batches)
            return None
        self._check_finite(total, outputs, batch, "training")
        batch_size = len(batch["gt"])
        self.log("train_loss", total, prog_bar=True, batch_size=batch_size)
        for name, value in terms.items():
            self.log(f"train_{name}", value, batch_size=batch_size)
        return total

    def _evaluate(self, batch: dict[str, torch.Tensor], stage: str, dataloader_idx: int) -> dict[str, torch.Tensor]:
        outputs = self.net(self._inputs(batch))
        light = None if stage == "val" else self.catalog.test_light(dataloader_idx)
        position = outputs["position"]
        self._metric(MetricKey(stage, light, "gt")).update(position, batch["gt"], batch["gt_valid"])
        self._metric(MetricKey(stage, light, "pseudo")).update(position, batch["pseudo"], batch["pseudo_valid"])
        return outputs

    def validation_step(self, batch: dict[str, torch.Tensor], batch_idx: int, dataloader_idx: int = 0) -> None:
        outputs = self._evaluate(batch, "val", dataloader_idx)
        total, _ = self.objective(outputs, batch)
        if total is not None:
            self._check_finite(total, outputs, batch, "validation")
            # synchronised: under DDP every rank's checkpoint callback must see the same value
            self.log("val_loss", total, batch_size=len(batch["gt"]), add_dataloader_idx=False, sync_dist=True)

    def on_validation_epoch_end(self) -> None:
        self._log_metrics("val")

    def test_step(self, batch: dict[str, torch.Tensor], batch_idx: int, dataloader_idx: int = 0) -> None:
        outputs = self._evaluate(batch, "test", dataloader_idx)
        self._collect(dataloader_idx, batch, outputs)

    def on_test_epoch_start(self) -> None:
        self._predictions = {}
        self.smoothed_predictions = {}

    def on_test_epoch_end(self) -> None:
        self._log_metrics("test")
        if self.hparams.smooth:
            self._log_smoothed()

    def predict_step(self, batch: dict[str, torch.Tensor], batch_idx: int, dataloader_idx: int = 0) -> dict:
        outputs = self.net(self._inputs(batch))
        self._collect(dataloader_idx, batch, outputs)
        return {"sequence": batch["sequence"], "time": batch["time"], "position": outputs["position"]}

    def on_predict_epoch_start(self) -> None:
        self._predictions = {}

    # ------------------------------------------------------------------------------ predictions

    def _collect(self, dataloader_idx: int, batch: dict[str, torch.Tensor], outputs: dict[str, torch.Tensor]) -> None:
        """Keep a batch's predictions. A net that detects (SRP-PHAT) also gives ``detected`` (B, bool: the
        windows it measured; others held or fell back), ``detection_score`` and ``state``
        (:data:`~zoo.nets.phase.gate.WINDOW_STATES` indices), kept for the prediction files."""
        position = outputs["position"]
        detected = outputs.get("detected")
        collected = {
            "sequence": batch["sequence"].cpu().numpy(),
            "time": batch["time"].cpu().numpy(),
            "position": position.detach().cpu().double().numpy(),
            "gt": batch["gt"].cpu().double().numpy(),
            "gt_valid": batch["gt_valid"].cpu().numpy(),
            "detected": (np.ones(len(position), dtype=bool) if detected is None
                         else detected.detach().cpu().numpy().astype(bool)),
        }
        for key in ("detection_score", "state"):
            if key in outputs:
                collected[key] = outputs[key].detach().cpu().numpy()
        self._predictions.setdefault(dataloader_idx, []).append(collected)

    def collected_loaders(self) -> list[int]:
        """The indices of the loaders this process collected predictions of, in order."""
        return sorted(self._predictions)

    def sequence_predictions(self, dataloader_idx: int = 0) -> dict[int, dict[str, np.ndarray]]:
        """This process's collected predictions of one loader, grouped by sequence and sorted by time."""
        parts = self._predictions.get(dataloader_idx, [])
        if not parts:
            return {}
        merged = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
        result = {}
        for sequence in np.unique(merged["sequence"]):
            rows = merged["sequence"] == sequence
            order = np.argsort(merged["time"][rows], kind="stable")
            result[int(sequence)] = {key: value[rows][order] for key, value in merged.items()}
        return result

    def _log_smoothed(self) -> None:
        from zoo.smoothing import make_smoother, smooth_detected

        smoother = make_smoother(**(self.hparams.smoother or {}))
        for dataloader_idx in self.collected_loaders():
            metric = TrajectoryMetrics().to(self.device)
            kept = self.smoothed_predictions.setdefault(dataloader_idx, {})
            for index, sequence in self.sequence_predictions(dataloader_idx).items():
                smoothed = kept[index] = smooth_detected(smoother, sequence["time"], sequence["position"],
                                                         sequence["detected"])
                metric.update(torch.from_numpy(np.asarray(smoothed)), torch.from_numpy(sequence["gt"]),
                              torch.from_numpy(sequence["gt_valid"]))
            self._log_values(MetricKey("test", self.catalog.test_light(dataloader_idx), "smooth"), metric)

    # ------------------------------------------------------------------------------ optimiser

    def configure_optimizers(self) -> torch.optim.Optimizer | None:
        if not self.learns:
            return None
        # the fused kernel is several times faster than the per-tensor loop on CPU, same update rule
        return torch.optim.Adam(self.parameters(), lr=self.hparams.lr, betas=tuple(self.hparams.betas),
                                weight_decay=self.hparams.weight_decay, fused=True)
