"""A phase-aware student: a learned heat map over the steered response of the microphone pairs.

Why this shape. The position information is in the pair delays, and which point in space explains a
set of delays is geometry, not something to learn: the steered response power (SRP) of a point is
the pairs' GCC-PHAT read at that point's delays (and, over the reflecting roof, at the delays of the
ground-image paths), exactly as :mod:`zoo.nets.phase.srp_phat` computes it. So the first layer is that
fixed map: on a 3D grid of cubes over the flight region (1 m by default), every frame group's
correlations are read at each cube's delays (max-pooled over the delays the cube spans), for the
multipath and the direct-only terms; the groups' mean and maximum give four channels. What SRP-PHAT
cannot do is learned: a small 3D convolutional net turns the map into a heat map, learning what a
drone's response looks like against the failure modes (the diffuse ambient's coherence near the array,
a ground-reflection cross term that is too sharp or too flat, a peak smeared along range at 20 m,
evidence below a fixed detection threshold that is consistent over the frame groups). The position is
the heat map's expectation over the cube centres (a soft arg-max, differentiable and sub-cell).

Why it should generalise beyond its labels. The LiDAR teacher labels the nearer part of a flight
(its pseudo-labels are biased to short range), and a net that regresses coordinates from features
learns that prior. This net is fully convolutional and never sees a coordinate: it scores each cube
by its neighbourhood of the response, the same function everywhere, so it learns the appearance of a
source, not where the labelled sources were. Training: the task's position loss on the expectation,
plus a cross-entropy of the heat map against a Gaussian around the target (``heatmap_weight``,
``target_sigma``), which teaches the peak even while the expectation is still spread.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from datamodules.features import phase_recipe
from zoo.nets.base import TrajectoryNet
from zoo.nets.phase.null import white_noise_correlations
from zoo.nets.phase.steering import (
    SPEED_OF_SOUND,
    Steering,
    cube_grid,
    default_mics,
    geometry_groups,
    search_region,
    with_bounds,
)
from zoo.registry import register_model

#: windows of white noise that set each cube's null mean
NULL_WINDOWS = 64


@register_model("phase_student")
class PhaseStudent(TrajectoryNet):
    """Fixed SRP map on a 3D grid, a 3D CNN heat map and its soft arg-max (see the module docstring)."""

    inputs = {"audio_phase": "gcc_phat_2s_static"}
    category = "self-supervised"
    context_keys = ("mic_positions",)

    def __init__(
        self,
        in_channels: int = 4,
        mic_positions: str | list[list[float]] = "distributed4",
        speed_of_sound: float = SPEED_OF_SOUND,
        region_min: Sequence[float] = (-2.0, -5.0, 0.5),
        region_max: Sequence[float] = (8.0, 25.0, 25.0),
        step: float = 1.0,
        frame_groups: int = 6,
        ground_height: float | None = 0.0,
        reflection_weight: float = 1.0,
        min_range: float = 4.0,
        channels: int = 12,
        heatmap_weight: float = 1.0,
        target_sigma: float = 1.0,
        input_recipes: dict[str, str] | None = None,
    ):
        """Args:
            mic_positions: the geometry used when a batch carries none (a preset name or channels x 3, m).
            speed_of_sound, ground_height, reflection_weight, min_range: the steered response's physics,
                as in :class:`zoo.nets.phase.srp_phat.SRPPhat`.
            region_min, region_max: the grid's region (m, rig frame); x and y follow the data's
                ``bev_bounds`` when the task sets them.
            step: the grid's cube side (m).
            frame_groups: the window's frames are averaged in this many consecutive groups (each about
                0.3 s for 23 frames: the delays drift little within one) before steering.
            channels: width of the 3D convolutions.
            heatmap_weight: weight of the heat map's cross-entropy against a Gaussian around the target.
            target_sigma: that Gaussian's standard deviation (m).
        """
        super().__init__(in_channels, input_recipes=input_recipes)
        self.recipe = phase_recipe(self.inputs["audio_phase"])
        self.default_mics = default_mics(mic_positions, in_channels, self.model_name)
        self.region = search_region(region_min, region_max, self.model_name)
        self.steering = Steering(self.recipe, speed_of_sound, ground_height, reflection_weight, min_range)
        if step <= 0 or frame_groups < 1:
            raise ValueError(f"phase_student: step must be > 0 and frame_groups >= 1, got {step}, {frame_groups}")
        self.step, self.frame_groups = float(step), int(frame_groups)
        self.heatmap_weight, self.target_sigma = float(heatmap_weight), float(target_sigma)
        self.heatmap = nn.Sequential(
            nn.Conv3d(4, channels, 3, padding=1), nn.ReLU(),
            nn.Conv3d(channels, channels, 3, padding=2, dilation=2), nn.ReLU(),
            nn.Conv3d(channels, channels, 3, padding=4, dilation=4), nn.ReLU(),
            nn.Conv3d(channels, 1, 1),
        )
        self._null: dict[tuple, torch.Tensor] = {}
        self._grid: tuple[torch.Tensor, tuple[int, int, int]] | None = None

    def set_bounds(self, bounds: list[list[float]] | torch.Tensor) -> None:
        """Cover the data's bird's-eye area [[x_min, x_max], [y_min, y_max]] (m) with the grid."""
        self.region = with_bounds(self.region, bounds)
        self._grid = None

    def grid(self) -> tuple[torch.Tensor, tuple[int, int, int]]:
        """The cube centres (G x 3, x slowest, z fastest) and the grid's shape, built once per region."""
        if self._grid is None:
            self._grid = cube_grid(self.region, self.step)
        return self._grid

    def response(self, phase: torch.Tensor, mics_batch: torch.Tensor | None, points: torch.Tensor) -> torch.Tensor:
        """The fixed first layer: B x pairs x frames x lags -> B x 4 x G, the multipath and direct responses'
        mean and maximum over the frame groups, each as its excess over the null (white noise per
        microphone) at that cube, standardised over the window's grid. A cube near the array spans many
        delays, so its pooled response is high for noise too: without the null subtracted the map would
        favour the array's surroundings. The standardisation makes the map's shape, not the source's
        level, what the heat map reads (the level varies by tens of dB between drones and ranges)."""
        out = torch.empty(phase.shape[0], 4, points.shape[0])
        for mics, rows in geometry_groups(phase, mics_batch, self.default_mics, self.model_name):
            excess = self._raw_response(phase[rows].detach().cpu(), mics, points)
            excess = excess - self.null_mean(mics, points, phase.shape[2])
            centred = excess - excess.mean(dim=-1, keepdim=True)
            out[rows] = centred / centred.std(dim=-1, keepdim=True).clamp_min(1e-6)
        return out.to(phase.device)

    def _raw_response(self, phase: torch.Tensor, mics: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """B x pairs x frames x lags -> B x 4 x G (multipath, direct; mean over groups, then maximum)."""
        b, p, f, lags = phase.shape
        groups = torch.stack([chunk.mean(dim=2) for chunk in
                              torch.tensor_split(phase.float(), min(self.frame_groups, f), dim=2)], dim=1)
        values = self.steering.grid_response(groups.reshape(-1, p, lags), points, mics, self.step)
        values = values.reshape(b, groups.shape[1], 2, -1)
        return torch.cat([values.mean(dim=1), values.amax(dim=1)], dim=1)

    def null_mean(self, mics: torch.Tensor, points: torch.Tensor, frames: int) -> torch.Tensor:
        """Per channel and cube (4 x G), the mean response to independent white noise per microphone
        (``NULL_WINDOWS`` windows, seeded), computed once per geometry and grid."""
        key = (mics.numpy().tobytes(), points.numpy().tobytes(), frames)
        if key not in self._null:
            correlation = white_noise_correlations(self.recipe, mics.shape[0], NULL_WINDOWS, frames)
            with torch.no_grad():
                phase = correlation.transpose(0, 1)  # windows x pairs x frames x lags
                self._null[key] = self._raw_response(phase, mics, points).mean(dim=0)
        return self._null[key]

    def prepare(self, inputs: dict[str, torch.Tensor]) -> None:
        """Compute the null mean of the inputs' geometries (otherwise the first call does)."""
        phase = inputs["audio_phase"]
        for geometry, _ in geometry_groups(phase, inputs.get("mic_positions"), self.default_mics, self.model_name):
            self.null_mean(geometry, self.grid()[0], phase.shape[2])

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        points, shape = self.grid()
        with torch.no_grad():
            volume = self.response(inputs["audio_phase"], inputs.get("mic_positions"), points)
        logits = self.heatmap(volume.reshape(volume.shape[0], 4, *shape)).flatten(1)  # B x G
        probability = logits.softmax(dim=1)
        position = probability @ points.to(probability.device)
        return {"position": position, "heatmap_logits": logits, "peak_probability": probability.amax(dim=1)}

    def auxiliary_losses(self, outputs: dict[str, torch.Tensor], batch: dict[str, torch.Tensor],
                         target: torch.Tensor, target_valid: torch.Tensor) -> dict[str, torch.Tensor]:
        """Cross-entropy of the heat map against a normalised Gaussian around each valid target."""
        terms = super().auxiliary_losses(outputs, batch, target, target_valid)
        if self.heatmap_weight > 0 and target_valid.any():
            points = self.grid()[0].to(target.device)
            squared = torch.cdist(target[target_valid].float(), points).square()
            wanted = torch.softmax(-squared / (2 * self.target_sigma ** 2), dim=1)
            log_probability = F.log_softmax(outputs["heatmap_logits"][target_valid], dim=1)
            terms["heatmap"] = self.heatmap_weight * -(wanted * log_probability).sum(dim=1).mean()
        return terms
