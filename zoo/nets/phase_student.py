"""A phase-aware student: position from the GCC-PHAT of every microphone pair, trained like the paper's.

Why this shape. The position is a smooth function of the pair delays (three unknowns from six
delays with four microphones), and each delay is the lag of a peak of that pair's correlation. So
the net first reads every pair's correlation on every frame with one small 1D convolutional encoder
over lags (shared by all pairs and frames: a peak means the same thing everywhere; max pooling keeps
the strongest peak of each neighbourhood, and the flattened map keeps *where* it is, which is the
delay). A learned embedding per pair then says which pair it was. The frames of a window are
combined by their mean and their maximum (robust to a frame lost to a gust or masked by noise,
without averaging the slowly drifting delays coherently). A multilayer perceptron maps the six pairs'
features to the position: it can learn what no fixed geometry formula knows, e.g. which secondary
peaks are the ground reflection's direct-to-image cross terms at this rig's microphone heights, and
how far to trust a weak peak. Input: recipe ``gcc_phat`` (pairs x frames x lags); about 0.3 M
parameters and 0.01 GMACs per window, so it runs far faster than real time on one core.
"""

from __future__ import annotations

import torch
from torch import nn

from datamodules.features import mic_pairs, phase_recipe
from zoo.nets.base import TrajectoryNet
from zoo.registry import register_model


@register_model("phase_student")
class PhaseStudent(TrajectoryNet):
    """Pair-correlation encoder, frame pooling and a position MLP (see the module docstring)."""

    inputs = {"audio_phase": "gcc_phat"}
    category = "self-supervised"

    def __init__(self, in_channels: int = 4, filters: int = 16, pair_features: int = 64, hidden: int = 256,
                 dropout: float = 0.2, input_recipes: dict[str, str] | None = None):
        super().__init__(in_channels, input_recipes=input_recipes)
        recipe = phase_recipe(self.inputs["audio_phase"])
        self.pairs = len(mic_pairs(in_channels))
        lags = recipe.num_lags()
        self.encoder = nn.Sequential(
            nn.Conv1d(1, filters // 2, 7, padding=3), nn.ReLU(), nn.MaxPool1d(4),
            nn.Conv1d(filters // 2, filters, 7, padding=3), nn.ReLU(), nn.MaxPool1d(4),
            nn.Flatten(), nn.Linear(filters * (lags // 16), pair_features), nn.ReLU(),
        )
        self.pair_embedding = nn.Parameter(torch.zeros(self.pairs, pair_features))
        self.head = nn.Sequential(
            nn.Linear(2 * pair_features * self.pairs, hidden), nn.ReLU(), nn.Dropout(dropout),
            nn.Linear(hidden, hidden // 2), nn.ReLU(), nn.Linear(hidden // 2, 3),
        )

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        phase = inputs["audio_phase"].float()  # B x P x F x L
        b, p, f, lags = phase.shape
        features = self.encoder(phase.reshape(b * p * f, 1, lags)).reshape(b, p, f, -1)
        features = features + self.pair_embedding[None, :, None, :]
        pooled = torch.cat([features.mean(dim=2), features.amax(dim=2)], dim=-1)  # B x P x 2D
        return {"position": self.head(pooled.flatten(1))}
