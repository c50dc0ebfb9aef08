"""VisualNet: the image-only ResNet-50 baseline of the AAUTE comparison (baselines.md section 3).

Layers (AV-FDTI ``nets/comparison/resnet50_visual.py``): an image of 3 x 256 x 256 scaled to [-1, 1]
(no ImageNet statistics, as published) -> the torchvision ResNet-50 trunk (2048 x 8 x 8; the whole
``resnet50`` is kept, so its unused 1000-way classifier, 2.05 M parameters, counts in the total) ->
Conv 3 x 3 2048 -> 256 + ReLU -> Conv 3 x 3 256 -> 32 + ReLU -> flatten 2048 -> Linear d + ReLU
(d = 256) -> DetectNet: position 256 -> 128 -> 3, class 256 -> 128 -> 6, trajectory 256 -> 128 -> 30.
31.18 M parameters in total, 29.13 M used (section 11; the trajectory head runs in the published
forward, so it counts as used, and it is returned here although nothing trains it yet).

Reduced budget (not the paper's): ``input_recipes={"image": "resnet64"}`` (or ``resnet128``) reads a
smaller image with the same parameters (the encoder brings its map to the 8 x 8 grid, see
:class:`~zoo.nets.blocks.VisualEncoder`); about 16x (4x) less compute than at 256 x 256.

Loss: the published code has none for this baseline; the zoo adds ``class_weight`` x cross-entropy
on the drone class (0.1, AV-FDTI's weight) to the task's position loss. ``class_weight = 0`` turns it off.
"""

from __future__ import annotations

import torch

from zoo.nets.base import NUM_CLASSES, TrajectoryNet
from zoo.nets.blocks import DetectNet, VisualEncoder
from zoo.registry import register_model


@register_model("visualnet")
class VisualNet(TrajectoryNet):
    """ResNet-50 image encoder + DetectNet heads.

    Args:
        feature_dim: width d of the visual feature (256 in the comparison).
        resnet_weights: a local torchvision ResNet-50 state-dict file (ImageNet V1 as published);
            None leaves the trunk randomly initialised. Nothing is downloaded.
        num_classes: class logits (five drones + "no drone").
        class_weight: weight of the class cross-entropy auxiliary loss.
        input_recipes: recipes replacing the reference ones, e.g. ``{"image": "resnet64"}`` (reduced budget).
    """

    inputs = {"image": "resnet256"}
    category = "supervised"

    def __init__(self, feature_dim: int = 256, resnet_weights: str | None = None, num_classes: int = NUM_CLASSES,
                 class_weight: float = 0.1, input_recipes: dict[str, str] | None = None):
        super().__init__(class_weight=class_weight, input_recipes=input_recipes)
        self.encoder = VisualEncoder(feature_dim, resnet_weights)
        self.head = DetectNet(feature_dim, num_classes)

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        self.check_inputs(inputs)
        return self.head(self.encoder(inputs["image"]))
