"""Self-calibration of the audio nodes' clock offsets from a recording's own audio.

Four single-microphone nodes give, per frame, three independent time differences for three
unknown source coordinates, so constant offsets between their clocks cannot be told from the
direct-path time differences alone (``benchmarks/studies/clock_sensitivity.py --identifiability``).
Each microphone also hears the source a second time via the roof (its ground image): the delay
``tau_i = (|s - m_i'| - |s - m_i|) / c`` between the two paths lies inside one node's own clock, so no
offset touches it. Per frame this estimator measures

- each channel's reflection delay: the peak, over ``0 .. 2 h_i / c``, of the cepstrum of its log power
  spectrum minus the channels' mean log spectrum (the source spectrum cancels; a reflection of factor
  ``r`` adds ``2 r cos(w tau_i)`` to the log spectrum, a cepstral peak at ``tau_i``), and
- each pair's apparent time difference: the lag of the GCC-PHAT correlation (the phase front end's
  cross-spectra, :class:`~datamodules.features.phase.GccPhat`; the mean cross-spectrum over the
  stretch, static sources such as a rooftop HVAC unit, subtracted first) that best explains its four
  multipath peaks (direct-direct, image-direct, direct-image, image-image) given the two delays,

then fits one source position per frame and the offsets and drifts shared by all frames (node 0 = 0)
by robust least squares (:func:`scipy.optimize.least_squares`, soft-L1 loss). When a static source is heard
throughout (a rooftop HVAC unit), its time differences drift along straight lines whose slopes are the drifts,
whatever its position (:mod:`datamodules.features.static_drift`): the drifts are then taken from it, the
cross-spectra corrected for them (so the static source stays static and its mean is subtracted) and the
offsets fitted alone. The uncertainty is the cluster-robust sandwich of that fit over 2 s clusters of
frames (the first-order delete-a-cluster jackknife) with a floor in quadrature, the error that no spread
over the frames shows;
refits leaving out blocks of frames (``uncertainty="jackknife"``) start from the solution and stop at their
iteration limit before they have moved as far as they would, so their spread is too small.

Convention (as the simulator's ``clocks_truth``): node ``n``'s sample ``k`` is taken at true time
``k / fs * (1 + drift_n) + offset_n``, so its audio shows a sound ``offset_n + drift_n * t`` seconds
early; :func:`correct_cross_spectra` undoes that on pair cross-spectra by the phase ramp
``exp(-i w (o_i - o_j))``.
"""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch

from datamodules.errors import ConfigError
from datamodules.features.phase import (
    SPEED_OF_SOUND,
    GccPhat,
    PhaseRecipe,
    correct_cross_spectra,
    mic_pairs,
    parabolic_offset,
)
from datamodules.features.static_drift import StaticDrift, static_source_drift
from datamodules.recording import AudioStream, RecordingError

#: when phase features correct the nodes' clocks: ``auto`` when the recording says its nodes do not share one
CLOCK_CALIBRATION_MODES = ("auto", "on", "off")


def check_mode(mode: str) -> str:
    """``mode`` if it is one of :data:`CLOCK_CALIBRATION_MODES` (else ConfigError, one line)."""
    if mode not in CLOCK_CALIBRATION_MODES:
        raise ConfigError(f"clock_calibration must be one of {CLOCK_CALIBRATION_MODES}, not {mode!r}")
    return mode


def wants_calibration(mode: str, meta: dict[str, Any]) -> bool:
    """Whether ``mode`` (checked by :func:`check_mode`) calibrates a recording with metadata ``meta``."""
    return mode == "on" or (mode == "auto" and meta.get("nodes_share_clock", True) is False)


class ClockCalibrationError(RecordingError):
    """A recording the calibration cannot use (no positions, too short, too few usable frames, an unreliable fit)."""


@dataclass(frozen=True)
class ClockCalibrationConfig:
    """Settings of :func:`estimate_clock_offsets` (defaults: the simulator's rooftop rig)."""

    frame_seconds: float = 4096 / 48000  #: the phase recipes' frame (85.3 ms)
    block_frames: int = 2  #: consecutive frames averaged into one block (0.17 s)
    max_blocks: int = 480  #: at most this many blocks, spread evenly over the recording (82 s)
    min_blocks: int = 10  #: fewer usable blocks: refuse
    f_min: float = 300.0  #: band of both measurements (Hz): above wind and HVAC rumble
    f_max: float = 8000.0
    lag_rate: float = 96000.0  #: correlation lag resolution 10.4 us (band-limited interpolation)
    quefrency_step: float = 5e-6  #: cepstrum grid (s)
    min_quefrency: float = 1.5e-4  #: below: the cepstrum's spectral-envelope lobe (about 1 / band)
    max_offset: float = 0.01  #: largest offset between two nodes searched (s)
    speed_of_sound: float = SPEED_OF_SOUND
    ground_height: float = 0.0  #: z of the reflecting roof in the rig frame (m)
    sigma: float = 2e-5  #: scale of a measurement's error (s): residuals are divided by it
    #: error of an offset (s) that no spread over the frames shows, added in quadrature to its std (dev flights:
    #: within 1 / 2 std 77-89 / 93-96 % of 10 s and 30 s stretch offsets, 53-72 / 81-92 % without; README)
    std_floor: float = 2e-5
    loss_scale: float = 3.0  #: soft-L1 knee, in units of ``sigma``
    min_peak: float = 4.0  #: blocks whose multipath score (mean over pairs, in units of the correlation's
    #: robust spread) is below: no coherent source
    #: also fit a constant drift per node (20 ppm is 1.2 ms over a minute); None: keep them only when one is
    #: ``drift_significance`` standard errors from zero (else refit the offsets alone). Always, as a drift left
    #: out bends the offsets along the rig's weakly observed direction: on 10 s stretches of development flights,
    #: drifts of 2-12 ppm left out moved them by up to 0.43 ms
    fit_drift: bool | None = True
    drift_significance: float = 3.0
    #: take the drifts from a static source when one is heard throughout (a rooftop HVAC unit:
    #: :func:`~datamodules.features.static_drift.static_source_drift`, a tenth of a ppm on development flights)
    #: and fit the offsets alone; without one, ``fit_drift`` decides
    static_drift: bool = True
    #: how the offsets' standard errors are found: ``sandwich``, the cluster-robust sandwich of the robust fit
    #: over clusters of ``cluster_seconds`` (a linearised delete-a-cluster jackknife: no refits), or
    #: ``jackknife``, refits leaving out each of ``jackknife_blocks`` contiguous blocks of frames
    uncertainty: str = "sandwich"
    cluster_seconds: float = 2.0  #: the frames' residuals are correlated over less than a second (dev flights)
    jackknife_blocks: int = 5  #: blocks of the uncertainty's jackknife (0: none)
    max_residual: float = 3e-5  #: a fit whose robust residual RMS (s) is above this explains no source: refuse
    max_std: float = 3e-4  #: a fit with any offset's jackknife standard error (s) above this: refuse
    max_drift_ppm: float = 100.0  #: a fitted drift beyond this is no audio crystal's (+-20-50 ppm): refuse

    def key(self) -> str:
        """A short digest of the settings (for cache keys)."""
        return hashlib.sha256(repr(sorted(asdict(self).items())).encode()).hexdigest()[:12]


@dataclass
class ClockCalibration:
    """Estimated clocks of a recording's nodes (node 0 is the reference)."""

    offsets_s: np.ndarray  #: per node, offset at the audio's first sample (s)
    offsets_std_s: np.ndarray  #: jackknife standard error (s); NaN without a jackknife
    drifts_ppm: np.ndarray  #: per node (0 unless fitted)
    drifts_std_ppm: np.ndarray
    frames: int  #: frames used
    residual_rms_s: float  #: robust RMS of the fit's residuals (s)
    positions: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 3)))  #: per frame (m)
    times: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))  #: frame centres (s from sample 0)
    #: the drifts were told by a static source (:func:`static_drifts`), not fitted with the offsets
    static_drift: bool = False

    def offsets_at(self, t: float | np.ndarray) -> np.ndarray:
        """Each node's offset (s) at ``t`` seconds after the first sample (..., nodes)."""
        t = np.asarray(t, dtype=np.float64)[..., None]
        return self.offsets_s + self.drifts_ppm * 1e-6 * t

    def meta(self) -> dict[str, Any]:
        """The estimate for a recording's metadata (``clock_calibration``)."""
        return {"offsets_s": self.offsets_s.tolist(), "offsets_std_s": self.offsets_std_s.tolist(),
                "drifts_ppm": self.drifts_ppm.tolist(), "drifts_std_ppm": self.drifts_std_ppm.tolist(),
                "frames": int(self.frames), "residual_rms_s": float(self.residual_rms_s),
                "static_drift": bool(self.static_drift)}

    def to_array(self) -> np.ndarray:
        """5 x nodes: offsets, their std, drifts, their std, then [frames, residual RMS, static drift, 0 ...]
        (for caches; with two nodes the static drift flag is not kept)."""
        extra = np.zeros(self.offsets_s.size)
        extra[:3] = [self.frames, self.residual_rms_s, float(self.static_drift)][:extra.size]
        return np.stack([self.offsets_s, self.offsets_std_s, self.drifts_ppm, self.drifts_std_ppm, extra])

    @classmethod
    def from_array(cls, array: np.ndarray) -> ClockCalibration:
        array = np.asarray(array, dtype=np.float64)
        static = bool(array[4, 2]) if array.shape[1] > 2 else False
        return cls(*array[:4].copy(), frames=int(array[4, 0]), residual_rms_s=float(array[4, 1]), static_drift=static)

    def key(self) -> str:
        """A short digest of the correction it makes (for feature cache keys)."""
        rounded = np.round(np.stack([self.offsets_s * 1e9, self.drifts_ppm * 1e3]))  # ns and ppb
        return hashlib.sha256(rounded.tobytes()).hexdigest()[:12]

    def summary(self) -> str:
        """One line: offsets (ms) with their uncertainty, and drifts if fitted."""
        parts = [f"{1e3 * o:+.3f} +- {1e3 * s:.3f}" for o, s in zip(self.offsets_s, self.offsets_std_s, strict=True)]
        text = f"clock offsets (ms, node 0 = 0): {', '.join(parts)} from {self.frames} frames"
        if np.any(self.drifts_ppm):
            source = ", from a static source" if self.static_drift else ""
            text += f"; drifts (ppm{source}): " + ", ".join(f"{d:+.1f}" for d in self.drifts_ppm)
        return text


# ------------------------------------------------------------------------------ measurements


@dataclass
class FrameMeasurements:
    """What each used frame says: reflection delays (F x C), pair time differences (F x P), frame times."""

    times: np.ndarray  #: frame centres, seconds after the first sample
    reflection: np.ndarray  #: F x C (s); NaN where no peak
    tdoa: np.ndarray  #: F x P (s), apparent (offset-corrupted)
    score: np.ndarray  #: B: mean over pairs of the chosen multipath score over the correlation's spread


def _block_starts(audio: AudioStream, config: ClockCalibrationConfig, frame: int) -> np.ndarray:
    """First sample of each block (``block_frames`` consecutive frames), at most ``max_blocks`` spread evenly."""
    span = frame * config.block_frames
    starts = np.arange(0, audio.num_samples - span + 1, span)
    if starts.size > config.max_blocks:
        starts = starts[np.linspace(0, starts.size - 1, config.max_blocks).round().astype(int)]
    return starts


def _interp(corr: np.ndarray, lags: np.ndarray, rate: float, half: int) -> np.ndarray:
    """Linear interpolation of ``corr`` (..., lags centred on 0, ``half`` each side) at ``lags`` (s); 0 outside."""
    position = lags * rate + half
    base = np.floor(position).astype(np.int64)
    frac = position - base
    inside = (base >= 0) & (base + 1 < corr.shape[-1])
    base = np.clip(base, 0, corr.shape[-1] - 2)
    value = np.take_along_axis(corr, base, -1) * (1 - frac) + np.take_along_axis(corr, base + 1, -1) * frac
    return np.where(inside, value, 0.0)


def _max_tdoa(mics: np.ndarray, config: ClockCalibrationConfig) -> float:
    """The largest pair time difference searched (s): the widest pair's geometric delay plus ``max_offset``."""
    mics = np.asarray(mics, dtype=np.float64)
    spread = max(np.linalg.norm(mics[i] - mics[j]) for i, j in mic_pairs(mics.shape[0])) / config.speed_of_sound
    return spread + config.max_offset


def measure(audio: AudioStream, config: ClockCalibrationConfig = ClockCalibrationConfig(),
            drifts_ppm: np.ndarray | None = None) -> FrameMeasurements:
    """Reflection delays and multipath-matched pair time differences of blocks spread over ``audio``.

    Each frame gives a PHAT correlation per pair (its cross-spectra minus their mean over all blocks:
    static sources) and a cepstrum per channel; a block averages its frames' correlations and cepstra
    (in the lag domain, so a moving source smears its peaks a little instead of cancelling them). With known
    ``drifts_ppm`` (per node) the cross-spectra are corrected for them first, so a static source stays static
    and the time differences carry the offsets alone.
    """
    fs, channels = float(audio.sample_rate), audio.num_channels
    c = config.speed_of_sound
    mics = np.asarray(audio.mic_positions, dtype=np.float64)
    heights = mics[:, 2] - config.ground_height
    if np.any(heights <= 0):
        raise ClockCalibrationError(f"clock calibration needs microphones above the ground plane "
                                    f"(z > {config.ground_height} m), got heights {heights.tolist()}")
    max_reflection = 2 * heights / c
    pairs = mic_pairs(channels)
    max_tdoa = _max_tdoa(mics, config)
    recipe = PhaseRecipe("clock_calibration", frame_seconds=config.frame_seconds, frames=config.block_frames,
                         max_delay=max_tdoa + float(max_reflection.max()) + 1e-3, lag_rate=config.lag_rate,
                         f_min=config.f_min, f_max=config.f_max)
    gcc = GccPhat(recipe, fs, channels)
    starts = _block_starts(audio, config, gcc.frame)
    if starts.size < config.min_blocks:
        raise ClockCalibrationError(f"clock calibration needs at least {config.min_blocks} blocks of "
                                    f"{config.block_frames} x {config.frame_seconds:.3f} s; the audio "
                                    f"({audio.duration:.1f} s) gives {starts.size}")
    freqs = np.fft.rfftfreq(gcc.n_fft, 1.0 / fs)[gcc.band]
    quefrency = np.arange(config.min_quefrency, float(max_reflection.max()) + config.quefrency_step,
                          config.quefrency_step)
    basis = torch.from_numpy(np.cos(2 * np.pi * freqs[:, None] * quefrency[None, :]) * (2.0 / freqs.size))

    def spectra_of(start: int) -> torch.Tensor:
        samples = audio.read(int(start), int(start) + gcc.frame * config.block_frames)
        if not np.isfinite(samples).all():
            raise ClockCalibrationError(f"clock calibration: the audio at {start / fs:.2f} s holds NaN or "
                                        f"infinite samples")
        x = torch.from_numpy(np.ascontiguousarray(samples)).reshape(channels, config.block_frames, gcc.frame)
        return torch.fft.rfft(x * gcc.window, n=gcc.n_fft)[..., gcc.band]

    with torch.no_grad():
        band_freqs = torch.from_numpy(freqs)
        frame_centres = (np.arange(config.block_frames) + 0.5) * gcc.frame / fs

        def cross_of(spectra: torch.Tensor, start: int) -> torch.Tensor:
            cross = (spectra[gcc.first] * spectra[gcc.second].conj()).to(torch.complex128)
            if drifts_ppm is None:
                return cross
            drift = np.asarray(drifts_ppm, dtype=np.float64) * 1e-6 * (start / fs + frame_centres)[:, None]
            return correct_cross_spectra(cross, band_freqs, drift, gcc.first, gcc.second)

        block_spectra = [spectra_of(start) for start in starts]  # each C x F x K, read and transformed once
        # the pairs' cross-spectra are formed again below rather than kept: 3x the spectra's memory
        static = sum(cross_of(spectra, start).mean(dim=1) for spectra, start in zip(block_spectra, starts,
                                                                                     strict=True)) / len(starts)
        corr_blocks, cepstrum_blocks = [], []
        for spectra, start in zip(block_spectra, starts, strict=True):
            cross = cross_of(spectra, start) - static[:, None, :]
            corr_blocks.append(gcc.correlate(cross).mean(dim=1).double())
            log_power = torch.log(spectra.abs().double() ** 2 + 1e-30)
            relative = log_power - log_power.mean(dim=0, keepdim=True)
            relative = relative - relative.mean(dim=-1, keepdim=True)
            cepstrum_blocks.append((relative @ basis).mean(dim=1))
        corr = torch.stack(corr_blocks, dim=1).numpy()  # P x B x lags
        cepstrum = torch.stack(cepstrum_blocks, dim=1).numpy()  # C x B x Q
    half = (corr.shape[-1] - 1) // 2
    rate = recipe.lag_rate
    blocks = len(starts)

    # reflection delays: the peak of each channel's cepstrum below its 2 h / c
    cepstrum[np.broadcast_to(quefrency > max_reflection[:, None, None], cepstrum.shape)] = -np.inf
    best = cepstrum.argmax(axis=-1)
    reflection = (quefrency[best] + parabolic_offset(cepstrum, best) * config.quefrency_step).T  # B x C

    # pair time differences: the lag whose four multipath peaks score highest
    lag_grid = np.arange(-half, half + 1) / rate
    candidates = lag_grid[np.abs(lag_grid) <= max_tdoa]
    tdoa = np.empty((blocks, len(pairs)))
    score = np.empty((blocks, len(pairs)))
    d = np.broadcast_to(candidates[None, :], (blocks, candidates.size))
    for p, (i, j) in enumerate(pairs):
        ti, tj = reflection[:, i][:, None], reflection[:, j][:, None]
        g = corr[p]
        total = (_interp(g, d, rate, half) + _interp(g, d + ti, rate, half) + _interp(g, d - tj, rate, half)
                 + _interp(g, d + ti - tj, rate, half))
        k = total.argmax(axis=1)
        tdoa[:, p] = candidates[k] + parabolic_offset(total, k) / rate
        noise = 1.4826 * np.median(np.abs(g - np.median(g, axis=1, keepdims=True)), axis=1)
        score[:, p] = total[np.arange(blocks), k] / 4 / np.maximum(noise, 1e-12)
    times = (starts + gcc.frame * config.block_frames / 2) / fs
    return FrameMeasurements(times, reflection, tdoa, score.mean(axis=1))


# ------------------------------------------------------------------------------ fit


def _ground_images(mics: np.ndarray, ground_height: float) -> np.ndarray:
    """The microphones' mirror images in the ground plane ``z = ground_height``."""
    return mics * [1, 1, -1] + [0, 0, 2 * ground_height]


#: fits of at most this many frames take exact trust-region steps (:meth:`_Model.solve`); a 30 s stretch has 176
EXACT_FRAMES = 200


class _Model:
    """Residuals of the joint fit: per frame a position, shared offsets (and drifts) of nodes 1.."""

    def __init__(self, mics: np.ndarray, m: FrameMeasurements, config: ClockCalibrationConfig):
        self.mics, self.m, self.config = mics, m, config
        self.images = _ground_images(mics, config.ground_height)
        self.channels = mics.shape[0]
        pairs = mic_pairs(self.channels)
        self.first = np.array([i for i, _ in pairs])
        self.second = np.array([j for _, j in pairs])
        self.clock_params = (self.channels - 1) * (2 if config.fit_drift else 1)

    def clocks(self, theta: np.ndarray, times: np.ndarray) -> np.ndarray:
        """F x C offsets (s) at the frame times."""
        n = self.channels - 1
        offsets = np.concatenate([[0.0], theta[:n]])
        drifts = np.concatenate([[0.0], theta[n:2 * n] * 1e-6]) if self.config.fit_drift else np.zeros(self.channels)
        return offsets[None, :] + drifts[None, :] * times[:, None]

    def residuals(self, theta: np.ndarray, frames: np.ndarray) -> np.ndarray:
        c, sigma = self.config.speed_of_sound, self.config.sigma
        s = theta[self.clock_params:].reshape(-1, 3)
        direct = np.linalg.norm(s[:, None, :] - self.mics[None], axis=-1) / c  # F x C
        image = np.linalg.norm(s[:, None, :] - self.images[None], axis=-1) / c
        apparent = direct - self.clocks(theta, self.m.times[frames])
        r_tdoa = self.m.tdoa[frames] - (apparent[:, self.first] - apparent[:, self.second])
        r_refl = self.m.reflection[frames] - (image - direct)
        return np.concatenate([r_tdoa.ravel(), r_refl.ravel()]) / sigma

    def jacobian(self, theta: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """The residuals' Jacobian (rows as :meth:`residuals`, dense) at ``theta``."""
        c, sigma, n = self.config.speed_of_sound, self.config.sigma, self.channels - 1
        count, pairs = frames.size, len(self.first)
        s = theta[self.clock_params:].reshape(-1, 3)
        to_mic = s[:, None, :] - self.mics[None]
        to_image = s[:, None, :] - self.images[None]
        u = to_mic / np.linalg.norm(to_mic, axis=-1, keepdims=True) / (c * sigma)  # F x C x 3: d(direct)/ds
        v = to_image / np.linalg.norm(to_image, axis=-1, keepdims=True) / (c * sigma)
        jac = np.zeros((count * (pairs + self.channels), self.clock_params + 3 * count))
        rows_t = np.arange(count)[:, None] * pairs + np.arange(pairs)[None, :]  # F x P
        for sign, node in ((1.0, self.first), (-1.0, self.second)):  # r = tdoa - (d_i - o_i) + (d_j - o_j)
            for p, k in enumerate(node):
                if k == 0:
                    continue
                jac[rows_t[:, p], k - 1] += sign / sigma
                if self.config.fit_drift:
                    jac[rows_t[:, p], n + k - 1] += sign * 1e-6 * self.m.times[frames] / sigma
        rows_r = count * pairs + np.arange(count)[:, None] * self.channels + np.arange(self.channels)[None, :]
        for f in range(count):
            columns = slice(self.clock_params + 3 * f, self.clock_params + 3 * f + 3)
            jac[rows_t[f], columns] = -(u[f, self.first] - u[f, self.second])
            jac[rows_r[f], columns] = -(v[f] - u[f])
        return jac

    def sparsity(self, count: int):
        from scipy.sparse import lil_matrix

        pairs, channels = len(self.first), self.channels
        rows = count * (pairs + channels)
        pattern = lil_matrix((rows, self.clock_params + 3 * count), dtype=np.int8)
        for f in range(count):
            position = slice(self.clock_params + 3 * f, self.clock_params + 3 * f + 3)
            pattern[f * pairs:(f + 1) * pairs, :self.clock_params] = 1
            pattern[f * pairs:(f + 1) * pairs, position] = 1
            base = count * pairs + f * channels
            pattern[base:base + channels, position] = 1
        return pattern

    def solve(self, frames: np.ndarray, start: np.ndarray):
        """The robust fit from ``start``: exact trust-region steps on the analytic Jacobian up to
        :data:`EXACT_FRAMES` frames, else iterative (LSMR) steps on a finite-difference sparse one.

        The offsets lie in a long, flat valley of the cost (traded against every frame's position): iterative
        steps crawl along it and stop at the evaluation limit short of the minimum (a 10 s stretch with drifts
        fitted: 0.37 ms from it after 200 evaluations), exact steps reach it in 20-45. An exact step factors the
        dense Jacobian, so a whole minute of frames (about 350) takes 7x the CPU; there the iterative steps
        converge (the same offsets within 0.001 ms on a development flight)."""
        from scipy.optimize import least_squares

        common = {"loss": "soft_l1", "f_scale": self.config.loss_scale, "method": "trf", "x_scale": "jac",
                  "max_nfev": 200}
        if frames.size <= EXACT_FRAMES:
            return least_squares(self.residuals, start, args=(frames,), jac=self.jacobian, tr_solver="exact",
                                 **common)
        return least_squares(self.residuals, start, args=(frames,), jac_sparsity=self.sparsity(frames.size),
                             **common)


def _initial_positions(mics: np.ndarray, m: FrameMeasurements, frames: np.ndarray,
                       config: ClockCalibrationConfig) -> np.ndarray:
    """Per frame, a position from its reflection delays alone (each fixes the source's elevation seen from
    one microphone) and the offset-free sign of its time differences, from a few starts."""
    from scipy.optimize import least_squares

    c = config.speed_of_sound
    images = _ground_images(mics, config.ground_height)
    centre = mics.mean(axis=0)
    out = np.empty((frames.size, 3))
    starts = [centre + v for v in ([0, 10, 8], [0, 10, 15], [5, 5, 10], [-5, 5, 10], [0, -10, 8], [5, 15, 5])]
    for n, f in enumerate(frames):
        target = m.reflection[f]

        def residual(s: np.ndarray, target: np.ndarray = target) -> np.ndarray:
            direct = np.linalg.norm(s - mics, axis=1)
            return ((np.linalg.norm(s - images, axis=1) - direct) / c - target) / config.sigma

        fits = [least_squares(residual, s0, loss="soft_l1", f_scale=config.loss_scale, max_nfev=50) for s0 in starts]
        out[n] = min(fits, key=lambda r: r.cost).x
    return out


def static_drifts(audio: AudioStream, config: ClockCalibrationConfig = ClockCalibrationConfig()) -> StaticDrift | None:
    """The nodes' drifts told by a static source in ``audio``, searched as far as ``config`` searches the pairs'
    time differences (:func:`~datamodules.features.static_drift.static_source_drift`), or None."""
    return static_source_drift(audio, f_min=config.f_min, f_max=config.f_max, frame_seconds=config.frame_seconds,
                               lag_rate=config.lag_rate, max_delay=_max_tdoa(audio.mic_positions, config),
                               max_drift_ppm=config.max_drift_ppm)


def estimate_clock_offsets(audio: AudioStream, config: ClockCalibrationConfig = ClockCalibrationConfig()
                           ) -> ClockCalibration:
    """Estimate the nodes' clock offsets (node 0 = 0) of ``audio`` from its own sound (see the module docstring).

    Raises:
        ClockCalibrationError: no microphone positions, too short a recording, too few frames with a
            coherent source, or a fit that explains them badly or is too uncertain (``max_residual``,
            ``max_std``), in one line.
    """
    mics = np.asarray(audio.mic_positions, dtype=np.float64)
    if audio.num_channels < 2:
        raise ClockCalibrationError(f"clock calibration needs at least 2 microphones, got {audio.num_channels}")
    if not np.isfinite(mics).all() or not np.any(mics):
        raise ClockCalibrationError("clock calibration needs the microphone positions (all zero or missing)")
    static = static_drifts(audio, config) if config.static_drift else None
    m = measure(audio, config, None if static is None else static.drifts_ppm)
    frames = np.flatnonzero((m.score >= config.min_peak) & np.isfinite(m.reflection).all(axis=1))
    if frames.size < config.min_blocks:
        raise ClockCalibrationError(f"clock calibration found a coherent source in {frames.size} blocks, needs "
                                    f"{config.min_blocks}")
    positions = _initial_positions(mics, m, frames, config)
    if static is not None:  # the time differences are corrected for the drifts: the offsets alone remain
        result = _fit(mics, m, frames, positions, dataclasses.replace(config, fit_drift=False))
        result.drifts_ppm, result.drifts_std_ppm = static.drifts_ppm.copy(), static.drifts_std_ppm.copy()
        result.static_drift = True
    elif config.fit_drift is None:  # fit drifts; keep them only if one of them is told from zero
        result = _fit(mics, m, frames, positions, dataclasses.replace(config, fit_drift=True))
        told = np.abs(result.drifts_ppm) > config.drift_significance * result.drifts_std_ppm
        if not np.any(told | ~np.isfinite(result.drifts_std_ppm)):
            result = _fit(mics, m, frames, result.positions, dataclasses.replace(config, fit_drift=False))
    else:
        result = _fit(mics, m, frames, positions, config)
    rms = result.residual_rms_s
    worst_std = float(np.nanmax(result.offsets_std_s, initial=0.0))
    if np.any(np.abs(result.drifts_ppm) > config.max_drift_ppm):
        raise ClockCalibrationError(f"clock calibration is unreliable (a drift beyond the plausible "
                                    f"+-{config.max_drift_ppm:g} ppm): {result.summary()}")
    if rms > config.max_residual or worst_std > config.max_std:
        raise ClockCalibrationError(
            f"clock calibration is unreliable (residual RMS {1e6 * rms:.0f} us, limit {1e6 * config.max_residual:.0f}; "
            f"offset std up to {1e3 * worst_std:.3f} ms, limit {1e3 * config.max_std:.3f}; {result.frames} blocks): "
            f"{result.summary()}")
    return result


def _fit(mics: np.ndarray, m: FrameMeasurements, frames: np.ndarray, positions: np.ndarray,
         config: ClockCalibrationConfig) -> ClockCalibration:
    """The joint fit from ``positions`` (per frame), its jackknife uncertainty and robust residual RMS."""
    model = _Model(mics, m, config)
    fit = model.solve(frames, np.concatenate([np.zeros(model.clock_params), positions.ravel()]))
    theta = fit.x
    n = mics.shape[0] - 1
    if config.uncertainty == "sandwich":
        spread = _sandwich(model, frames, theta, fit.fun, config.cluster_seconds)
    else:
        spread = _jackknife(model, frames, theta, config.jackknife_blocks)
    std = np.full(model.clock_params, np.nan) if spread is None else spread
    residual = fit.fun * config.sigma
    rms = float(1.4826 * np.median(np.abs(residual - np.median(residual))))
    drifts = np.concatenate([[0.0], theta[n:2 * n]]) if config.fit_drift else np.zeros(n + 1)
    drift_std = np.concatenate([[0.0], std[n:2 * n]]) if config.fit_drift else np.zeros(n + 1)
    offsets_std = with_std_floor(np.concatenate([[0.0], std[:n]]), config.std_floor)
    return ClockCalibration(np.concatenate([[0.0], theta[:n]]), offsets_std, drifts, drift_std,
                            int(frames.size), rms, theta[model.clock_params:].reshape(-1, 3), m.times[frames])


def with_std_floor(offsets_std: np.ndarray, floor_s: float) -> np.ndarray:
    """Offset stds (node 0 first, the reference: 0) with ``floor_s`` added in quadrature to the others."""
    return np.concatenate([offsets_std[:1], np.hypot(offsets_std[1:], floor_s)])


def _jackknife(model: _Model, frames: np.ndarray, theta: np.ndarray, blocks: int) -> np.ndarray | None:
    """Delete-a-block jackknife standard errors of the clock parameters (warm-started refits)."""
    if blocks < 2 or frames.size < 2 * blocks:
        return None
    k = model.clock_params
    estimates = []
    for block in np.array_split(np.arange(frames.size), blocks):
        keep = np.setdiff1d(np.arange(frames.size), block)
        start = np.concatenate([theta[:k], theta[k:].reshape(-1, 3)[keep].ravel()])
        estimates.append(model.solve(frames[keep], start).x[:k])
    estimates = np.array(estimates)
    return np.sqrt((blocks - 1) / blocks * ((estimates - estimates.mean(axis=0)) ** 2).sum(axis=0))


def _sandwich(model: _Model, frames: np.ndarray, theta: np.ndarray, residuals: np.ndarray,
              cluster_seconds: float) -> np.ndarray | None:
    """Cluster-robust sandwich standard errors of the clock parameters of the soft-L1 fit at ``theta``.

    With ``H = J^T W J`` (``W`` the robust loss's weights) and each cluster's score ``g_b = J_b^T W_b r_b``,
    ``cov = H^-1 (sum_b g_b g_b^T) H^-1 b / (b - 1)``: the first-order effect of leaving out each cluster of frames
    (``cluster_seconds`` long), which a refit from the solution would only approach in its iteration limit.
    """
    times = model.m.times[frames]
    cluster = np.floor((times - times.min()) / cluster_seconds).astype(np.int64)
    clusters = np.unique(cluster)
    if clusters.size < 2:
        return None
    jac = model.jacobian(theta, frames)
    z = (residuals / model.config.loss_scale) ** 2
    weights = 1.0 / np.sqrt(1.0 + z)  # soft-L1: rho'(z)
    hessian = jac.T @ (weights[:, None] * jac)
    scores = jac * (weights * residuals)[:, None]
    pairs, channels = len(model.first), model.channels
    row_frame = np.concatenate([np.repeat(np.arange(frames.size), pairs), np.repeat(np.arange(frames.size), channels)])
    per_cluster = np.zeros((clusters.size, jac.shape[1]))
    np.add.at(per_cluster, np.searchsorted(clusters, cluster[row_frame]), scores)
    try:
        bread = np.linalg.solve(hessian, per_cluster.T)[:model.clock_params]  # k x clusters
    except np.linalg.LinAlgError:
        return None
    meat = bread @ bread.T * clusters.size / (clusters.size - 1)
    return np.sqrt(np.clip(np.diag(meat), 0.0, None))
