"""Building blocks shared by several zoo networks (layer specifications from the published code).

- :class:`FourBranchAudio`: the AV-FDTI / AV-PedAware / AAUTE audio encoder: four parallel
  convolutions over the whole mel x time map of a C x 64 x 64 spectrogram, two narrow in mel and
  spanning all time frames (3 x 64, 5 x 64) and two spanning all mel bins (64 x 3, 64 x 5), each with
  ReLU and channel dropout, concatenated (244 k features for k filters) and projected to d.
- :class:`VisualEncoder`: a torchvision ResNet-50 trunk (2048 x 8 x 8 at 256 x 256), two 3 x 3
  convolutions (2048 -> 256 -> 32) and a projection of the 2048 flattened values to d. The whole
  ResNet-50 is kept as a sub-module, as in the original, so its unused classifier is part of the
  parameter total and the authors' checkpoints map one to one. Other image sizes (the reduced-budget
  recipes) are brought to the reference 8 x 8 grid before the projection, with the same parameters.
- :class:`MLP` and :class:`DetectNet` (position 3, class 6 and a 10-step trajectory head).
- :class:`VisibilityGate`: a softmax over [audio, visual] tokens from a "drone visible" MLP on the
  visual feature, whose weighted sum is the fused feature (AV-PED, AV-FDTI).
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn
from torch.nn import functional as F

from zoo.nets.base import NUM_CLASSES


class FourBranchAudio(nn.Module):
    """Full-axis convolutions over a C x 64 x 64 mel map -> d features."""

    size = 64

    def __init__(self, in_channels: int = 4, kernels: int = 16, feature_dim: int = 512, dropout: float = 0.3):
        super().__init__()
        n = self.size
        self.branches = nn.ModuleList(
            nn.Sequential(nn.Conv2d(in_channels, kernels, kernel_size=k), nn.ReLU(), nn.Dropout2d(dropout))
            for k in ((3, n), (5, n), (n, 3), (n, 5))
        )
        self.features = kernels * ((n - 2) + (n - 4) + (n - 2) + (n - 4))  # 244 k
        self.project = nn.Sequential(nn.Linear(self.features, feature_dim), nn.ReLU())

    def forward(self, mel: torch.Tensor) -> torch.Tensor:
        if mel.shape[-2:] != (self.size, self.size):
            raise ValueError(f"the four-branch audio encoder needs {self.size} x {self.size} mel maps, "
                             f"got {tuple(mel.shape[-2:])}")
        return self.project(torch.cat([branch(mel).flatten(1) for branch in self.branches], dim=1))


def resnet50(weights: str | Path | None = None) -> nn.Module:
    """torchvision ResNet-50, optionally initialised from a local state-dict file (never downloaded)."""
    from torchvision.models import resnet50 as build

    model = build(weights=None)
    if weights is not None:
        path = Path(weights)
        if not path.is_file():
            raise FileNotFoundError(f"ResNet-50 weights file {path} not found (no weights are downloaded)")
        state = torch.load(path, map_location="cpu", weights_only=True)
        model.load_state_dict(state)
    return model


class VisualEncoder(nn.Module):
    """ResNet-50 trunk + conv 2048->256 + conv 256->32 + FC 2048->d (reference: an image of 3 x 256 x 256).

    The trunk's stride is 32, so a 256 x 256 image gives the 32 x 8 x 8 map whose 2048 values the FC
    reads. Another image size (a reduced-budget recipe such as ``resnet64``: a 2 x 2 map) is brought to
    that 8 x 8 grid first, so the parameters, and a checkpoint, are the same at every size:

    - a map smaller than 8 x 8 in both axes is upsampled by **nearest** neighbour: every reference cell
      gets the feature of the reduced cell that covers the same part of the image (at the power-of-two
      sizes an exact block copy), so each FC weight keeps looking at the image region it was trained on,
      and no values between cells are invented (bilinear would blend neighbouring regions);
    - any other map (larger in an axis) is **adaptive-average pooled**: every reference cell averages
      the cells covering its part of the image.

    At 8 x 8 (256 x 256 images) neither runs: the reference path is unchanged, op for op.
    """

    grid = (8, 8)  #: the reference map size the projection reads

    def __init__(self, feature_dim: int = 256, resnet_weights: str | None = None):
        super().__init__()
        self.resnet = resnet50(resnet_weights)
        self.reduce = nn.Sequential(
            nn.Conv2d(2048, 256, 3, padding=1), nn.ReLU(), nn.Conv2d(256, 32, 3, padding=1), nn.ReLU()
        )
        self.project = nn.Sequential(nn.Linear(32 * self.grid[0] * self.grid[1], feature_dim), nn.ReLU())

    def trunk(self, image: torch.Tensor) -> torch.Tensor:
        r = self.resnet
        x = r.maxpool(r.relu(r.bn1(r.conv1(image))))
        return r.layer4(r.layer3(r.layer2(r.layer1(x))))

    def to_grid(self, features: torch.Tensor) -> torch.Tensor:
        """B x 32 x h x w -> B x 32 x 8 x 8 (see the class docstring); the reference map is returned as is."""
        size = tuple(features.shape[-2:])
        if size == self.grid:
            return features
        if size[0] <= self.grid[0] and size[1] <= self.grid[1]:
            return F.interpolate(features, size=self.grid, mode="nearest")
        return F.adaptive_avg_pool2d(features, self.grid)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.project(self.to_grid(self.reduce(self.trunk(image))).flatten(1))


class MLP(nn.Sequential):
    """Linear layers with ReLU between them (none after the last)."""

    def __init__(self, sizes: tuple[int, ...], dropout_before_last: float = 0.0):
        layers: list[nn.Module] = []
        for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
            if i == len(sizes) - 2 and dropout_before_last > 0:
                layers.append(nn.Dropout(dropout_before_last))
            layers.append(nn.Linear(a, b))
            if i < len(sizes) - 2:
                layers.append(nn.ReLU())
        super().__init__(*layers)


DETECT_HEADS = ("position", "classes", "trajectory")


class DetectNet(nn.Module):
    """Three independent heads on a d-vector: position (3), class logits (6), trajectory (10 x 3).

    ``heads`` keeps a subset (always with ``position``): the original AV-PedAware has a position head only.
    """

    def __init__(self, feature_dim: int, num_classes: int = NUM_CLASSES, steps: int = 10,
                 heads: tuple[str, ...] = DETECT_HEADS):
        super().__init__()
        unknown = sorted(set(heads) - set(DETECT_HEADS))
        if unknown or "position" not in heads:
            raise ValueError(f"DetectNet heads must include 'position' and be among {DETECT_HEADS}, got {heads}")
        self.steps = steps
        self.position = MLP((feature_dim, 256, 128, 3))
        if "classes" in heads:
            self.classes = MLP((feature_dim, 256, 128, num_classes))
        if "trajectory" in heads:
            self.trajectory = MLP((feature_dim, 256, 128, 3 * steps))

    def forward(self, features: torch.Tensor) -> dict[str, torch.Tensor]:
        outputs = {"position": self.position(features)}
        if hasattr(self, "classes"):
            outputs["class_logits"] = self.classes(features)
        if hasattr(self, "trajectory"):
            outputs["trajectory"] = self.trajectory(features).view(-1, self.steps, 3)
        return outputs


class VisibilityGate(nn.Module):
    """Softmax weights over the [audio, visual] tokens from a "drone visible" MLP on the visual feature."""

    def __init__(self, feature_dim: int, hidden: tuple[int, ...] = (128,)):
        super().__init__()
        self.detect = MLP((feature_dim, *hidden, 2))

    def forward(self, audio: torch.Tensor, visual: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Fused feature (B x d) and the visibility logits (B x 2; index 1 = visible)."""
        logits = self.detect(visual)
        weights = torch.softmax(logits, dim=1)
        tokens = torch.stack([audio, visual], dim=1)  # B x 2 x d
        return (weights.unsqueeze(-1) * tokens).sum(dim=1), logits


def visibility_loss(logits: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of the visibility logits against the 0/1 "drone visible" label."""
    return nn.functional.cross_entropy(logits, visible.round().long())
