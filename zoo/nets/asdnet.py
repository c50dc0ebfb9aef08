"""ASDNet: the TalkNet active-speaker model adapted to drone localisation (baselines.md section 7).

Layers (AV-FDTI ``nets/comparison/talkNetModel.py`` and ``talknet/*``, TalkNet-ASD's design):

- inputs: the recipe-A mel map resized to 4 x 13 x 13 (``avfdti_13``) and the camera image resized to
  3 x 112 x 112 (``talknet112``, in [-1, 1], no further normalisation, as in the adaptation). The 3
  colour channels are read as T = 3 grayscale "frames";
- visual frontend, per frame: Conv3d 1 -> 64, kernel (5, 7, 7), stride (1, 2, 2), padding (2, 3, 3),
  no bias -> BatchNorm3d -> ReLU -> MaxPool3d (1, 3, 3) / (1, 2, 2), padding (0, 1, 1): 64 x 28 x 28;
  then a ResNet-18-style trunk of four :class:`ResNetLayer` (64, 128, 256, 512 channels; strides 1, 2,
  2, 2) -> 512 x 4 x 4 -> AvgPool 4 x 4 -> 512 per frame;
- V-TCN: five residual depthwise-separable 1-D blocks on 512 channels (ReLU, BatchNorm1d, depthwise
  conv k3, PReLU, global LayerNorm, pointwise conv); Conv1d 512 -> 256 k5 + BatchNorm1d + ReLU, Conv1d
  256 -> 128 k1 -> visual embedding B x 3 x 128;
- audio encoder (SE-ResNet-34-like): Conv2d 4 -> 16, kernel 8, stride (2, 1), padding 3 -> BatchNorm ->
  ReLU; SE basic blocks [3, 4, 6, 3] with 16, 32, 64, 128 filters and strides 1, 2, 2, 1 (SE reduction
  8); mean over the mel axis -> audio embedding B x 3 x 128 (13 x 13 -> 2 x 3 before the mean);
- cross-attention A->V and V->A (:class:`AttentionLayer`, d 128, 8 heads, dropout 0.1, FFN x 4,
  post-norm), concatenation -> B x 3 x 256, self-attention (d 256), flatten 768 -> Linear 100 + ReLU ->
  Linear 100 -> 3 (position) and 100 -> 6 (class logits).

Reduced budget (not the paper's): ``input_recipes={"image": "talknet56"}`` reads 56 x 56 frames (a
512 x 2 x 2 trunk map) with the same parameters: the frame pooling, a 4 x 4 average at the reference
size, i.e. a global average, becomes a global average over whatever map the trunk gives; about 4x less
visual compute.

Details kept from the published code: the SE block applies ReLU *before* its first BatchNorm; the
attention layer takes its query from ``tar`` and keys / values from ``src`` but adds the residual to
``src`` (so "A->V" returns the audio stream updated by attention from the visual queries); the
visual BatchNorms of the lip-reading trunk use momentum 0.01 and eps 1e-3; the audio convolutions are
Kaiming-initialised (fan out).

Deviation (fixed bug): TalkNet's frontend stacks all B * T frames on the depth axis of a single batch
element, so its temporal kernel (5 frames, padding 2) also convolves the last frames of sample i - 1
and the first of sample i + 1 into sample i: a prediction depended on its batch mates and on the
batch order. Here each sample's T frames are convolved separately (zero padding at its own borders,
which is what the batch's first and last samples got in the original). The weights are the same, so
a published checkpoint loads unchanged; ``batch_mixing=True`` reproduces the original behaviour for
comparisons only.

Parameters: 15,820,476, all used. Section 11 gives 16.13 M total / 15.72 M used. The total is
reproduced exactly when the two dead modules of the original are added back: a ``DetectNet(256, 6)``
that is never called (301,095) and the 1 x 1 downsample convolution of the first ResNet layer, which
TalkNet declares in every layer but uses only with stride 2 (4,096): 15,820,476 + 305,191 =
16,125,667. Both are omitted: ``aaute import-checkpoint --format avfdti-comparison`` drops ``detectnet.*`` and
``visualFrontend.resnet.layer1.downsample.weight``, renames the prefixes (``visualFrontend.frontend3D`` ->
``visual_frontend.frontend3d``, ``resnet.layerN`` -> ``resnet.N-1``, ``audioEncoder.conv1/bn1`` ->
``audio_encoder.stem.0/1``, ``audioEncoder.layerN`` -> ``audio_encoder.layers.N-1``, ``se.fc.0/2`` ->
``se.2/4``, ...) and flattens the global LayerNorm's (1, C, 1) gamma / beta into GroupNorm's weight /
bias. Section 11's *used* count is 98,816 lower than ours because it misses the output projections of
the three ``nn.MultiheadAttention`` modules (2 x 16,512 + 65,792): those are applied functionally, not
by calling the sub-module, so a counter based on forward hooks sees them as unused, but they are used.
The published forward also printed two debug lines; there are none here.

Loss: the baselines' training scripts are not published (section 0, 16). The zoo trains the position
through the task's loss and adds ``class_weight`` x cross-entropy on the drone class, 0.1 following
AV-FDTI's class weight.
"""

from __future__ import annotations

import torch
from torch import nn

from zoo.nets.base import NUM_CLASSES, TrajectoryNet
from zoo.registry import register_model


def _bn2d(channels: int) -> nn.BatchNorm2d:
    """BatchNorm of the lip-reading ResNet (momentum 0.01, eps 1e-3)."""
    return nn.BatchNorm2d(channels, momentum=0.01, eps=0.001)


def _conv3x3(in_channels: int, out_channels: int, stride: int | tuple[int, int] = 1) -> nn.Conv2d:
    return nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False)


# --------------------------------------------------------------------------------------------- visual


class ResNetLayer(nn.Module):
    """Two residual units of the lip-reading ResNet-18 (TalkNet's visual trunk).

    conv-BN-ReLU-conv, + skip (the input, or a 1 x 1 strided projection when ``stride`` > 1), BN-ReLU;
    conv-BN-ReLU-conv, + skip from the *pre-BN* sum of the first unit, BN-ReLU.
    """

    def __init__(self, in_channels: int, out_channels: int, stride: int):
        super().__init__()
        if stride == 1 and in_channels != out_channels:
            raise ValueError("a stride-1 ResNetLayer keeps the channel count")
        self.conv1a = _conv3x3(in_channels, out_channels, stride)
        self.bn1a = _bn2d(out_channels)
        self.conv2a = _conv3x3(out_channels, out_channels)
        self.downsample = (nn.Conv2d(in_channels, out_channels, 1, stride=stride, bias=False) if stride > 1
                           else None)
        self.outbna = _bn2d(out_channels)
        self.conv1b = _conv3x3(out_channels, out_channels)
        self.bn1b = _bn2d(out_channels)
        self.conv2b = _conv3x3(out_channels, out_channels)
        self.outbnb = _bn2d(out_channels)
        self.relu = nn.ReLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skip = x if self.downsample is None else self.downsample(x)
        first = self.conv2a(self.relu(self.bn1a(self.conv1a(x)))) + skip
        out = self.relu(self.outbna(first))
        out = self.conv2b(self.relu(self.bn1b(self.conv1b(out)))) + first
        return self.relu(self.outbnb(out))


class VisualFrontend(nn.Module):
    """3-D stem over each sample's T frames, then the 2-D ResNet-18 trunk per frame: B x T x H x W -> B x T x 512."""

    def __init__(self, batch_mixing: bool = False):
        super().__init__()
        self.batch_mixing = batch_mixing
        self.frontend3d = nn.Sequential(
            nn.Conv3d(1, 64, (5, 7, 7), stride=(1, 2, 2), padding=(2, 3, 3), bias=False),
            nn.BatchNorm3d(64, momentum=0.01, eps=0.001),
            nn.ReLU(),
            nn.MaxPool3d((1, 3, 3), stride=(1, 2, 2), padding=(0, 1, 1)),
        )
        self.resnet = nn.Sequential(ResNetLayer(64, 64, 1), ResNetLayer(64, 128, 2), ResNetLayer(128, 256, 2),
                                    ResNetLayer(256, 512, 2))
        self.pool = nn.AvgPool2d(4, stride=1)  # the reference 4 x 4 map -> 1 x 1: a global average

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        b, t, h, w = frames.shape
        if self.batch_mixing:  # the published layout: one "video" of B * T frames
            x = self.frontend3d(frames.reshape(1, 1, b * t, h, w))
        else:  # B videos of T frames each
            x = self.frontend3d(frames.unsqueeze(1))
        x = x.transpose(1, 2).reshape(b * t, x.shape[1], *x.shape[-2:])  # (B T) x 64 x 28 x 28, sample-major
        x = self.resnet(x)
        # the reference path as published; other frame sizes: the global average it amounts to there
        x = self.pool(x) if x.shape[-2:] == (4, 4) else x.mean(dim=(-2, -1), keepdim=True)
        return x.reshape(b, t, -1)

    def extra_repr(self) -> str:
        return f"batch_mixing={self.batch_mixing}"


class DSConv1d(nn.Module):
    """V-TCN block: ReLU, BN, depthwise conv k3, PReLU, global LayerNorm, pointwise conv, plus the input."""

    def __init__(self, channels: int = 512):
        super().__init__()
        self.net = nn.Sequential(
            nn.ReLU(),
            nn.BatchNorm1d(channels),
            nn.Conv1d(channels, channels, 3, padding=1, groups=channels, bias=False),
            nn.PReLU(),
            nn.GroupNorm(1, channels, eps=1e-8),  # global LayerNorm: statistics over channels and time
            nn.Conv1d(channels, channels, 1, bias=False),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.net(x)


# --------------------------------------------------------------------------------------------- audio


class SEBasicBlock(nn.Module):
    """Squeeze-excitation basic block: conv-ReLU-BN (ReLU first, as published), conv-BN, SE, + skip, ReLU."""

    def __init__(self, in_channels: int, channels: int, stride: int | tuple[int, int] = 1, reduction: int = 8):
        super().__init__()
        self.conv1 = _conv3x3(in_channels, channels, stride)
        self.bn1 = nn.BatchNorm2d(channels)
        self.conv2 = _conv3x3(channels, channels)
        self.bn2 = nn.BatchNorm2d(channels)
        self.se = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Linear(channels, channels // reduction),
                                nn.ReLU(), nn.Linear(channels // reduction, channels), nn.Sigmoid())
        self.relu = nn.ReLU()
        self.downsample = None
        if stride not in (1, (1, 1)) or in_channels != channels:
            self.downsample = nn.Sequential(nn.Conv2d(in_channels, channels, 1, stride=stride, bias=False),
                                            nn.BatchNorm2d(channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.bn2(self.conv2(self.bn1(self.relu(self.conv1(x)))))
        out = out * self.se(out)[:, :, None, None]
        skip = x if self.downsample is None else self.downsample(x)
        return self.relu(out + skip)


class AudioEncoder(nn.Module):
    """SE-ResNet over a C x mel x time map, averaged over mel: B x C x 13 x 13 -> B x 3 x 128."""

    def __init__(self, in_channels: int = 4, layers: tuple[int, ...] = (3, 4, 6, 3),
                 filters: tuple[int, ...] = (16, 32, 64, 128), strides: tuple[int, ...] = (1, 2, 2, 1)):
        super().__init__()
        self.stem = nn.Sequential(nn.Conv2d(in_channels, filters[0], 8, stride=(2, 1), padding=3, bias=False),
                                  nn.BatchNorm2d(filters[0]), nn.ReLU())
        stages: list[nn.Module] = []
        width = filters[0]
        for blocks, channels, stride in zip(layers, filters, strides, strict=True):
            stages.append(nn.Sequential(SEBasicBlock(width, channels, stride),
                                        *(SEBasicBlock(channels, channels) for _ in range(blocks - 1))))
            width = channels
        self.layers = nn.Sequential(*stages)
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, mel: torch.Tensor) -> torch.Tensor:
        return self.layers(self.stem(mel)).mean(dim=2).transpose(1, 2)


# --------------------------------------------------------------------------------------------- fusion


class AttentionLayer(nn.Module):
    """TalkNet's attention block (post-norm): ``norm1(src + MHA(q=tar, k=v=src))``, then a ReLU FFN x 4 and norm2."""

    def __init__(self, d_model: int, heads: int = 8, dropout: float = 0.1):
        super().__init__()
        self.self_attn = nn.MultiheadAttention(d_model, heads, dropout=dropout, batch_first=True)
        self.linear1 = nn.Linear(d_model, 4 * d_model)
        self.linear2 = nn.Linear(4 * d_model, d_model)
        self.norm1 = nn.LayerNorm(d_model)
        self.norm2 = nn.LayerNorm(d_model)
        self.dropout = nn.Dropout(dropout)
        self.dropout1 = nn.Dropout(dropout)
        self.dropout2 = nn.Dropout(dropout)

    def forward(self, src: torch.Tensor, tar: torch.Tensor) -> torch.Tensor:
        attended = self.self_attn(tar, src, src, need_weights=False)[0]
        x = self.norm1(src + self.dropout1(attended))
        ffn = self.linear2(self.dropout(torch.relu(self.linear1(x))))
        return self.norm2(x + self.dropout2(ffn))


# --------------------------------------------------------------------------------------------- model


@register_model("asdnet")
class ASDNet(TrajectoryNet):
    """TalkNet-style audio-visual network with a position / class regression head.

    Args:
        in_channels: microphone channels of the mel map (4).
        dropout: dropout of the attention layers (0.1).
        num_classes: class logits (6).
        class_weight: weight of the class cross-entropy (0.1, AV-FDTI's weight).
        batch_mixing: reproduce the published frontend that convolves across batch boundaries (off:
            each sample's frames are convolved on their own; see the module docstring).
        input_recipes: recipes replacing the reference ones, e.g. ``{"image": "talknet56"}`` (reduced budget).
    """

    inputs = {"audio_mel": "avfdti_13", "image": "talknet112"}
    category = "supervised"

    def __init__(self, in_channels: int = 4, dropout: float = 0.1, num_classes: int = NUM_CLASSES,
                 class_weight: float = 0.1, batch_mixing: bool = False, input_recipes: dict[str, str] | None = None):
        super().__init__(in_channels, class_weight, input_recipes)
        self.visual_frontend = VisualFrontend(batch_mixing)
        self.visual_tcn = nn.Sequential(*(DSConv1d(512) for _ in range(5)))
        self.visual_conv1d = nn.Sequential(nn.Conv1d(512, 256, 5, padding=2), nn.BatchNorm1d(256), nn.ReLU(),
                                           nn.Conv1d(256, 128, 1))
        self.audio_encoder = AudioEncoder(in_channels)
        self.cross_a2v = AttentionLayer(128, 8, dropout)
        self.cross_v2a = AttentionLayer(128, 8, dropout)
        self.self_av = AttentionLayer(256, 8, dropout)
        self.fc = nn.Sequential(nn.Linear(3 * 256, 100), nn.ReLU())
        self.position = nn.Linear(100, 3)
        self.classes = nn.Linear(100, num_classes)

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        self.check_inputs(inputs)
        visual = self.visual_frontend(inputs["image"]).transpose(1, 2)  # B x 512 x T
        visual = self.visual_conv1d(self.visual_tcn(visual)).transpose(1, 2)  # B x T x 128
        audio = self.audio_encoder(inputs["audio_mel"])  # B x T x 128
        audio, visual = self.cross_a2v(src=audio, tar=visual), self.cross_v2a(src=visual, tar=audio)
        fused = torch.cat([audio, visual], dim=2)
        fused = self.self_av(src=fused, tar=fused)  # B x T x 256
        feature = self.fc(fused.flatten(1))
        return {"position": self.position(feature), "class_logits": self.classes(feature)}
