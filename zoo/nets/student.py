"""The AAUTE audio student ("Ours"): four-branch mel encoder and a position MLP.

Layers (the authors' ``audio_net.py``): the four full-axis convolutions of
:class:`~zoo.nets.blocks.FourBranchAudio` with 16 filters each, ReLU and Dropout2d(0.2), 3904
features -> Linear 512 + ReLU -> 256 -> 128 -> Dropout(0.4) -> 3. Input: recipe B (``aaute``), a
4 x 64 x 64 mel map covering about 0-1.2 kHz. 2.230 M parameters. No class or visual head.
"""

from __future__ import annotations

import torch

from zoo.nets.base import TrajectoryNet
from zoo.nets.blocks import MLP, FourBranchAudio
from zoo.registry import register_model


@register_model("student")
class Student(TrajectoryNet):
    """Audio-only position regressor trained on LiDAR pseudo-labels."""

    inputs = {"audio_mel": "aaute"}
    category = "self-supervised"

    def __init__(self, in_channels: int = 4, kernels: int = 16, feature_dim: int = 512, dropout: float = 0.2,
                 head_dropout: float = 0.4):
        super().__init__(in_channels)
        self.encoder = FourBranchAudio(in_channels, kernels, feature_dim, dropout)
        self.head = MLP((feature_dim, 256, 128, 3), dropout_before_last=head_dropout)

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {"position": self.head(self.encoder(inputs["audio_mel"]))}
