"""SRP-PHAT: steered-response-power localisation from the phase recipe, no training.

For every short frame of a window, the steered response of a point ``g`` is the mean over
microphone pairs of their GCC-PHAT at the pair's delay ``(|g - m_i| - |g - m_j|) / c`` and, over a
reflecting ground (the roof, z = 0 in the rig frame), at the three delays where the ground image of
either path meets the other (image-direct, direct-image, image-image; terms that merge into one
peak count once). Over a hard ground each pair's correlation holds all four peaks at similar
heights, so a free-field search often locks onto a cross term and misplaces the range; steering
the image terms makes them confirm the true point instead. Points within ``min_range`` of the
array are not searched (the diffuse ambient's coherence peaks there). The
point of highest response is found coarse to fine: a grid over the flight region, where each cell
scores the largest correlation over the range of delays its volume spans (cells are split near the
array, where they span more), then cubes of half the step around the best cells, all on the
window's mean correlation (or on each of ``search_groups`` consecutive groups of its frames, whose
candidates serve that group's frames: a near drone's delays move too far in 2 s for one mean); then,
per frame, each of the best candidates is fitted to the delays of
that frame's correlation peaks near its own (Gauss-Newton), which resolves range from the
wavefront's curvature where a grid step could not, then hill-climbed on the frame's exact
response (linear interpolation between lags).

A frame counts as a detection when its peak response exceeds a threshold set from a null statistic:
the same search on independent white noise per microphone (nothing coherent, like channels shifted
apart by seconds): the quantile ``1 - false_alarm`` of the best frame of each null window, so
``false_alarm`` is a share of windows at any frame count; no ground truth is involved. A window's
position is the coordinate-wise median of its detected frames. With ``confirm_seconds``, a detected
window counts only when the sequence's previous detection is that recent and near (two detections
confirm a track), so an isolated false detection is neither output nor held. When no
frame of a window is detected, the last detected position of the same sequence is held for
``hold_seconds``, then the mean of the sequence's detections so far (``fallback: mean``) or the
search region's centre (``fallback: centre``) is returned (the centre before the first detection).
That memory follows the batches' ``sequence`` and ``time`` entries (windows in time order, as the
test and predict loaders give them); without them every window stands alone. A window whose batch entry
``uncorrected_clocks`` is true (nodes on separate clocks whose calibration the audio refused: its time
differences carry the clocks' offsets, milliseconds that move a peak by metres) is never a detection.

Outputs: ``position`` (B x 3), ``detection_score`` (B: the window's highest frame response over the
threshold; above 1 means detected), ``detected`` (B, bool) and ``state`` (B, indices into
:data:`~zoo.nets.phase.gate.WINDOW_STATES`: detected, held, fallback or uncorrected). ``fit`` trains
nothing: the net has no trainable parameters, so ``aaute fit`` returns at once and ``aaute test``
evaluates it directly.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Sequence

import torch

from datamodules.features import phase_recipe
from zoo.nets.base import TrajectoryNet
from zoo.nets.phase.gate import WINDOW_STATES, DetectionGate
from zoo.nets.phase.null import white_noise_correlations
from zoo.nets.phase.search import FIT_STEPS, CandidateSearch
from zoo.nets.phase.steering import SPEED_OF_SOUND, Steering, default_mics, geometry_groups, search_region, with_bounds
from zoo.registry import register_model

log = logging.getLogger(__name__)

#: null windows searched at once while setting a threshold
NULL_BATCH = 64
#: bumped whenever the search changes what it finds, so stored thresholds of older code are not reused
THRESHOLD_VERSION = 4


@register_model("srp_phat")
class SRPPhat(TrajectoryNet):
    """Steered response power with PHAT weighting over a 3D grid (see the module docstring).

    It composes the phase pieces: ``steering`` (:class:`~zoo.nets.phase.steering.Steering`, the geometry),
    ``search`` (:class:`~zoo.nets.phase.search.CandidateSearch`, which owns the region) and ``gate``
    (:class:`~zoo.nets.phase.gate.DetectionGate`, the per-sequence memory); it keeps the null thresholds.
    """

    inputs = {"audio_phase": "gcc_phat"}
    category = "non-learned"
    trains_position = False
    context_keys = ("mic_positions", "time", "sequence", "uncorrected_clocks")

    def __init__(
        self,
        in_channels: int = 4,
        mic_positions: str | list[list[float]] = "distributed4",
        speed_of_sound: float = SPEED_OF_SOUND,
        region_min: Sequence[float] = (-2.0, -5.0, 0.5),
        region_max: Sequence[float] = (8.0, 25.0, 25.0),
        coarse_step: float = 1.0,
        fine_step: float = 0.0625,
        candidates: int = 32,
        frame_candidates: int = 4,
        search_groups: int = 1,
        false_alarm: float = 0.01,
        null_windows: int = 300,
        hold_seconds: float = 10.0,
        confirm_seconds: float = 0.0,
        confirm_distance: float = 5.0,
        ground_height: float | None = 0.0,
        reflection_weight: float = 1.0,
        refine_levels: int = 1,
        fit_delays: bool = True,
        fit_steps: int = FIT_STEPS,
        min_range: float = 4.0,
        fallback: str = "mean",
        input_recipes: dict[str, str] | None = None,
    ):
        """Args:
            mic_positions: the geometry used when a batch carries none (a preset name or channels x 3, m).
            speed_of_sound: m/s (349: the simulator's 30 C air).
            region_min, region_max: the search region (m, rig frame); x and y follow the data's
                ``bev_bounds`` when the task sets them. The default is the MMAUD flight region.
            coarse_step: the grid's cell side (m) far from the array; cells are halved near it, down to
                ``fine_step``.
            candidates: best cells kept at each level of a window's search.
            frame_candidates: best cells kept per frame before the exact last level.
            search_groups: the grid levels search this many consecutive groups of a window's frames
                (each on its frames' mean correlation) and each frame fits its own group's candidates;
                1: the whole window's mean.
            false_alarm: share of null windows allowed over each detection threshold.
            null_windows: windows of white noise that set the thresholds.
            hold_seconds: how long a sequence keeps its last detection before falling back to its mean.
            confirm_seconds, confirm_distance: a detection counts only when the sequence's previous one
                lies within ``confirm_seconds`` before it and ``confirm_distance`` (m) of it (a track is
                confirmed by two detections, as radar trackers confirm tracks), so an isolated false
                detection is neither output nor held; 0 s: every detection counts.
            ground_height: z (m, rig frame) of the reflecting ground plane (the roof surface is z = 0 in
                the rig frame), or None for free-field steering. Each pair's correlation then holds, besides
                the direct-direct peak, peaks where the ground image of one or both paths meets the other:
                steering all four lets the reflection confirm the direct peak instead of competing with it.
            reflection_weight: weight of each of the three reflected terms against the direct one (1: a
                hard ground such as concrete, reflection factor about 0.95).
            refine_levels: per frame, levels of 27-point refinement (from ``2 ** (levels - 1) * fine_step``
                down to ``fine_step``) on the exact multipath response after the delay fit.
            fit_delays: fit each frame's candidates to its direct pair delays (Gauss-Newton) first.
            fit_steps: Gauss-Newton steps at most (the fit stops earlier once no candidate moves 1 mm; fewer
                than the default 30 cost accuracy: see README, "The phase localisers live").
            fallback: after the hold, ``mean`` (of the sequence's detections so far) or ``centre`` (of
                the search region: the flight region's prior, unbiased by false or near detections).
            min_range: points closer than this to the microphones' centre (m) score 0: the drone keeps
                clear of the rig, and the diffuse ambient's coherence makes false peaks inside the array.
        """
        super().__init__(in_channels, input_recipes=input_recipes)
        self.recipe = phase_recipe(self.inputs["audio_phase"])
        self.default_mics = default_mics(mic_positions, in_channels, self.model_name)
        self.steering = Steering(self.recipe, speed_of_sound, ground_height, reflection_weight, min_range)
        self.search = CandidateSearch(self.steering, search_region(region_min, region_max, self.model_name),
                                      coarse_step, fine_step, candidates, frame_candidates, search_groups,
                                      refine_levels, fit_delays, fit_steps)
        self.false_alarm, self.null_windows = float(false_alarm), int(null_windows)
        self.gate = DetectionGate(hold_seconds, confirm_seconds, confirm_distance, fallback)
        self._thresholds: dict[bytes, float] = {}

    # ------------------------------------------------------------------------------ configuration

    @property
    def region(self) -> torch.Tensor:
        """The search region (3 x 2: per axis min and max, m, rig frame)."""
        return self.search.region

    def set_bounds(self, bounds: list[list[float]] | torch.Tensor) -> None:
        """Search x and y inside the data's bird's-eye area [[x_min, x_max], [y_min, y_max]] (m)."""
        self.search.set_region(with_bounds(self.region, bounds))
        self._thresholds.clear()

    def _check_region(self, mics: torch.Tensor) -> None:
        centre = mics.mean(dim=0)
        outside = (centre < self.region[:, 0] - 5.0) | (centre > self.region[:, 1] + 5.0)
        if bool(outside.any()):
            log.warning("srp_phat: the search region %s lies more than 5 m from the microphones' centre %s; "
                        "check region_min/region_max and the data's bev_bounds",
                        self.region.tolist(), [round(v, 2) for v in centre.tolist()])

    # ------------------------------------------------------------------------------ null statistic

    def threshold(self, mics: torch.Tensor) -> float:
        """The detection threshold of a geometry: the ``1 - false_alarm`` quantile, over null windows, of
        the peak response of their best frame (so ``false_alarm`` is the share of null windows with a
        detection, whatever the recipe's frame count)."""
        key = mics.numpy().tobytes()
        if key not in self._thresholds:
            windows = self.null_windows
            correlation = white_noise_correlations(self.recipe, mics.shape[0], windows, self.recipe.frames)
            found = [self.search.peaks(correlation.permute(1, 2, 0, 3)[start:start + NULL_BATCH], mics)
                     for start in range(0, windows, NULL_BATCH)]
            best = torch.cat([peaks.amax(dim=1) for _, peaks in found])  # each window's best frame
            value = float(torch.quantile(best, 1.0 - self.false_alarm))
            self._thresholds[key] = value
            log.info("srp_phat: detection threshold %.4f (null quantile %.3f of the best frame of %d white-noise "
                     "windows)", value, 1.0 - self.false_alarm, windows)
        return self._thresholds[key]

    def threshold_key(self, mics: torch.Tensor) -> str:
        """A digest of everything a geometry's threshold depends on (recipe, physics, search settings, null
        statistic, geometry, :data:`THRESHOLD_VERSION`), so a stored threshold is reused only where it holds."""
        search = self.search
        settings = (THRESHOLD_VERSION, self.recipe.key(), self.steering.speed_of_sound, self.steering.ground_height,
                    self.steering.reflection_weight, self.steering.min_range, self.region.tolist(), search.coarse_step,
                    search.fine_step, search.candidates, search.frame_candidates, search.search_groups,
                    search.refine_levels, search.uses_delay_fit, self.false_alarm, self.null_windows,
                    *((search.fit_steps,) if search.fit_steps != FIT_STEPS else ()),
                    mics.double().numpy().tobytes().hex())
        return hashlib.sha256(repr(settings).encode()).hexdigest()[:24]

    def known_threshold(self, mics: torch.Tensor) -> float | None:
        """The geometry's threshold if it has been computed or set (:meth:`set_threshold`), else None."""
        return self._thresholds.get(mics.numpy().tobytes())

    def set_threshold(self, mics: torch.Tensor, value: float) -> None:
        """Use ``value`` as the geometry's threshold (one stored under its :meth:`threshold_key`)."""
        self._thresholds[mics.numpy().tobytes()] = float(value)

    def prepare(self, inputs: dict[str, torch.Tensor]) -> None:
        """Build the search's tables and the detection threshold of the inputs' geometry (otherwise the first
        call does)."""
        for geometry, _ in self.geometry_groups(inputs["audio_phase"], inputs.get("mic_positions")):
            self.search.prepare(geometry)
            self.threshold(geometry)

    def geometry_groups(self, phase: torch.Tensor, mics_batch: torch.Tensor | None
                        ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """:func:`~zoo.nets.phase.steering.geometry_groups` with this net's default geometry and name."""
        return geometry_groups(phase, mics_batch, self.default_mics, self.model_name)

    # ------------------------------------------------------------------------------ forward

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        phase = inputs["audio_phase"]
        b = phase.shape[0]
        mics_batch = inputs.get("mic_positions")
        positions = torch.empty(b, 3)
        scores = torch.empty(b)
        detected = torch.empty(b, dtype=torch.bool)
        with torch.no_grad():
            for mics, rows in self.geometry_groups(phase, mics_batch):
                if mics.numpy().tobytes() not in self._thresholds:
                    self._check_region(mics)
                threshold = self.threshold(mics)
                points, peak = self.search.peaks(phase[rows].detach().cpu().permute(0, 2, 1, 3), mics)
                hit = peak > threshold
                positions[rows] = self.window_positions(points, hit)
                scores[rows] = peak.max(dim=1).values / threshold
                detected[rows] = hit.any(dim=1)
        uncorrected = inputs.get("uncorrected_clocks")
        if uncorrected is not None:  # time differences off by the nodes' clock offsets: a peak there is no fix
            uncorrected = uncorrected.to(torch.bool).cpu()
            detected &= ~uncorrected
        positions, detected = self.hold_or_fallback(positions, detected, inputs.get("sequence"), inputs.get("time"))
        states = torch.tensor([WINDOW_STATES.index(state) for state in self.gate.states], dtype=torch.long)
        if uncorrected is not None:
            states[uncorrected] = WINDOW_STATES.index("uncorrected")
        return {"position": positions.to(phase.dtype).to(phase.device),
                "detection_score": scores.to(phase.dtype).to(phase.device), "detected": detected.to(phase.device),
                "state": states.to(phase.device)}

    @staticmethod
    def window_positions(points: torch.Tensor, hit: torch.Tensor) -> torch.Tensor:
        """A window's position (B x 3) from its frames' points (B x F x 3): the coordinate-wise median of the
        frames that ``hit`` (B x F) marks detected; NaN where none is."""
        return torch.where(hit[..., None], points, torch.full_like(points, float("nan"))).nanmedian(dim=1).values

    def hold_or_fallback(self, positions: torch.Tensor, detected: torch.Tensor, sequence: torch.Tensor | None,
                         time: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Positions (B x 3, NaN where not ``detected``) with the gate's hold and fallback applied, and the
        detections that count (:meth:`zoo.nets.phase.gate.DetectionGate.apply`; its centre: the region's)."""
        return self.gate.apply(positions, detected, sequence, time, self.region.mean(dim=1).float())
