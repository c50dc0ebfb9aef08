"""Trajectory metrics of the AAUTE / TAME evaluation code, as a torchmetrics Metric.

Dx, Dy, Dz: mean absolute error per axis; E: mean Euclidean error (all samples, no filtering);
RMSE: root of the mean squared Euclidean error. Metres. Synchronised across DDP processes by
torchmetrics (sums and counts are reduced, then divided).
"""

from __future__ import annotations

import torch
from torchmetrics import Metric

NAMES = ("Dx", "Dy", "Dz", "E", "RMSE")


class TrajectoryError(Metric):
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
