"""DarkNet: the Darknet-53 image baseline of the AAUTE comparison, trained from scratch (baselines.md section 4).

Layers (AV-FDTI ``nets/comparison/darknet.py``), every convolution a :class:`ConvBN` (Conv2d without
bias, "same" padding k // 2 -> BatchNorm -> LeakyReLU(0.01)):

- stem: 3 x 3, 3 -> 32 at 256 x 256;
- five stages, each a stride-2 3 x 3 convolution doubling the channels followed by 1, 2, 8, 8 and 4
  residual blocks (32 -> 64, 64 -> 128, 128 -> 256, 256 -> 512, 512 -> 1024) -> 1024 x 8 x 8;
- residual block: 1 x 1 c -> c/2, 3 x 3 c/2 -> c, plus the skip. **Published quirk**: the original
  adds the skip unconditionally and once more when its ``shortcut`` flag is set (always), so a block
  computes F(x) + 2 x. ``faithful_residual=True`` (default) reproduces that; False gives the usual
  F(x) + x. The weights are the same either way (a checkpoint loads into both);
- global average pool -> 1024 -> Linear 100 + ReLU -> Linear 100 -> 3 (position) and 100 -> 6 (class).

Reduced budget (not the paper's): ``input_recipes={"image": "resnet64"}`` (or ``resnet128``): the
backbone is fully convolutional and ends in a global average pool, so a smaller image (a 1024 x 2 x 2
map at 64 x 64) needs no adapter and keeps the same parameters; about 16x (4x) less compute.

40.69 M parameters, all used (section 11). The original's custom weight init runs before any layer
exists and is therefore a no-op: PyTorch's default init applies, as here.

Loss: the published code has none; the zoo adds ``class_weight`` x cross-entropy on the drone class
(0.1, AV-FDTI's weight) to the task's position loss.
"""

from __future__ import annotations

import torch
from torch import nn

from zoo.nets.base import NUM_CLASSES, TrajectoryNet
from zoo.registry import register_model

STAGES = ((64, 1), (128, 2), (256, 8), (512, 8), (1024, 4))  #: (output channels, residual blocks) per stage


class ConvBN(nn.Sequential):
    """Conv2d (no bias, padding k // 2) -> BatchNorm2d -> LeakyReLU(0.01)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 1, stride: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, kernel_size, stride, kernel_size // 2, bias=False)
        self.bn = nn.BatchNorm2d(out_channels)
        self.act = nn.LeakyReLU(0.01)


class DarkResidual(nn.Module):
    """1 x 1 c -> c/2 and 3 x 3 c/2 -> c, plus the skip once (standard) or twice (``faithful``, as published)."""

    def __init__(self, channels: int, faithful: bool = True):
        super().__init__()
        self.faithful = faithful
        self.reduce = ConvBN(channels, channels // 2, 1)
        self.expand = ConvBN(channels // 2, channels, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.expand(self.reduce(x))
        return out + x + x if self.faithful else out + x

    def extra_repr(self) -> str:
        return f"faithful={self.faithful}"


@register_model("darknet")
class DarkNet53(TrajectoryNet):
    """Darknet-53 backbone + a 100-unit layer with position and class outputs.

    Args:
        faithful_residual: reproduce the published F(x) + 2x residual (False: F(x) + x).
        num_classes: class logits (five drones + "no drone").
        class_weight: weight of the class cross-entropy auxiliary loss.
        input_recipes: recipes replacing the reference ones, e.g. ``{"image": "resnet64"}`` (reduced budget).
    """

    inputs = {"image": "resnet256"}
    category = "supervised"

    def __init__(self, faithful_residual: bool = True, num_classes: int = NUM_CLASSES, class_weight: float = 0.1,
                 input_recipes: dict[str, str] | None = None):
        super().__init__(class_weight=class_weight, input_recipes=input_recipes)
        layers: list[nn.Module] = [ConvBN(3, 32, 3)]
        channels = 32
        for out_channels, blocks in STAGES:
            layers.append(ConvBN(channels, out_channels, 3, stride=2))
            layers.extend(DarkResidual(out_channels, faithful_residual) for _ in range(blocks))
            channels = out_channels
        self.backbone = nn.Sequential(*layers)  # flat, in the order of the original ``features``
        self.fc = nn.Sequential(nn.Linear(channels, 100), nn.ReLU())
        self.position = nn.Linear(100, 3)
        self.classes = nn.Linear(100, num_classes)

    @property
    def faithful_residual(self) -> bool:
        """Whether the residual blocks add their skip twice (the published behaviour)."""
        return all(m.faithful for m in self.modules() if isinstance(m, DarkResidual))

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        self.check_inputs(inputs)
        features = self.fc(self.backbone(inputs["image"]).mean(dim=(2, 3)))
        return {"position": self.position(features), "class_logits": self.classes(features)}
