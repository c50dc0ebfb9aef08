"""Trajectory metrics of the AAUTE / TAME evaluation code, as a torchmetrics Metric, and their logged names.

Dx, Dy, Dz: mean absolute error per axis; E: mean Euclidean error (all samples, no filtering);
RMSE: root of the mean squared Euclidean error. Metres. Synchronised across DDP processes by
torchmetrics (sums and counts are reduced, then divided). :class:`MetricKey` says which
accumulator a value comes from and gives the name it is logged under (``val_E``,
``test_E_pseudo_dark``, ``test_E_smooth_ideal``, ...), which results tables read.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torchmetrics import Metric

NAMES = ("Dx", "Dy", "Dz", "E", "RMSE")


@dataclass(frozen=True)
class MetricKey:
    """One accumulator of trajectory metrics: a stage, a test loader's light condition and a reference."""

    stage: str  #: 'val' or 'test'
    light: str | None  #: the test loader's condition; None for validation, whose names carry none
    #: 'gt' (unsuffixed), 'pseudo' (against pseudo-labels) or 'smooth' (smoothed predictions against ground truth)
    reference: str = "gt"

    @property
    def slot(self) -> str:
        """Its key in a ``ModuleDict`` of metrics."""
        return f"{self.stage}|{self.light}|{self.reference}"

    def logged_name(self, name: str) -> str:
        """The logged name of metric ``name`` (one of ``NAMES``): ``<stage>_<name>[_<reference>][_<light>]``."""
        reference = "" if self.reference == "gt" else f"_{self.reference}"
        light = "" if self.light is None else f"_{self.light}"
        return f"{self.stage}_{name}{reference}{light}"


class TrajectoryMetrics(Metric):
    """Accumulates position errors over (prediction, target, valid) batches."""

    full_state_update = False
    higher_is_better = False

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.add_state("abs_sum", default=torch.zeros(3, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("euclid_sum", default=torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("square_sum", default=torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("count", default=torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, prediction: torch.Tensor, target: torch.Tensor, valid: torch.Tensor | None = None) -> None:
        error = (prediction.detach() - target.detach()).to(torch.float64)
        if valid is not None:
            error = error[valid.bool()]
        self.abs_sum += error.abs().sum(dim=0)
        distance = error.norm(dim=1)
        self.euclid_sum += distance.sum()
        self.square_sum += (distance**2).sum()
        self.count += distance.numel()

    def compute(self) -> dict[str, torch.Tensor]:
        n = self.count.clamp(min=1.0)
        per_axis = self.abs_sum / n
        values = (*per_axis, self.euclid_sum / n, torch.sqrt(self.square_sum / n))
        result = dict(zip(NAMES, values, strict=True))
        if self.count == 0:
            result = {name: torch.tensor(float("nan"), dtype=torch.float64) for name in NAMES}
        return result


#: Deprecated alias of :class:`TrajectoryMetrics` (the old name read like an exception); kept for one release.
TrajectoryError = TrajectoryMetrics
