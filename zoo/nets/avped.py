"""AV-PED: the AV-PedAware audio-visual baseline as compared in the AAUTE paper (baselines.md section 8.1).

Layers (AV-FDTI ``nets/comparison/avped.py``):

- audio: :class:`~zoo.nets.blocks.FourBranchAudio` on the recipe-A mel map 4 x 64 x 64, 16 filters per
  branch, ReLU + Dropout2d(0.3), 3904 features -> Linear 256 + ReLU: the audio token;
- visual: :class:`~zoo.nets.blocks.VisualEncoder` (ResNet-50 trunk, 2 convs, FC 2048 -> 256): the visual token;
- gate: a "drone visible" MLP on the visual feature 256 -> 128 -> 2, softmax, weighted sum of the
  [audio, visual] tokens (a dark image should move the weight to the audio token);
- heads: DetectNet(256): position 3, class 6, trajectory 10 x 3; the visibility logits are returned too.

Reduced budget (not the paper's): ``input_recipes={"image": "resnet64"}`` (or ``resnet128``) reads a
smaller image through the same visual encoder and parameters (its map is brought to the 8 x 8 grid);
the gate reads the visual feature as before, so a dark frame still moves the weight to audio.

32.27 M parameters in total, 30.22 M used. Section 11 gives 32.36 M total: the published audio
encoder also declares two unused wider branches (10 x 64, 64 x 10) and four unused BatchNorms
(82 k), which are not rebuilt here (a checkpoint converter drops them); the used count matches.

Auxiliary losses (none are published for the comparison variant, so the sources are mixed):
``visibility_weight`` x CE(visibility logits, ``visible``) with 0.5, the weight of AV-PedAware's own
detect loss (section 8.2), and ``class_weight`` x CE(class) with 0.1, AV-FDTI's weight (AV-PedAware
has no class head). The trajectory head is not trained: batches carry no future targets yet.
"""

from __future__ import annotations

import torch

from zoo.nets.base import NUM_CLASSES, TrajectoryNet
from zoo.nets.blocks import (
    DETECT_HEADS,
    DetectNet,
    FourBranchAudio,
    VisibilityGate,
    VisualEncoder,
    visibility_loss,
)
from zoo.registry import register_model


@register_model("avped")
class AVPed(TrajectoryNet):
    """Audio and visual tokens fused by a visibility gate, then DetectNet heads.

    Args:
        in_channels: microphone channels of the mel map.
        kernels: filters per audio branch (16).
        feature_dim: token width d (256).
        dropout: Dropout2d of the audio branches (0.3).
        resnet_weights: a local torchvision ResNet-50 state-dict file (ImageNet V1); None: random.
        gate_hidden: hidden widths of the visibility MLP ((128,) in the comparison variant).
        num_classes: class logits.
        visibility_weight: weight of the visibility cross-entropy (AV-PedAware: 0.5).
        class_weight: weight of the class cross-entropy (AV-FDTI: 0.1).
        input_recipes: recipes replacing the reference ones, e.g. ``{"image": "resnet64"}`` (reduced budget).
        heads: the DetectNet heads kept (all three; the original AV-PedAware, imported with ``aaute
            import-checkpoint --format avped``, has only ``("position",)``).
    """

    inputs = {"audio_mel": "avfdti", "image": "resnet256"}
    category = "supervised"

    def __init__(self, in_channels: int = 4, kernels: int = 16, feature_dim: int = 256, dropout: float = 0.3,
                 resnet_weights: str | None = None, gate_hidden: tuple[int, ...] = (128,),
                 num_classes: int = NUM_CLASSES, visibility_weight: float = 0.5, class_weight: float = 0.1,
                 input_recipes: dict[str, str] | None = None, heads: tuple[str, ...] = DETECT_HEADS):
        super().__init__(in_channels, class_weight, input_recipes)
        self.visibility_weight = visibility_weight
        self.audio = FourBranchAudio(in_channels, kernels, feature_dim, dropout)
        self.visual = VisualEncoder(feature_dim, resnet_weights)
        self.gate = VisibilityGate(feature_dim, tuple(gate_hidden))
        self.head = DetectNet(feature_dim, num_classes, heads=tuple(heads))

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        self.check_inputs(inputs)
        fused, visibility = self.gate(self.audio(inputs["audio_mel"]), self.visual(inputs["image"]))
        return {**self.head(fused), "visibility_logits": visibility}

    def auxiliary_losses(
        self, outputs: dict[str, torch.Tensor], batch: dict[str, torch.Tensor], target: torch.Tensor,
        target_valid: torch.Tensor,
    ) -> dict[str, torch.Tensor]:
        terms = super().auxiliary_losses(outputs, batch, target, target_valid)
        if self.visibility_weight > 0 and "visible" in batch:
            terms["visibility"] = self.visibility_weight * visibility_loss(outputs["visibility_logits"],
                                                                           batch["visible"])
        return terms
