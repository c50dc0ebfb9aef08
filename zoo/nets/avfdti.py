"""AV-FDTI: audio-visual fusion with a bird's-eye heat-map head (baselines.md section 9).

Layers (AV-FDTI ``nets/AVFDTI.py`` and its blocks; k = 32 filters, d = 512):

- audio: :class:`~zoo.nets.blocks.FourBranchAudio` on the recipe-A mel map 4 x 64 x 64, 32 filters per
  branch, ReLU + Dropout2d(0.3), 7808 features -> Linear 512 + ReLU: the audio token;
- visual: :class:`~zoo.nets.blocks.VisualEncoder` (ResNet-50 trunk, 2 convs, FC 2048 -> 512);
- gate: a "drone visible" MLP on the visual feature 512 -> 256 -> 128 -> 2, softmax, weighted sum of
  the [audio, visual] tokens: the fused token;
- :class:`AttentionBlock`: 8-head attention (dropout 0.4), query = audio token, key = value = fused
  token, residual onto the fused token + LayerNorm, FFN 512 -> 2048 -> 512 (ReLU, dropout 0.4) +
  residual + LayerNorm. With one token on each side the attention weight is 1: in effect a value
  projection plus the FFN (published that way);
- heads on the result: class 512 -> 256 -> 128 -> 6, trajectory 512 -> 256 -> 128 -> 30 (10 x 3),
  z 512 -> 256 -> 100 -> 1 (m), offset 512 -> 100 -> 2 (cm), and :class:`HeatmapDecoder`: Linear
  512 -> 256 + ReLU -> 1 x 16 x 16 -> ConvT(1 -> 32, k3 s2 p1 op1) -> four ConvT(32 -> 32, same) -> 512 x
  512 (ReLU after each) -> ``decoder_convs`` x (Conv 3 x 3 32 -> 32 + ReLU) -> Conv 3 x 3 32 -> 1 ->
  sigmoid: a 512 x 512 bird's-eye heat map, rows = y, columns = x.

``decoder_convs = 1`` (default) is the variant of the comparison (section 11, about 37 M used: 37.52 M
here, 39.56 M in total with the unused ResNet classifier); 3 is the later published code.

Position (``utils/metrics.calculate_result``): column sums of the heat map -> argmax = x index, row
sums -> argmax = y index, x = x_min + index x cell + offset_x / 100 (likewise y), z from the z head.
The bird's-eye bounds are a persistent buffer set by :meth:`AVFDTI.set_bounds` (the task passes the
DataModule's ``bev_bounds``); until then the published AV-FDTI area x in [-1.828, 5.861] m,
y in [-4.721, 18.767] m applies. The argmax is not differentiable, so ``trains_position = False``:
AV-FDTI trains only its heads.

Losses (``utils/train_val.py``, :meth:`AVFDTI.auxiliary_losses`), on samples with a valid target:

- heat map: one Gaussian of radius 40 px (sigma = 81 / 6) at the target's cell (row = y index,
  column = x index; the cell is floor((position - min) / cell size)), scored by the CenterNet-style
  focal loss with exponent 1 on (1 - p) and p, negatives weighted by (1 - gt)^4, normalised by the
  number of exact-1 pixels (:func:`heatmap_focal_loss`, computed as the equal :func:`peak_focal_loss`);
- + MSE(z) + 0.1 MSE(offset, the quantisation residual in cm) + 0.1 CE(visibility) + 0.1 CE(class)
  (the last two over all samples with a label). The published 0.1 MSE(trajectory) term is omitted:
  batches carry no future targets yet.

Reduced budget (not the paper's; it changes the architecture, so a reduced AV-FDTI is reported as
such): ``heatmap_size`` (default 512, the reference) = 16 x 2^k sets the decoder's output, with
k stride-2 transposed convolutions instead of five; 128 drops two of them and runs the final convs at
128 x 128, about 16x less decoder compute, with 2 x (9 ``kernels``^2 + ``kernels``) fewer parameters
and fewer ``heatmap.layers`` entries (a reference checkpoint does not load into it). The
grid covers the same bird's-eye bounds with 512 / size times larger cells, so :meth:`AVFDTI.decode`,
:meth:`AVFDTI.target_cells` (offsets still in cm from the cell corner) and the losses follow the
size, and ``heatmap_radius`` is given in pixels of the reference 512 map and scaled by size / 512
(40 -> 10 px at 128: the same metric area). ``input_recipes={"image": "resnet64"}`` reads a smaller
image with the same encoder parameters (:class:`~zoo.nets.blocks.VisualEncoder`). The reference
shapes and parameters are unchanged by default.

Targets outside the bounds are clipped to the border (their Gaussian sits on the edge cell and the
offset is measured from the clipped point); they are counted in ``clipped_targets`` and logged, since
many of them mean the bounds do not fit the data.
"""

from __future__ import annotations

import logging
import math

import torch
from torch import nn
from torch.nn import functional as F

from zoo.nets.base import NUM_CLASSES, TrajectoryNet, classification_loss
from zoo.nets.blocks import MLP, FourBranchAudio, VisibilityGate, VisualEncoder, visibility_loss
from zoo.registry import register_model

log = logging.getLogger(__name__)

#: [[x_min, x_max], [y_min, y_max]] (m) hard-coded in AV-FDTI (``utils/metrics.py``, ``obtain_gaussian``)
AVFDTI_BOUNDS = ((-1.827702940235904, 5.861056694237837), (-4.720740577048357, 18.766594286932648))
REFERENCE_HEATMAP = 512  #: the published heat-map side (px)
HEATMAP_SEED = 16  #: side of the decoder's seed map before the transposed convolutions


class AttentionBlock(nn.Module):
    """Post-norm cross-attention (query = audio token, key/value = fused token) + FFN, both with residuals."""

    def __init__(self, feature_dim: int = 512, heads: int = 8, dropout: float = 0.4, expansion: int = 4):
        super().__init__()
        self.attention = nn.MultiheadAttention(feature_dim, heads, dropout=dropout, batch_first=True)
        self.norm1 = nn.LayerNorm(feature_dim)
        self.ffn = nn.Sequential(
            nn.Linear(feature_dim, expansion * feature_dim), nn.ReLU(), nn.Dropout(dropout),
            nn.Linear(expansion * feature_dim, feature_dim), nn.Dropout(dropout),
        )
        self.norm2 = nn.LayerNorm(feature_dim)
        self.dropout = nn.Dropout(dropout)

    def forward(self, fused: torch.Tensor, audio: torch.Tensor) -> torch.Tensor:
        """B x d fused and audio features -> B x d."""
        attended = self.attention(audio[:, None], fused[:, None], fused[:, None], need_weights=False)[0][:, 0]
        x = self.norm1(fused + self.dropout(attended))
        return self.norm2(x + self.ffn(x))


class HeatmapDecoder(nn.Module):
    """d-vector -> 16 x 16 seed -> ``upsamplings`` stride-2 transposed convs (5: 512 x 512) -> heat-map logits."""

    def __init__(self, feature_dim: int = 512, channels: int = 32, convs: int = 1, seed: int = 16,
                 upsamplings: int = 5):
        super().__init__()
        if upsamplings < 1:
            raise ValueError(f"the heat-map decoder needs at least one transposed convolution, got {upsamplings}")
        self.seed = seed
        self.size = seed * 2**upsamplings
        self.project = nn.Sequential(nn.Linear(feature_dim, seed * seed), nn.ReLU())
        layers: list[nn.Module] = []
        for i in range(upsamplings):
            layers += [nn.ConvTranspose2d(1 if i == 0 else channels, channels, 3, stride=2, padding=1,
                                          output_padding=1), nn.ReLU()]
        for _ in range(convs):
            layers += [nn.Conv2d(channels, channels, 3, padding=1), nn.ReLU()]
        layers.append(nn.Conv2d(channels, 1, 3, padding=1))
        self.layers = nn.Sequential(*layers)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """B x d -> B x size x size logits (rows = y, columns = x)."""
        seed = self.project(features).view(-1, 1, self.seed, self.seed)
        return self.layers(seed)[:, 0]


def gaussian_profile(distance: torch.Tensor, radius: int) -> torch.Tensor:
    """exp(-d^2 / 2 sigma^2) within ``radius`` pixels, else 0; sigma = (2 r + 1) / 6 (CenterNet's gaussian2D).

    The 2-D target Gaussian is the outer product of two profiles, exactly 1 at the peak.
    """
    sigma = (2 * radius + 1) / 6
    return torch.exp(-(distance**2) / (2 * sigma**2)) * (distance.abs() <= radius)


def heatmap_focal_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """AV-FDTI's CenterNet-style focal loss (``utils/loss._neg_loss``) on B x H x W maps, any target.

    -[sum over gt == 1 of (1 - p) log p + sum over gt < 1 of (1 - gt)^4 p log(1 - p)] / #(gt == 1),
    exponent 1 on (1 - p) and p; without positives the negative sum alone (as published). The logs
    are taken from the logits (log-sigmoid) rather than from p clamped to [1e-7, 1 - 1e-7]: the same
    value wherever the clamp is inactive, and no dead gradients where it would be. (1 - gt)^4 is 0 at
    the peaks, so no negative mask is needed. This is the reference; training uses the equal and
    cheaper :func:`peak_focal_loss`.
    """
    p = torch.sigmoid(logits)
    positive = target == 1
    positive_term = (F.logsigmoid(logits) * (1 - p))[positive].sum()
    negative_term = (F.logsigmoid(-logits) * p * (1 - target).pow(4)).sum()
    return -(positive_term + negative_term) / positive.sum().clamp(min=1)


def peak_focal_loss(logits: torch.Tensor, peaks: torch.Tensor, radius: int) -> torch.Tensor:
    """:func:`heatmap_focal_loss` for one Gaussian per map, without building the B x H x W target.

    ``peaks`` holds each map's peak cell as (column, row) = (x index, y index), B x 2. The negative
    weight (1 - gt)^4 is 1 outside the (2 r + 1)^2 window around the peak, so the negative term is the
    unweighted sum over the whole map plus a correction inside the (border-clipped) window: three
    element-wise passes over the map instead of about ten, and no target map in memory.
    """
    batch, height, width = logits.shape
    p = torch.sigmoid(logits)
    negative = (F.logsigmoid(-logits) * p).sum()
    steps = torch.arange(-radius, radius + 1, device=logits.device)
    profile = gaussian_profile(steps.double(), radius).to(logits.dtype)
    correction_weight = (1 - profile[:, None] * profile[None, :]).pow(4) - 1  # -1 at the peak: no negative there
    rows, columns = peaks[:, 1, None] + steps, peaks[:, 0, None] + steps  # B x (2 r + 1)
    inside = ((rows >= 0) & (rows < height))[:, :, None] & ((columns >= 0) & (columns < width))[:, None, :]
    window = logits[torch.arange(batch, device=logits.device)[:, None, None], rows.clamp(0, height - 1)[:, :, None],
                    columns.clamp(0, width - 1)[:, None, :]]
    correction = (F.logsigmoid(-window) * torch.sigmoid(window) * correction_weight * inside).sum()
    peak = logits[torch.arange(batch, device=logits.device), peaks[:, 1], peaks[:, 0]]
    positive = (F.logsigmoid(peak) * (1 - torch.sigmoid(peak))).sum()
    return -(positive + negative + correction) / max(batch, 1)


@register_model("avfdti")
class AVFDTI(TrajectoryNet):
    """AV-FDTI: gated audio-visual fusion, attention, heat-map / offset / z / class / trajectory heads.

    Args:
        in_channels: microphone channels of the mel map.
        kernels: filters per audio branch and channels of the heat-map decoder (32).
        feature_dim: token width d (512).
        dropout: Dropout2d of the audio branches (0.3).
        attention_dropout: dropout of the attention block (0.4).
        heads: attention heads (8).
        decoder_convs: 3 x 3 convolutions at the heat-map size before the output conv (1: the compared
            variant; 3: the later published code).
        resnet_weights: a local torchvision ResNet-50 state-dict file (ImageNet V1); None: random.
        num_classes: class logits.
        heatmap_radius: radius of the target Gaussian in pixels of the reference 512 x 512 map (40; sigma =
            (2 r + 1) / 6); scaled by ``heatmap_size`` / 512 (rounded, at least 1 px): ``self.heatmap_radius``.
        heatmap_size: side of the heat map, 16 x 2^k with k >= 1 (512, the reference; 128 for a reduced
            budget: a different architecture, see the module docstring).
        input_recipes: recipes replacing the reference ones, e.g. ``{"image": "resnet64"}`` (reduced budget).
        heatmap_weight, z_weight, offset_weight, visibility_weight, class_weight: loss weights
            (1, 1, 0.1, 0.1, 0.1 as published since commit b50f11d).
    """

    inputs = {"audio_mel": "avfdti", "image": "resnet256"}
    category = "supervised"
    trains_position = False

    def __init__(self, in_channels: int = 4, kernels: int = 32, feature_dim: int = 512, dropout: float = 0.3,
                 attention_dropout: float = 0.4, heads: int = 8, decoder_convs: int = 1,
                 resnet_weights: str | None = None, num_classes: int = NUM_CLASSES, heatmap_radius: int = 40,
                 heatmap_weight: float = 1.0, z_weight: float = 1.0, offset_weight: float = 0.1,
                 visibility_weight: float = 0.1, class_weight: float = 0.1, heatmap_size: int = REFERENCE_HEATMAP,
                 input_recipes: dict[str, str] | None = None):
        super().__init__(in_channels, input_recipes=input_recipes)
        upsamplings = round(math.log2(heatmap_size / HEATMAP_SEED)) if heatmap_size > HEATMAP_SEED else 0
        if upsamplings < 1 or HEATMAP_SEED * 2**upsamplings != heatmap_size:
            raise ValueError(f"AV-FDTI heatmap_size must be {HEATMAP_SEED} x 2^k with k >= 1 (32, 64, 128, 256, "
                             f"512 = the reference), got {heatmap_size}")
        self.heatmap_radius = max(1, round(heatmap_radius * heatmap_size / REFERENCE_HEATMAP))  #: px of this map
        self.loss_weights = {"heatmap": heatmap_weight, "z": z_weight, "offset": offset_weight,
                        "visibility": visibility_weight, "class": class_weight}
        self.audio = FourBranchAudio(in_channels, kernels, feature_dim, dropout)
        self.visual = VisualEncoder(feature_dim, resnet_weights)
        self.gate = VisibilityGate(feature_dim, (256, 128))
        self.attention = AttentionBlock(feature_dim, heads, attention_dropout)
        self.classes = MLP((feature_dim, 256, 128, num_classes))
        self.trajectory = MLP((feature_dim, 256, 128, 30))
        self.z = MLP((feature_dim, 256, 100, 1))
        self.offset = MLP((feature_dim, 100, 2))
        self.heatmap = HeatmapDecoder(feature_dim, kernels, decoder_convs, HEATMAP_SEED, upsamplings)
        self.register_buffer("bev_bounds", torch.tensor(AVFDTI_BOUNDS, dtype=torch.float64))
        self.clipped_targets = 0  #: heat-map targets that lay outside the bounds (clipped to the border)
        self.heatmap_targets = 0  #: heat-map targets built so far

    def reduced_settings(self) -> dict[str, str]:
        settings = super().reduced_settings()
        if self.heatmap.size != REFERENCE_HEATMAP:
            settings["heatmap_size"] = f"{self.heatmap.size} (reference {REFERENCE_HEATMAP})"
        return settings

    # ------------------------------------------------------------------------------ bounds

    def set_bounds(self, bounds: list[list[float]] | torch.Tensor) -> None:
        """Set the bird's-eye area [[x_min, x_max], [y_min, y_max]] (m) that the heat map covers."""
        new = torch.as_tensor(bounds, dtype=torch.float64)
        if new.shape != (2, 2) or not torch.isfinite(new).all() or bool((new[:, 0] >= new[:, 1]).any()):
            raise ValueError(f"bounds must be [[x_min, x_max], [y_min, y_max]] with min < max, got {bounds}")
        current = self.bev_bounds.detach().cpu().double()
        default = torch.tensor(AVFDTI_BOUNDS, dtype=torch.float64)
        if not torch.equal(current, new) and not torch.allclose(current, default):
            log.warning("AV-FDTI bird's-eye bounds changed from %s to %s: heat maps learnt with the old bounds "
                        "now decode to other positions", current.tolist(), new.tolist())
        self.bev_bounds.copy_(new)

    def _grid(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Lower corner (x, y) and cell size (x, y) of the heat map, in metres (float64)."""
        bounds = self.bev_bounds.double()
        return bounds[:, 0], (bounds[:, 1] - bounds[:, 0]) / self.heatmap.size

    def decode(self, heatmap: torch.Tensor, offset: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Position B x 3 (m) from a heat map B x size x size, offsets B x 2 (cm) and heights B x 1 (m)."""
        size = self.heatmap.size
        if tuple(heatmap.shape[-2:]) != (size, size):
            raise ValueError(f"AV-FDTI decodes {size} x {size} heat maps (heatmap_size {size}), "
                             f"got {tuple(heatmap.shape[-2:])}")
        x_index = heatmap.sum(dim=1).argmax(dim=1)  # column sums -> x
        y_index = heatmap.sum(dim=2).argmax(dim=1)  # row sums -> y
        low, cell = self._grid()
        xy = low + torch.stack([x_index, y_index], dim=1).double() * cell
        return torch.cat([xy.to(offset.dtype) + offset / 100, z], dim=1)

    def target_cells(self, position: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Heat-map cell (x index, y index) B x 2, offset B x 2 (cm) and "was outside the bounds" B.

        The cell is floor((position - min) / cell size) and the offset the residual from the cell's lower
        corner, as AV-FDTI's ``obtain_gaussian`` (which first rounds to 1e-3 px; not reproduced). A
        position outside the bounds is clipped to the border first.
        """
        low, cell = self._grid()
        high = low + cell * self.heatmap.size
        xy = position[:, :2].double()
        outside = ((xy < low) | (xy > high)).any(dim=1)
        xy = torch.minimum(torch.maximum(xy, low), high)
        index = ((xy - low) / cell).floor().clamp(0, self.heatmap.size - 1)
        offset = ((xy - low - index * cell) * 100).to(position.dtype)
        return index.long(), offset, outside

    def heatmap_target(self, position: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Target heat map B x H x W (rows = y, columns = x), offset B x 2 (cm) and outside B, for positions B x 3."""
        index, offset, outside = self.target_cells(position)
        pixels = torch.arange(self.heatmap.size, device=position.device)
        distance = (pixels[None, :, None] - index[:, None, :]).double()  # B x size x (x, y)
        profile = gaussian_profile(distance, self.heatmap_radius).to(position.dtype)
        return profile[:, :, 1, None] * profile[:, None, :, 0], offset, outside

    # ------------------------------------------------------------------------------ forward and losses

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        self.check_inputs(inputs)
        audio = self.audio(inputs["audio_mel"])
        fused, visibility = self.gate(audio, self.visual(inputs["image"]))
        features = self.attention(fused, audio)
        logits = self.heatmap(features)
        heatmap = torch.sigmoid(logits)
        offset, z = self.offset(features), self.z(features)
        return {
            "position": self.decode(heatmap.detach(), offset, z),
            "heatmap": heatmap,
            "heatmap_logits": logits,
            "offset": offset,
            "z": z,
            "visibility_logits": visibility,
            "class_logits": self.classes(features),
            "trajectory": self.trajectory(features).view(-1, 10, 3),
        }

    def auxiliary_losses(
        self, outputs: dict[str, torch.Tensor], batch: dict[str, torch.Tensor], target: torch.Tensor,
        target_valid: torch.Tensor,
    ) -> dict[str, torch.Tensor]:
        w = self.loss_weights
        terms: dict[str, torch.Tensor] = {}
        if target_valid.any():
            position = target[target_valid]
            cells, offset, outside = self.target_cells(position)
            self._count_clipped(int(outside.sum()), len(position))
            logits = outputs["heatmap_logits"][target_valid]
            terms["heatmap"] = w["heatmap"] * peak_focal_loss(logits, cells, self.heatmap_radius)
            terms["z"] = w["z"] * F.mse_loss(outputs["z"][target_valid, 0], position[:, 2])
            terms["offset"] = w["offset"] * F.mse_loss(outputs["offset"][target_valid], offset)
        if w["visibility"] > 0 and "visible" in batch:
            terms["visibility"] = w["visibility"] * visibility_loss(outputs["visibility_logits"], batch["visible"])
        if w["class"] > 0 and "class_id" in batch:
            terms["class"] = w["class"] * classification_loss(outputs["class_logits"], batch["class_id"])
        return terms

    def _count_clipped(self, clipped: int, total: int) -> None:
        before = self.clipped_targets
        self.clipped_targets += clipped
        self.heatmap_targets += total
        if clipped and (before == 0 or int(math.log10(self.clipped_targets)) > int(math.log10(before))):
            log.warning("AV-FDTI: %d of %d heat-map targets lay outside the bird's-eye bounds %s and were clipped "
                        "to the border (set data.bev_bounds to cover the flights)", self.clipped_targets,
                        self.heatmap_targets, self.bev_bounds.tolist())
