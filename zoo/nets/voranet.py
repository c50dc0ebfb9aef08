"""VorasNet: AV-FDTI's re-implementation of the DroneChase audio network (baselines.md section 6).

Layers (AV-FDTI ``nets/comparison/voranet.py``), on the recipe-A mel map upsampled to 4 x 224 x 224
(``avfdti_224``):

- three blocks of Conv2d 3 x 3, stride 2, padding 1 (4 -> 64, 64 -> 64, 64 -> 64) -> BatchNorm2d ->
  ReLU -> MaxPool 2 x 2: 224 -> 56 -> 14 -> 3, a 64 x 3 x 3 map;
- **published quirk, reproduced**: the map is *reshaped* (a view of the contiguous C x H x W memory, not
  a permutation) to 3 "time steps" of 192 values, and only the first 128 values of each step are kept.
  Step t therefore holds flat values 192 t ... 192 t + 127, i.e. about 14 consecutive channels with all
  their 3 x 3 positions (step 0: channels 0-13 and two values of channel 14), not a row or column of the
  map: channels and space are mixed, and a third of the 576 values (192) never reach the LSTM. It is
  what the compared model computed, so the zoo keeps it;
- LSTM(128 -> 128, one layer, batch first); the last step -> Linear 128 -> 32 + ReLU -> Linear 32 -> 3
  (position) and Linear 32 -> 6 (class logits).

213,129 parameters, all used (section 11: 0.213 M). The input size is fixed: any other size than
224 x 224 changes the number of values per step (a 64 x 64 map gives 64, the LSTM expects 128), so it
is rejected with a ValueError.

Loss: the baselines' training scripts are not published (section 0, 16). The zoo trains the position
through the task's loss and adds ``class_weight`` x cross-entropy on the drone class, 0.1 following
AV-FDTI's class weight.
"""

from __future__ import annotations

import torch
from torch import nn

from zoo.nets.base import NUM_CLASSES, TrajectoryNet
from zoo.registry import register_model


def conv_block(in_channels: int, out_channels: int) -> nn.Sequential:
    """Conv 3 x 3 stride 2 padding 1 -> BatchNorm -> ReLU -> MaxPool 2 x 2 (a 16-fold smaller map)."""
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, 3, stride=2, padding=1), nn.BatchNorm2d(out_channels),
                         nn.ReLU(), nn.MaxPool2d(2))


@register_model("voranet")
class VorasNet(TrajectoryNet):
    """Three conv blocks, a reshape into 3 steps, an LSTM and position / class heads.

    Args:
        in_channels: microphone channels of the mel map (4).
        channels: filters of the three conv blocks (64).
        hidden: LSTM input and hidden size (128; the first ``hidden`` values of each step are fed).
        num_classes: class logits (6).
        class_weight: weight of the class cross-entropy (0.1, AV-FDTI's weight).
    """

    inputs = {"audio_mel": "avfdti_224"}
    category = "supervised"

    def __init__(self, in_channels: int = 4, channels: int = 64, hidden: int = 128, num_classes: int = NUM_CLASSES,
                 class_weight: float = 0.1):
        super().__init__(in_channels, class_weight)
        self.hidden = hidden
        self.features = nn.Sequential(conv_block(in_channels, channels), conv_block(channels, channels),
                                      conv_block(channels, channels))
        self.lstm = nn.LSTM(hidden, hidden, num_layers=1, batch_first=True)
        self.fc = nn.Sequential(nn.Linear(hidden, 32), nn.ReLU())
        self.position = nn.Linear(32, 3)
        self.classes = nn.Linear(32, num_classes)

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        self.check_inputs(inputs)
        x = self.features(inputs["audio_mel"])  # B x 64 x 3 x 3
        steps = x.reshape(x.shape[0], x.shape[2], -1)  # the published view: B x H x (C * W) = B x 3 x 192
        if steps.shape[2] < self.hidden:
            raise ValueError(f"voranet: {steps.shape[2]} values per step reach an LSTM of input size {self.hidden}")
        sequence, _ = self.lstm(steps[:, :, : self.hidden])
        feature = self.fc(sequence[:, -1])
        return {"position": self.position(feature), "class_logits": self.classes(feature)}
