"""The phase localisers live: ``srp_phat`` and ``phase_student`` behind ``aaute track``.

:func:`load_phase_model` builds the net from a config (``configs/model/srp_phat.yaml``: the net's settings,
the data's phase recipe and bird's-eye bounds, the optional ``live_smoother``), a project checkpoint or
weights. :class:`PhaseTracker` is the :class:`~zoo.deploy.tracking.Tracker` with the streaming phase front
end (:class:`~datamodules.features.IncrementalPhase`) in place of the mel one: after each 0.1 s block the
window ending there goes to the net with the stream's microphone positions, its time and one sequence
index, so ``srp_phat``'s gate (confirmation, hold, fallback) runs in stream order exactly as it does over
the time-ordered windows of ``aaute predict``. Nothing reads audio after the row's time; the smoother's
``lag`` is the only look-ahead.

Rows (:data:`PHASE_COLUMNS`): ``x, y, z, std_x, std_y, std_z`` the online robust smoother's position and
std; ``raw_x, raw_y, raw_z`` the localiser's output (what ``aaute predict`` gives); ``detection_score``
(peak response over the detection threshold) and ``detected``; ``state``: ``detected`` (a counted
detection), ``held`` (the last detection, within ``hold_seconds``), ``fallback`` (after the hold, or
before the first detection), ``estimate`` (``phase_student``, which always answers) or ``uncorrected``
(nodes on separate clocks, before their first clock estimate: never a detection, since a millisecond
between nodes moves a peak by metres; ``srp_phat`` falls back, the score keeps the peak). Only measurements
(``detected`` and ``estimate``) feed the smoother, each with its noise scaled by its score: a held row takes
the smoother's interpolation when a measurement follows within the lag, else the latest smoothed position
(its std grown with the time since); a fallback or uncorrected row carries the localiser's position with
std NaN (no measurement supports it).

Geometry is never guessed: the source's positions must be known (the recording's, or ``--mic-positions``);
their count must equal the channels (:class:`PhaseTracker` refuses otherwise); a sample rate below twice
the recipe's highest frequency is refused; an aperture too small for the region is warned about
(:func:`check_geometry`).

Nodes on separate clocks (a source that says ``nodes_share_clock: false``): with ``clock_seconds`` > 0
the front end is :class:`~zoo.deploy.live_clocks.CalibratingPhase`: the nodes' clocks are estimated from the
stream's first ``clock_seconds`` of audio, in a worker process while the rows go on, then again from every
further ``clock_seconds`` (``clock_follow``), and the cross-spectra of every frame after an estimate are
corrected by all of them so far. Rows before the first, and all rows while every estimate fails (a log line
says why), come from the uncorrected time differences: they are ``uncorrected`` rows, kept out of the
smoother, and ``srp_phat`` counts no detection in them (none is held after the correction).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch
import yaml
from torch import nn

from datamodules.errors import ConfigError
from datamodules.features import SPEED_OF_SOUND, IncrementalPhase, PhaseRecipe
from datamodules.formats.node_audio import warn_unshared_clocks
from datamodules.streams import AudioSource
from zoo.deploy.live_clocks import CalibratingPhase
from zoo.deploy.tracking import (
    HOP_SECONDS,
    McapTrackWriter,
    Tracker,
    TrackingError,
    TrackingReport,
    load_net,
)
from zoo.nets.phase.gate import WINDOW_STATES
from zoo.smoothing import ROBUST_PRESETS, OnlineRow, OnlineSmoother

log = logging.getLogger(__name__)

PHASE_COLUMNS = ("timestamp", "x", "y", "z", "std_x", "std_y", "std_z", "raw_x", "raw_y", "raw_z",
                 "detection_score", "detected", "state")
#: the nets streamed here
PHASE_NETS = ("srp_phat", "phase_student")
#: path difference (m) the wavefront's curvature must reach across the array at the region's far edge for its
#: range to be resolved: one lag of the recipe is 14.5 mm of path at 24 kHz
MIN_CURVATURE_LAGS = 1.0
#: seconds of the stream whose audio calibrates the clocks of nodes that do not share one
CLOCK_SECONDS = 30.0


# ============================================================================================ model


@dataclass
class PhaseTrackingModel:
    """A phase net ready for streaming: the net, its name, phase recipe, window, origin and live smoother."""

    net: nn.Module
    name: str
    recipe: PhaseRecipe
    window_seconds: float
    source: str
    live_smoother: dict[str, Any] = field(default_factory=dict)


def _from_config(path: Path, mics: np.ndarray | None) -> tuple[nn.Module, str, dict[str, Any], dict[str, Any]]:
    """The net a LightningCLI config describes (``model.init_args.net``, ``net_kwargs``; with ``mics``, for
    that array: its channel count and positions), the data's init args and the model's ``live_smoother``."""
    from zoo.registry import get_model

    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such config")
    try:
        config = yaml.safe_load(path.read_text()) or {}
        model = (config.get("model") or {}).get("init_args") or {}
        data = (config.get("data") or {}).get("init_args") or {}
    except (yaml.YAMLError, AttributeError) as error:
        raise ConfigError(f"{path}: expected a model config (model.init_args.net ...): {error}") from None
    name = model.get("net")
    if name not in PHASE_NETS:
        raise ConfigError(f"{path}: aaute track --config streams {', '.join(PHASE_NETS)}; this config's net is "
                          f"{name!r} (give a trained mel model by --weights or --ckpt_path)")
    kwargs = dict(model.get("net_kwargs") or {})
    if mics is not None:  # a non-learned net steers any array: the stream's
        kwargs.update(in_channels=int(mics.shape[0]), mic_positions=np.asarray(mics, dtype=float).tolist())
    net = get_model(name, **kwargs)
    if any(p.requires_grad for p in net.parameters()):
        raise ConfigError(f"{path}: {name!r} learns its weights; give them with --weights or --ckpt_path")
    return net.eval(), name, data, dict(model.get("live_smoother") or {})


def load_phase_model(config: str | Path | None = None, ckpt_path: str | Path | None = None,
                     weights: str | Path | None = None, offline: bool | None = None,
                     source: AudioSource | None = None) -> PhaseTrackingModel:
    """A phase net from a config (non-learned nets), a checkpoint or weights, its region set to the data's
    bird's-eye bounds (as ``aaute test`` sets it). A config's net is built for ``source``'s array (any
    channel count of at least 2) when one is given.

    Raises:
        ConfigError: no or several sources, a config of another net, a learned net without weights.
        TrackingError: weights of a net that does not read one phase input.
    """
    if config is not None:
        if ckpt_path is not None or weights is not None:
            raise ConfigError("aaute track needs exactly one of --ckpt_path FILE, --weights NAME_OR_PATH and "
                              "--config FILE")
        mics = None
        if source is not None:
            require_positions(source, Path(config).stem)
            mics = np.asarray(source.mic_positions, dtype=np.float64)
        net, name, data, smoother = _from_config(Path(config), mics)
        origin = str(config)
    else:
        net, name, origin, data = load_net(ckpt_path, weights, offline)
        smoother = {}
    if set(getattr(net, "inputs", {})) != {"audio_phase"}:
        raise TrackingError(f"model {name!r} reads {dict(getattr(net, 'inputs', {}))}, not one phase input")
    wanted = (data.get("inputs") or {}).get("audio_phase")
    if wanted is not None and wanted != net.recipe.name:
        raise ConfigError(f"{origin}: data.inputs.audio_phase {wanted!r} differs from the net's recipe "
                          f"{net.recipe.name!r} (net_kwargs.input_recipes)")
    preset = smoother.get("preset", "robust")
    if preset not in ROBUST_PRESETS:
        raise ConfigError(f"{origin}: live_smoother preset {preset!r} is not one of {sorted(ROBUST_PRESETS)}")
    bounds = data.get("bev_bounds") or [[-2.0, 8.0], [-5.0, 25.0]]  # MMAUDDataModule's default
    net.set_bounds(bounds)
    return PhaseTrackingModel(net, name, net.recipe, net.recipe.span_seconds, origin, smoother)


def is_phase_model(config: str | Path | None, ckpt_path: str | Path | None, weights: str | Path | None) -> bool:
    """Whether ``aaute track``'s model arguments name a phase model (a config always does)."""
    if config is not None:
        return True
    from zoo.weights import resolve_weights
    from zoo.weights.files import read_file

    if ckpt_path is not None:
        stored = read_file(Path(ckpt_path)) if Path(ckpt_path).is_file() else {}
        hyper = stored.get("hyper_parameters", {}) if isinstance(stored, dict) else {}
        return hyper.get("net") in PHASE_NETS
    contents, entry = resolve_weights(None, weights, None)
    name = contents.net or (entry.name.split(".")[0] if entry else None)
    inputs = contents.inputs or (entry.inputs if entry else {})
    return name in PHASE_NETS or "audio_phase" in inputs


# ============================================================================================ geometry


def require_positions(source: AudioSource, model: str) -> None:
    """Raise TrackingError, in one line saying what is needed, unless ``source`` knows its microphone positions."""
    if not source.mic_positions_known:
        raise TrackingError(f"{source.name}: model {model!r} steers with the microphone positions, which this "
                            f"source does not give ({source.mic_source}); pass --mic-positions FILE (one 'x y z' "
                            f"row in metres per channel)")


def check_geometry(model: PhaseTrackingModel, source: AudioSource) -> np.ndarray:
    """The source's microphone positions (channels x 3, m), checked for a phase model.

    Raises:
        TrackingError: positions unknown (a default array, or a recording that says so), a count other than
            the channels, or a sample rate below twice the recipe's highest frequency.
    """
    require_positions(source, model.name)
    mics = np.asarray(source.mic_positions, dtype=np.float64)
    if mics.shape != (source.channels, 3):
        raise TrackingError(f"{source.name}: {source.channels} audio channels but microphone positions of shape "
                            f"{mics.shape} ({source.mic_source}); expected one x y z row per channel")
    if source.sample_rate < 2 * model.recipe.f_max:
        raise TrackingError(f"{source.name}: sample rate {source.sample_rate:g} Hz; model {model.name!r} reads "
                            f"the band up to {model.recipe.f_max:g} Hz of recipe {model.recipe.name!r}, so it "
                            f"needs at least {2 * model.recipe.f_max:g} Hz")
    speed = float(getattr(model.net.steering, "speed_of_sound", SPEED_OF_SOUND))
    distances = np.linalg.norm(mics[:, None] - mics[None], axis=-1)
    aperture = float(distances.max())
    if aperture / speed > model.recipe.max_delay:
        log.warning("%s: microphones %.2f m apart: delays up to %.1f ms, beyond the recipe's %.1f ms lags; those "
                    "pairs see no far source", source.name, aperture, 1e3 * aperture / speed,
                    1e3 * model.recipe.max_delay)
    region = model.net.region.numpy()
    corners = np.array(np.meshgrid(*region, indexing="ij")).reshape(3, -1).T
    far = float(np.linalg.norm(corners - mics.mean(axis=0), axis=1).max())
    curvature = aperture ** 2 / (8 * far) / speed * model.recipe.lag_rate  # the wavefront's sagitta, in lags
    if curvature < MIN_CURVATURE_LAGS:
        log.warning("%s: a %.2f m aperture cannot resolve range at the region's far edge (%.0f m: the wavefront "
                    "bends by %.2f lags across the array, under %g); expect directions, not distances",
                    source.name, aperture, far, curvature, MIN_CURVATURE_LAGS)
    return mics


# ============================================================================================ thresholds


def thresholds_file() -> Path:
    """Where ``srp_phat``'s detection thresholds are kept between runs: ``$AAUTE_CACHE/srp_phat_thresholds.json``
    or ``~/.cache/aaute/srp_phat_thresholds.json``."""
    from zoo.weights.hub import weights_dir

    return weights_dir().parent / "srp_phat_thresholds.json"


def prepare_threshold(net: nn.Module, mics: torch.Tensor, path: Path | None = None) -> None:
    """Give ``srp_phat`` its detection threshold for ``mics`` before the stream starts: from the thresholds
    file when a run with the same settings and geometry stored it (:meth:`SRPPhat.threshold_key`), else
    computed from the null statistic now (tens of seconds on one core) and stored there."""
    if not hasattr(net, "threshold_key"):
        return
    import json

    from datamodules.atomic import atomic_write

    path = thresholds_file() if path is None else path
    key = net.threshold_key(mics)
    try:
        stored = json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, ValueError):
        stored = {}
    if isinstance(stored.get(key), float):
        net.set_threshold(mics, stored[key])
        net.search.prepare(mics)  # the search's tables (computing the threshold builds them too)
        log.info("srp_phat: detection threshold %.4f from %s", stored[key], path)
        return
    stored[key] = net.threshold(mics)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path) as tmp:
            tmp.write_text(json.dumps(stored, indent=1, sort_keys=True))
    except OSError as error:  # a read-only cache costs the next run the computation, nothing else
        log.warning("srp_phat: could not store the detection threshold in %s (%s)", path, error)


# ============================================================================================ rows


@dataclass
class PhaseRow:
    """One row of :data:`PHASE_COLUMNS`."""

    timestamp: float
    raw: np.ndarray
    score: float
    detected: bool
    state: str
    mean: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    std: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    resolved: bool = False

    @property
    def measured(self) -> bool:
        return self.state in ("detected", "estimate")

    def values(self) -> tuple[Any, ...]:
        return (self.timestamp, *map(float, self.mean), *map(float, self.std), *map(float, self.raw),
                float(self.score), int(self.detected), self.state)


class GatedSmoothing:
    """The online smoother over the measured rows of a stream, the rows given back in time order.

    Each measured row enters with its noise scaled by its detection score (the preset's
    :meth:`~zoo.smoothing.RobustHyperparameters.noise_scale`; 1 for a row without a score).
    A measured row waits for its smoothed value (``lag`` seconds of later measurements, or until ``lag``
    seconds of stream pass without one). A held row waits ``lag`` seconds of stream too: when a measurement
    came within them, it takes the smoother's interpolation at its time (:meth:`OnlineSmoother.predict`,
    from the measurements up to its time plus the lag, as a measured row does); otherwise (and always at
    lag 0) it takes the latest smoothed position, its std grown by what the smoother's Matern-5/2 prior lets
    the track move in the time since (variance ``outputscale * (1 - rho(dt))`` per axis, ``rho`` the
    prior's correlation). A held row's std, either way, is calibrated by the preset's ``hold_scale`` factor
    (the prior's spread is not the detections' error, which ``std_scale`` calibrates). A measured row's std,
    and a held row's, is also multiplied by the preset's
    :meth:`~zoo.smoothing.RobustHyperparameters.std_score_factor` of its score (a held row: of the last
    measurement before it). A fallback row keeps its own position with std NaN.
    """

    def __init__(self, smoother: OnlineSmoother):
        self.smoother = smoother
        self.queue: deque[PhaseRow] = deque()
        self.waiting: dict[float, PhaseRow] = {}
        #: held rows waiting for ``lag`` seconds of stream, each with the score of the last measurement before it
        self.holding: deque[tuple[PhaseRow, float]] = deque()
        self.last_fed: float | None = None
        self.last_score = math.nan  #: the score of the last measured row fed
        #: time, mean, std (uncalibrated) and score of the last measured row given back
        self.latest: tuple[float, np.ndarray, np.ndarray, float] | None = None
        lengthscale, outputscale, _ = smoother.hyperparameters.arrays()
        self._lengthscale, self._outputscale = lengthscale, outputscale

    def held_std(self, std: np.ndarray, elapsed: float, score: float) -> np.ndarray:
        """The calibrated std of a position held ``elapsed`` seconds after the smoothed one of (uncalibrated)
        std ``std`` and detection ``score``."""
        r = np.sqrt(5.0) * max(elapsed, 0.0) / self._lengthscale
        moved = self._outputscale * (1.0 - (1.0 + r + r * r / 3.0) * np.exp(-r))
        return self._score_factor(score) * self.smoother.hold_scale * np.sqrt(std**2 + moved)

    def _score_factor(self, score: float) -> float:
        return self.smoother.hyperparameters.std_score_factor(score)

    def _fill(self, rows: list[OnlineRow]) -> None:
        for row in rows:
            target = self.waiting.pop(row.timestamp)
            target.mean, target.resolved = np.asarray(row.mean), True
            target.std = np.asarray(row.std) * self._score_factor(target.score)

    def _settle(self, now: float | None) -> None:
        """Resolve the held rows whose lag has passed by ``now`` (None: all), before a later row is fed."""
        while self.holding and (now is None or now > self.holding[0][0].timestamp + self.smoother.lag):
            row, score = self.holding.popleft()
            last = self.smoother.last_time
            if last is not None and last > row.timestamp:  # a measurement within the lag: interpolate
                row.mean, std = self.smoother.predict(row.timestamp)
                row.std = std * self._score_factor(score)
                row.resolved = True

    def add(self, row: PhaseRow) -> list[PhaseRow]:
        """Take one row; return the rows now complete, in time order."""
        self._settle(row.timestamp)
        self.queue.append(row)
        if row.measured:
            self.waiting[row.timestamp] = row
            scale = self.smoother.hyperparameters.noise_scale(row.score)  # a weak peak: a noisier position
            self._fill(self.smoother.update(row.timestamp, row.raw, scale))
            self.last_fed, self.last_score = row.timestamp, row.score
            return self._ready()
        if row.state == "held" and self.smoother.lag > 0 and self.last_fed is not None:
            self.holding.append((row, self.last_score))
        if self.waiting and self.last_fed is not None and row.timestamp - self.last_fed >= self.smoother.lag:
            self._fill(self.smoother.flush())  # no measurement for lag seconds: the waiting ones have their future
        return self._ready()

    def flush(self) -> list[PhaseRow]:
        self._fill(self.smoother.flush())
        self._settle(None)
        return self._ready()

    def _ready(self) -> list[PhaseRow]:
        out = []
        while self.queue:
            row = self.queue[0]
            if not row.resolved and (row.measured or (self.holding and self.holding[0][0] is row)):
                break  # waiting for its lag
            self.queue.popleft()
            if row.measured:
                uncalibrated = row.std / (self.smoother.scale * self._score_factor(row.score))
                self.latest = (row.timestamp, row.mean, uncalibrated, row.score)
            elif row.resolved:
                pass  # a held row interpolated by the smoother
            elif row.state == "held" and self.latest is not None:
                t, mean, std, score = self.latest
                row.mean, row.std = mean, self.held_std(std, row.timestamp - t, score)
            else:
                row.mean, row.std = row.raw.copy(), np.full(3, np.nan)
            out.append(row)
        return out


def smooth_rows(timestamps: np.ndarray, raw: np.ndarray, scores: np.ndarray, detected: np.ndarray,
                states: np.ndarray, smoother: OnlineSmoother) -> list[PhaseRow]:
    """A detecting localiser's rows (``aaute predict``'s, or stored ones) smoothed as ``aaute track`` smooths
    them (:class:`GatedSmoothing`), in time order."""
    gated = GatedSmoothing(smoother)
    rows: list[PhaseRow] = []
    for i in np.argsort(timestamps, kind="stable"):
        rows += gated.add(PhaseRow(float(timestamps[i]), np.asarray(raw[i], dtype=np.float64), float(scores[i]),
                                   bool(detected[i]), str(states[i])))
    return rows + gated.flush()


class PhaseCsvWriter:
    """Rows of :data:`PHASE_COLUMNS` as CSV lines, each flushed at once."""

    def __init__(self, stream: IO[str]):
        self.stream = stream
        stream.write(",".join(PHASE_COLUMNS) + "\n")
        stream.flush()

    def write(self, row: PhaseRow) -> None:
        t, *numbers, detected, state = row.values()
        self.stream.write(f"{t:.6f}," + ",".join(f"{v:.6f}" for v in numbers) + f",{detected},{state}\n")
        self.stream.flush()


class PhaseMcapWriter(McapTrackWriter):
    """Rows of :data:`PHASE_COLUMNS` as JSON messages on one MCAP topic (schema ``aaute/PhaseTrackPoint``)."""

    SCHEMA = {"type": "object", "title": "aaute/PhaseTrackPoint",
              "properties": {**{name: {"type": "number"} for name in PHASE_COLUMNS[:-2]},
                             "detected": {"type": "boolean"}, "state": {"type": "string"}}}

    def write(self, row: PhaseRow) -> None:  # type: ignore[override]
        import json

        from datamodules.recording import seconds_to_ns

        values = dict(zip(PHASE_COLUMNS, row.values(), strict=True))
        values = {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in values.items()}
        values["detected"] = bool(values["detected"])
        stamp = int(seconds_to_ns(row.timestamp))
        self.writer.add_message(self.channel, stamp, json.dumps(values).encode(), stamp, self.sequence)
        self.sequence += 1
        self.stream.flush()


# ============================================================================================ tracker


class PhaseTracker(Tracker):
    """:class:`~zoo.deploy.tracking.Tracker` for a phase net (see the module docstring).

    Args:
        model: :func:`load_phase_model`.
        source, writers, lag, hop_seconds, batch: as for :class:`~zoo.deploy.tracking.Tracker`.
        preset: the online smoother's preset (default: the model's ``live_smoother`` preset, else ``robust``).
        clock_seconds: for a source whose nodes do not share a clock, seconds of its start that calibrate
            them (0: none, the rows carry the clocks' error).
        clock_follow: estimate the clocks again from every further ``clock_seconds`` of the stream and
            correct by all the estimates (drift followed); False: the first estimate serves the whole stream.
    """

    frame_kind = "GCC-PHAT"

    def __init__(self, model: PhaseTrackingModel, source: AudioSource, writers: list[Any], lag: float = 0.0,
                 preset: str | None = None, hop_seconds: float = HOP_SECONDS, batch: int = 1,
                 clock_seconds: float = CLOCK_SECONDS, clock_follow: bool = True):
        self.mics = check_geometry(model, source)
        self.clock_seconds = float(clock_seconds) if not source.nodes_share_clock else 0.0
        self.clock_follow = clock_follow
        if not source.nodes_share_clock and self.clock_seconds > 0:
            log.warning("%s: audio nodes on separate clocks: their offsets are estimated from the first %g s of "
                        "the stream; rows before that use uncorrected time differences", source.name,
                        self.clock_seconds)
        else:
            warn_unshared_clocks({"nodes_share_clock": source.nodes_share_clock,
                                  "audio_alignment_uncertainty_s": source.alignment_uncertainty_s}, source.name,
                                 f"live tracking with {model.name!r}")
        preset = preset or model.live_smoother.get("preset", "robust")
        super().__init__(model, source, writers, lag, preset, hop_seconds, batch)  # type: ignore[arg-type]
        self.window = self.front.window
        self.gated = GatedSmoothing(self.smoother)
        self.mic_tensor = torch.from_numpy(self.mics.astype(np.float32))  # as the DataModule's batches carry them
        prepare_threshold(model.net, self.mic_tensor.double())  # as the net keys the batch's geometry

    def run(self) -> TrackingReport:
        try:
            return super().run()
        finally:
            if isinstance(self.front, CalibratingPhase):
                self.front.close()

    def front_end(self) -> IncrementalPhase:
        if self.clock_seconds > 0:
            return CalibratingPhase(self.model.recipe, self.source.sample_rate, self.mics,  # type: ignore[arg-type]
                                    self.clock_seconds, self.source.name, follow=self.clock_follow)
        return IncrementalPhase(self.model.recipe, self.source.sample_rate, self.source.channels)  # type: ignore[arg-type]

    def localise(self, features: torch.Tensor, times: list[float], corrected: list[bool] | None = None
                 ) -> list[PhaseRow]:
        """The net on windows (B x pairs x frames x lags) ending at ``times``, in stream order: one row each.

        ``corrected`` (default: all) says which windows' time differences are on one clock; the others become
        ``uncorrected`` rows: the net is told (``uncorrected_clocks``, as the DataModule tells it offline), so
        ``srp_phat`` counts no detection there and its gate holds none of them after the correction."""
        b = features.shape[0]
        corrected = [True] * b if corrected is None else corrected
        inputs = {"audio_phase": features, "mic_positions": self.mic_tensor.expand(b, -1, -1),
                  "time": torch.tensor(times, dtype=torch.float64), "sequence": torch.zeros(b, dtype=torch.long),
                  "uncorrected_clocks": ~torch.tensor(corrected, dtype=torch.bool)}
        with torch.inference_mode():
            out = self.model.net(inputs)
        positions = out["position"].double().numpy()
        if "state" in out:
            scores, detected = out["detection_score"].double().numpy(), out["detected"].numpy()
            states = [WINDOW_STATES[i] for i in out["state"].tolist()]
        else:
            scores, detected, states = np.full(b, np.nan), np.ones(b, dtype=bool), ["estimate"] * b
        return [PhaseRow(t, positions[i], float(scores[i]), bool(detected[i]), states[i]) if corrected[i] else
                PhaseRow(t, positions[i], float(scores[i]), False, "uncorrected") for i, t in enumerate(times)]

    def _corrected(self, stop: int) -> bool:
        """Whether the window ending at stream sample ``stop`` has its time differences on one clock: always for
        a source on one clock or tracked uncalibrated (``clock_seconds`` 0), else once the first estimate
        corrects them."""
        return not isinstance(self.front, CalibratingPhase) or self.front.corrected(stop)

    def _positions(self, pending: list[tuple[int, torch.Tensor, float]], report: TrackingReport) -> None:
        if not pending:
            return
        rows = self.localise(torch.stack([f for _, f, _ in pending]), [self._timestamp(s) for s, _, _ in pending],
                             [self._corrected(s) for s, _, _ in pending])
        report.updates += len(pending)
        for (stop, _, arrival), row in zip(pending, rows, strict=True):
            if not np.isfinite(row.raw).all():
                log.warning("%s: model %s gave a non-finite position at %.3f s: skipped", self.source.name,
                            self.model.name, self._timestamp(stop))
                report.skipped_windows += 1
                continue
            self._emit(self.gated.add(row), report)  # type: ignore[arg-type]
            self._record(arrival, report)
        pending.clear()

    def _record(self, arrival: float, report: TrackingReport) -> None:
        import time

        done = time.perf_counter()
        report.latencies.append(done - arrival)
        report.compute_seconds += done - max(arrival, report.busy_until)
        report.busy_until = done

    def _finish_rows(self) -> list[Any]:
        return self.gated.flush()
