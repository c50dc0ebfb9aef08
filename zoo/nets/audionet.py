"""AudioNet: the audio-only supervised baseline of the AAUTE comparison (baselines.md section 5).

Layers (AV-FDTI ``nets/comparison/audionet.py``, ``AudioNet_detect`` over ``nets/audio_net.py``), on the
recipe-A mel map 4 x 64 x 64 (channel, mel, time):

- :class:`~zoo.nets.blocks.FourBranchAudio` with k = 16 filters per branch: convolutions 3 x 64 and
  5 x 64 (narrow in mel, spanning all time frames) and 64 x 3 and 64 x 5 (spanning all mel bins), no
  padding, each followed by ReLU and Dropout2d(0.3), flattened and concatenated (244 k = 3904
  features) -> Linear 3904 -> d + ReLU, d = 256 (the configuration of the paper's baseline; the
  code's default is 512);
- :class:`~zoo.nets.blocks.DetectNet` (d): three MLPs d -> 256 -> 128 -> position 3, class logits 6
  and a 10 x 3 trajectory.

Parameters: 1,366,375, equal to the *used* count of section 11 (1.366 M). Section 11's total of
1.448 M also counts modules the published encoder declares but never calls: two wider branches
(10 x 64 and 64 x 10, 4 -> 16, 2 x 40,976 parameters) and four BatchNorm2d(16) whose calls are
commented out (4 x 32), 82,080 in all. They are not rebuilt: the published key names
(``audionet.convt1`` ...) differ from the zoo's anyway, so loading an authors' checkpoint needs a key
map, and that map can drop the dead keys (including the BatchNorms' running statistics). The map:
``audionet.convt1/convt2/convf1/convf2`` -> ``encoder.branches.0/1/2/3.0``, ``audionet.fc_audio`` ->
``encoder.project.0``, ``detectnet.position_est1/2/3`` -> ``head.position.0/2/4``, ``detectnet.cls1/2/3``
-> ``head.classes.0/2/4``, ``detectnet.traj1/2/3`` -> ``head.trajectory.0/2/4``; dropped:
``audionet.convt3``, ``audionet.convf3``, ``audionet.bn1..bn4``. (The first published upload applied those
BatchNorms after the ReLU; the version the baselines link to does not.)

Loss: the baselines' training scripts are not published (section 0, 16). The zoo trains the position
through the task's loss and adds ``class_weight`` x cross-entropy on the drone class, 0.1 following
AV-FDTI's class weight. The trajectory head is computed and returned but not trained: batches carry no
future targets yet.
"""

from __future__ import annotations

import torch

from zoo.nets.base import NUM_CLASSES, TrajectoryNet
from zoo.nets.blocks import DetectNet, FourBranchAudio
from zoo.registry import register_model


@register_model("audionet")
class AudioNet(TrajectoryNet):
    """Four-branch mel encoder and DetectNet heads (position, class, trajectory).

    Args:
        in_channels: microphone channels of the mel map (4).
        kernels: filters per branch k (16).
        feature_dim: width d of the audio feature (256, the paper's baseline).
        dropout: Dropout2d probability of the branches (0.3).
        num_classes: class logits (6: five drones and "no drone").
        class_weight: weight of the class cross-entropy (0.1, AV-FDTI's weight).
    """

    inputs = {"audio_mel": "avfdti"}
    category = "supervised"

    def __init__(self, in_channels: int = 4, kernels: int = 16, feature_dim: int = 256, dropout: float = 0.3,
                 num_classes: int = NUM_CLASSES, class_weight: float = 0.1):
        super().__init__(in_channels, class_weight)
        self.encoder = FourBranchAudio(in_channels, kernels, feature_dim, dropout)
        self.head = DetectNet(feature_dim, num_classes)

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        self.check_inputs(inputs)
        return self.head(self.encoder(inputs["audio_mel"]))
