"""The shared MMAUD DataModule: the same windows, splits and targets for every model of the zoo.

A sample is a window of sensor data ending at a label time (causal), with every target the loss
or the evaluation may need: ground-truth xyz, pseudo-label xyz, a validity flag for each (a window
inside a teacher gap has no pseudo-label), drone class, visibility in the camera, time and
sequence. Models differ only in which inputs they consume and with which recipe
(:mod:`datamodules.features`); the inputs are computed once into a memory-mapped cache. On a
recording with audio only windows whose audio lies inside it are used, whatever the model consumes,
so audio, visual and audio-visual models are scored on the same windows.

The split is an evaluation protocol (:mod:`datamodules.splits`): ``by_sequence`` (default: whole
recordings, explicit lists or seeded and stratified by drone), ``time_blocks`` (contiguous blocks of
every recording with purge gaps, for few flights) or ``random_windows`` (the papers' protocol, whose
test windows overlap training windows). Under the window-level protocols each recording yields one
piece per split (sequence id ``<recording id>#<split>``) that indexes into the recording's cached
features, so features are computed once per recording whatever the protocol. Validation and test
run under each light condition in
``test_lights`` (loader index k is condition ``test_lights[k]``), so one ``test`` reports both the
ideal-light and the darkness numbers.
"""

from __future__ import annotations

import logging
import zlib
from collections import Counter
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader

from datamodules.cache import FeatureCache, array_fingerprint, path_fingerprint
from datamodules.errors import ConfigError
from datamodules.features import (
    DARK_MODES,
    PhaseWindows,
    audio_window,
    image_features,
    image_recipe,
    mel_features,
    mel_recipe,
    phase_recipe,
    stored_recipe,
)
from datamodules.features.clock_calibration import (
    ClockCalibration,
    ClockCalibrationConfig,
    ClockCalibrationError,
    check_mode,
    estimate_clock_offsets,
    wants_calibration,
)
from datamodules.formats.node_audio import warn_unshared_clocks
from datamodules.formats.positions import require_mic_positions
from datamodules.recording import Recording, RecordingError, Track
from datamodules.samples import SequenceSamples, WindowDataset
from datamodules.splits import (
    SPLITS,
    SplitConfig,
    SplitError,
    assign_sequences,
    assign_windows,
    nearest_distance,
    shortfall_message,
)

log = logging.getLogger(__name__)

INPUT_KINDS = ("audio_mel", "audio_phase", "image")
TARGET_MODES = ("both", "ground_truth", "pseudo")
LIGHTS = ("ideal", "dark")
#: how audio windows are placed on samples, part of the cache keys of audio features; "w2": a label time within
#: float64 resolution of a sample boundary ends its window on that boundary (AudioStream.sample_index)
WINDOW_INDEXING = "w2"
#: the splits each stage needs windows in
STAGE_SPLITS = {"fit": ("train", "val"), "validate": ("val",), "test": ("test",), "predict": ("test",)}


def discover(root: str | Path | list[str | Path]) -> list[Path]:
    """Every recording under ``root`` (files, folders or lists of them), in a stable order."""
    from datamodules.formats import discover_all

    roots = root if isinstance(root, list | tuple) else [root]
    found = discover_all(roots)
    if not found:
        raise RecordingError(f"no recordings found under {roots}")
    return sorted(found)


def _nearest(track: Track | None, times: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Track xyz at the nearest valid point to each time, and whether one lies within ``tolerance``."""
    xyz = np.zeros((times.size, 3))
    valid = np.zeros(times.size, dtype=bool)
    if track is None or not track.valid.any():
        return xyz, valid
    stamps, points = track.timestamps[track.valid], track.xyz[track.valid]
    right = np.clip(np.searchsorted(stamps, times), 1, max(stamps.size - 1, 1))
    left = right - 1
    pick = np.where(np.abs(stamps[np.minimum(right, stamps.size - 1)] - times) < np.abs(stamps[left] - times),
                    np.minimum(right, stamps.size - 1), left)
    valid = np.abs(stamps[pick] - times) <= tolerance
    xyz[valid] = points[pick[valid]]
    return xyz, valid


def _visibility(recording: Recording, positions: np.ndarray, has_image: np.ndarray) -> np.ndarray:
    """Whether the drone is in the (left-cropped) camera image at each position.

    Simulated recordings carry the camera geometry, so visibility is computed by projection; for
    other layouts it is 1 wherever a frame exists (their own detection labels are not read yet).
    """
    if recording.meta.get("source_format") != "simulator" or recording.frames is None:
        return has_image.astype(np.float32)
    from datamodules.simulate.camera import CameraModel, project

    model = CameraModel()
    u, _, inside = project(model, positions)
    return (inside & (u < 1280) & has_image).astype(np.float32)


class MMAUDDataModule(L.LightningDataModule):
    """Windows of MMAUD(-like) recordings for every model of the zoo.

    Args:
        root: recordings: files or folders (any readable layout), or a list of them.
        split: the evaluation protocol (:mod:`datamodules.splits`). ``{"protocol": "by_sequence", "seed": 0,
            "val": 0.2, "test": 0.2}`` (the default: whole sequences, seeded, stratified by drone), or
            explicit ``{"train": [ids], "val": [ids], "test": [ids]}`` (sequence ids or file stems; a value
            may instead be a list file of the derived layout, e.g. ``train.txt``, whose sequences it
            names), or ``{"protocol": "time_blocks", "seed": 0, "val": 0.2, "test": 0.2, "blocks": 5}``
            (``block_seconds`` instead of ``blocks``; ``purge_seconds`` defaults to, and is never less
            than, the window), or ``{"protocol": "random_windows", ...}`` (the papers' overlapping split).
        window_seconds: audio seconds ending at the label time (causal).
        label_rate: samples per second (labels are thinned to this rate).
        inputs: what the model consumes: ``{"audio_mel": <mel recipe>, "audio_phase": <phase recipe>,
            "image": <image recipe>}``; with ``audio_phase``, batches also carry each recording's
            ``mic_positions`` (B x channels x 3).
        light: condition of the validation loader ('ideal' or 'dark').
        test_lights: conditions of the test loaders, in order.
        dark_mode: 'published' (constant near-black image, visibility 0) or 'physical' (low-light rendering).
        train_dark_probability: share of training images darkened (0.3 in AV-FDTI, 0.4 in AV-PedAware).
        targets: which targets batches carry: 'both', 'ground_truth' or 'pseudo' (the other is marked
            invalid, so a self-supervised run cannot see ground truth even by mistake).
        faithful_window_order: reproduce the original newest-first audio chunk order.
        batch_size, num_workers: DataLoader settings.
        cache_dir: feature cache (default ``$AAUTE_CACHE`` or ``~/.cache/aaute/features``).
        image_tolerance_s: the camera frame must lie this close to the label time.
        bev_bounds: [[x_min, x_max], [y_min, y_max]] (m) of the bird's-eye area that heat-map models
            (AV-FDTI) cover; the default is the MMAUD flight region the simulator flies in.
        reader_options: passed to :func:`datamodules.formats.open_recording` for the layouts that take
            them, e.g. ``{"sample_rate": 46080}`` for the derived npy layout of the AAUTE code.
        clock_calibration: whether phase features first correct the audio nodes' clock offsets, estimated
            from each recording's own audio (:mod:`datamodules.features.clock_calibration`): ``auto`` (when
            the recording's metadata says ``nodes_share_clock: false``), ``on`` or ``off``.
    """

    def __init__(
        self,
        root: str | list[str],
        split: dict[str, Any] | None = None,
        window_seconds: float = 2.0,
        label_rate: float = 10.0,
        inputs: dict[str, str] | None = None,
        light: str = "ideal",
        test_lights: list[str] | None = None,
        dark_mode: str = "published",
        train_dark_probability: float = 0.3,
        targets: str = "both",
        faithful_window_order: bool = False,
        batch_size: int = 32,
        num_workers: int = 0,
        cache_dir: str | None = None,
        image_tolerance_s: float = 0.1,
        bev_bounds: list[list[float]] | None = None,
        reader_options: dict[str, Any] | None = None,
        clock_calibration: str = "auto",
    ):
        super().__init__()
        check_mode(clock_calibration)
        if bev_bounds is None:
            bev_bounds = [[-2.0, 8.0], [-5.0, 25.0]]
        self.save_hyperparameters()
        self.inputs = dict(inputs or {"audio_mel": "aaute"})
        unknown = set(self.inputs) - set(INPUT_KINDS)
        if unknown:
            raise ConfigError(f"unknown input(s) {sorted(unknown)}; known: {INPUT_KINDS}")
        self.audio_recipe = mel_recipe(self.inputs["audio_mel"]) if "audio_mel" in self.inputs else None
        self.phase_recipe = phase_recipe(self.inputs["audio_phase"]) if "audio_phase" in self.inputs else None
        self.image_recipe = image_recipe(self.inputs["image"]) if "image" in self.inputs else None
        if self.phase_recipe is not None and self.phase_recipe.span_seconds > window_seconds + 1e-9:
            raise ValueError(f"phase recipe {self.phase_recipe.name!r} reads {self.phase_recipe.span_seconds:.3f} s "
                             f"per window, more than window_seconds {window_seconds}")
        self.test_lights = list(test_lights or ["ideal", "dark"])
        for value in (light, *self.test_lights):
            if value not in LIGHTS:
                raise ConfigError(f"light must be one of {LIGHTS}, not {value!r}")
        if dark_mode not in DARK_MODES:
            raise ConfigError(f"dark_mode must be one of {DARK_MODES}, not {dark_mode!r}")
        if targets not in TARGET_MODES:
            raise ConfigError(f"targets must be one of {TARGET_MODES}, not {targets!r}")
        self.split_config = SplitConfig.from_dict(split, self._window_span())
        self.cache = FeatureCache(cache_dir)
        self.sequences: dict[str, list[SequenceSamples]] = {}
        self.skipped: dict[str, int] = {}
        self.purged = 0  #: windows dropped in the purge gaps of time_blocks
        self.drone_counts: dict[str, int] = {}  #: recordings found per drone
        self.audio_sample_rates: list[float] = []  #: of the recordings indexed (Hz)
        #: per recording calibrated (path), its clock estimate, or the one-line reason it has none (uncorrected)
        self.clock_estimates: dict[str, ClockCalibration | str] = {}

    @property
    def protocol(self) -> str:
        """The evaluation protocol as results tables label it (``random_windows`` says it overlaps)."""
        return self.split_config.label

    def _window_span(self) -> float:
        """Seconds of audio one window covers (at least ``window_seconds``)."""
        span = float(self.hparams.window_seconds)
        if self.hparams.faithful_window_order and self.audio_recipe is not None:
            span = max(span, self.audio_recipe.chunk_seconds * (1 - min(self.audio_recipe.chunk_offsets)))
        return span

    # ------------------------------------------------------------------------------ preparation

    def prepare_data(self) -> None:
        """Index every recording and build the feature caches (rank 0 of each node)."""
        self._index()

    def setup(self, stage: str | None = None) -> None:
        """Index (if not done yet) and check that the splits ``stage`` needs have windows."""
        stage = getattr(stage, "value", stage)  # Lightning passes its TrainerFn enum: "fit", not "TrainerFn.FITTING"
        if not self.sequences:
            self._index()  # other ranks: the caches exist by now, only the index is rebuilt
        self._require(stage, STAGE_SPLITS.get(stage or "", ()))
        if self.split_config.protocol == "random_windows":
            summary = self.split_summary()
            log.warning("split protocol random_windows: %.0f%% of the test windows (%.0f%% of the validation "
                        "windows) have a training window of the same flight closer than the %g s window, so "
                        "their audio overlaps it; test errors are optimistic and not comparable to by_sequence "
                        "or time_blocks", 100 * summary["test"]["overlap_with_train"],
                        100 * summary["val"]["overlap_with_train"], self._window_span())

    def _require(self, stage: str | None, needed: tuple[str, ...]) -> None:
        """Fail with one actionable line if a split in ``needed`` has no windows."""
        summary = self.split_summary()
        empty = [name for name in needed if summary[name]["windows"] == 0]
        if empty:
            raise SplitError(shortfall_message(self.split_config, stage or f"load {empty[0]}", empty, summary,
                                               self.drone_counts))

    def split_summary(self) -> dict[str, Any]:
        """What the split holds, for results tables and run records.

        Returns:
            ``{"protocol": <label as in protocol>, "purged_windows": <dropped in purge gaps>, "train": {...},
            "val": {...}, "test": {...}}``; per split ``sequences`` (recordings contributing), ``pieces``
            (entries in :attr:`sequence_ids`), ``blocks`` (contiguous time blocks: one per piece under
            by_sequence, one per window under random_windows) and ``windows``; val and test also give
            ``overlap_with_train``: the share of their windows with a training window of the same recording
            closer than the window's audio span (0 unless the protocol is random_windows). time_blocks adds
            ``purge_seconds``.
        """
        span = self._window_span()
        train_times: dict[str, list[np.ndarray]] = {}
        for piece in self.sequences.get("train", []):
            train_times.setdefault(piece.recording_id, []).append(piece.times)
        summary: dict[str, Any] = {"protocol": self.protocol, "purged_windows": int(self.purged)}
        if self.split_config.protocol == "time_blocks":
            summary["purge_seconds"] = self.split_config.purge_seconds
        for name in SPLITS:
            pieces = self.sequences.get(name, [])
            entry: dict[str, Any] = {"sequences": len({p.recording_id for p in pieces}), "pieces": len(pieces),
                                     "blocks": sum(p.blocks for p in pieces), "windows": sum(len(p) for p in pieces)}
            if name != "train":
                overlapping = 0
                for piece in pieces:
                    reference = np.sort(np.concatenate(train_times.get(piece.recording_id, [np.zeros(0)])))
                    overlapping += int((nearest_distance(piece.times, reference) < span).sum())
                entry["overlap_with_train"] = overlapping / entry["windows"] if entry["windows"] else 0.0
            summary[name] = entry
        return summary

    def state_dict(self) -> dict[str, Any]:
        """Kept in checkpoints: the audio rates trained on (``aaute track`` refuses audio at another)."""
        return {"audio_sample_rates": list(self.audio_sample_rates)}

    @property
    def sequence_paths(self) -> list[Path]:
        """The file or folder of each sequence, in :attr:`sequence_ids` order."""
        return [s.path for name in SPLITS for s in self.sequences.get(name, [])]

    @property
    def sequence_ids(self) -> list[str]:
        """All sequence ids in a fixed order; batches carry an index into this list."""
        return [s.sequence_id for name in SPLITS for s in self.sequences.get(name, [])]

    @property
    def bev_bounds(self) -> list[list[float]]:
        """The bird's-eye area [[x_min, x_max], [y_min, y_max]] (m) that heat-map and search nets cover."""
        return self.hparams.bev_bounds

    def _index(self) -> None:
        from datamodules.formats import open_recording

        paths = discover(self.hparams.root)
        options = dict(self.hparams.reader_options or {})
        recordings = [(path, open_recording(path, **options)) for path in paths]
        ids = [rec.sequence_id for _, rec in recordings]
        if len(set(ids)) != len(ids):
            clashes = {i: [str(p) for p, rec in recordings if rec.sequence_id == i] for i in ids if ids.count(i) > 1}
            listing = "; ".join(f"{i!r} in {', '.join(files)}" for i, files in clashes.items())
            raise RecordingError(f"{self.hparams.root}: sequence ids are not unique: {listing}; expected one "
                                 f"recording per id (remove the copies)")
        self.drone_counts = dict(Counter(rec.drone or "unknown" for _, rec in recordings))
        self.audio_sample_rates = sorted({float(r.audio.sample_rate) for _, r in recordings if r.audio is not None})
        by_sequence = self.split_config.protocol == "by_sequence"
        assignment = self._assign_splits(recordings) if by_sequence else ["all"] * len(recordings)
        self.sequences = {name: [] for name in SPLITS}
        self.skipped, self.purged, self.clock_estimates = {}, 0, {}
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # one small window at a time: threads only contend
        try:
            for split_name in assignment:
                path, recording = recordings.pop(0)  # released when done: readers cache chunks
                if split_name is None:
                    continue
                samples = self._samples(path, recording)  # features of every window, once per recording
                if samples is None:
                    continue
                if by_sequence:
                    self.sequences[split_name].append(samples)
                else:
                    self._add_pieces(samples)
        finally:
            torch.set_num_threads(threads)
        ids = self.sequence_ids
        if len(set(ids)) != len(ids):
            raise RecordingError(f"sequence ids of the split pieces are not unique under {self.hparams.root} "
                                 f"(a recording id ends in '#<split>'?)")
        for reason, count in self.skipped.items():
            log.warning("skipped %d windows: %s", count, reason)
        if self.split_config.protocol == "time_blocks":
            log.info("time_blocks: dropped %d windows in purge gaps of %g s between blocks of different splits",
                     self.purged, self.split_config.purge_seconds)
        sizes = {name: sum(len(s) for s in seqs) for name, seqs in self.sequences.items()}
        log.info("split %s: samples per split %s (pieces %s)", self.split_config.describe(), sizes,
                 {n: len(s) for n, s in self.sequences.items()})

    def _add_pieces(self, samples: SequenceSamples) -> None:
        """Split one recording's windows (window-level protocols): one piece per split it reaches."""
        assignment = assign_windows(samples.times, self.split_config, samples.sequence_id)
        self.purged += assignment.dropped
        for name in SPLITS:
            rows = assignment.rows(name)
            if rows.size:
                self.sequences[name].append(samples.piece(rows, f"{samples.sequence_id}#{name}",
                                                          assignment.blocks(name)))

    def _assign_splits(self, recordings: list[tuple[Path, Recording]]) -> list[str | None]:
        """The by_sequence split of each recording (None: not used)."""
        names = [(rec.sequence_id, path.stem) for path, rec in recordings]
        return assign_sequences(names, [rec.drone for _, rec in recordings], self.split_config)

    def _label_times(self, recording: Recording) -> np.ndarray:
        reference = recording.ground_truth if recording.ground_truth is not None else recording.pseudo_labels
        if reference is None:
            raise RecordingError(f"recording {recording.sequence_id!r} has neither ground truth nor pseudo-labels "
                                 f"(label it with 'aaute label')")
        times = reference.timestamps
        if times.size > 1:
            step = max(1, int(round(1.0 / (self.hparams.label_rate * np.median(np.diff(times))))))
            times = times[::step]
        return times

    def _count_skip(self, reason: str, count: int) -> None:
        if count:
            self.skipped[reason] = self.skipped.get(reason, 0) + int(count)

    def _samples(self, path: Path, recording: Recording) -> SequenceSamples | None:
        times = self._label_times(recording)
        keep = np.ones(times.size, dtype=bool)
        audio = recording.audio
        for recipe in (self.audio_recipe, self.phase_recipe):
            if recipe is not None and audio is None:
                raise RecordingError(f"{path}: the model needs audio ('{recipe.name}') but the recording has none")
        if self.phase_recipe is not None:
            if not wants_calibration(self.hparams.clock_calibration, recording.meta):
                warn_unshared_clocks(recording.meta, str(path), f"phase features ('{self.phase_recipe.name}')")
            require_mic_positions(recording, path, f"phase features ('{self.phase_recipe.name}')")
        if self.phase_recipe is not None and audio.num_channels < 2:
            raise RecordingError(f"{path}: phase features ('{self.phase_recipe.name}') need at least 2 microphones "
                                 f"with known positions; the recording has {audio.num_channels}")
        if audio is not None:  # every model gets the same windows: those with their audio inside the recording
            span = self.hparams.window_seconds
            if self.hparams.faithful_window_order and self.audio_recipe is not None:
                span = self.audio_recipe.chunk_seconds * (1 - min(self.audio_recipe.chunk_offsets))
            inside = (times - span >= audio.t0 - 1e-9) & (times <= audio.t_end + 1e-9)
            self._count_skip("window not inside the audio", int((keep & ~inside).sum()))
            keep &= inside
        image_index = np.full(times.size, -1)
        if recording.frames is not None and len(recording.frames):
            nearest = np.array([recording.frames.nearest(t) for t in times], dtype=np.int64)
            close = np.abs(recording.frames.timestamps[nearest] - times) <= self.hparams.image_tolerance_s
            image_index = np.where(close, nearest, -1)
        if self.image_recipe is not None:
            if recording.frames is None:
                raise RecordingError(f"{path}: the model needs images but the recording has no camera")
            self._count_skip("no camera frame near the label time", int((keep & (image_index < 0)).sum()))
            keep &= image_index >= 0
        times, image_index = times[keep], image_index[keep]
        if times.size == 0:
            log.warning("%s: no usable windows", path)
            return None

        tolerance = 0.5 / self.hparams.label_rate
        gt, gt_valid = _nearest(recording.ground_truth, times, tolerance)
        pseudo, pseudo_valid = _nearest(recording.pseudo_labels, times, tolerance)
        if self.hparams.targets == "pseudo":
            gt_valid[:] = False
        elif self.hparams.targets == "ground_truth":
            pseudo_valid[:] = False
        position = np.where(gt_valid[:, None], gt, pseudo)
        visible = _visibility(recording, position, image_index >= 0)
        from datamodules.simulate.drones import DRONES

        class_id = DRONES[recording.drone].class_id if recording.drone in DRONES else -1
        keys = self._build_features(path, recording, times, image_index)
        mics = audio.mic_positions.astype(np.float32) if self.phase_recipe is not None else None
        refused = isinstance(self.clock_estimates.get(str(path)), str)  # auto, and the audio could not tell them
        return SequenceSamples(path, recording.sequence_id, recording.drone, times, gt, gt_valid, pseudo,
                               pseudo_valid, image_index, visible, class_id, keys, mic_positions=mics,
                               uncorrected_clocks=refused)

    def _clock_calibration(self, path: Path, recording: Recording) -> ClockCalibration | None:
        """The nodes' clock offsets estimated from the recording's audio (cached beside its features).

        When the audio cannot tell them (too short, no coherent source, an unreliable fit), ``clock_calibration:
        on`` raises and ``auto`` warns and leaves the features uncorrected (None): time differences between
        its nodes then carry their clock error. Either way :attr:`clock_estimates` keeps the outcome."""
        config = ClockCalibrationConfig()
        audio = recording.audio
        options = repr(sorted((self.hparams.reader_options or {}).items())).encode()
        key = (f"clocks-{config.key()}-{array_fingerprint(audio.mic_positions.astype(np.float64))}-"
               f"{path_fingerprint(path)}-{zlib.crc32(options):08x}")

        def estimate(_: int) -> np.ndarray:
            try:
                return estimate_clock_offsets(audio, config).to_array()
            except ClockCalibrationError as error:
                raise ClockCalibrationError(f"{path}: {error} (set clock_calibration: off to skip it)") from None

        try:
            self.cache.build(key, 1, (5, audio.num_channels), np.float64, estimate)
        except ClockCalibrationError as error:
            if self.hparams.clock_calibration == "on":
                raise
            self.clock_estimates[str(path)] = str(error)
            log.warning("%s; its phase features are NOT corrected: its nodes' clock offsets stay in its time "
                        "differences", error)
            return None
        clocks = ClockCalibration.from_array(self.cache.open(key)[0])
        self.clock_estimates[str(path)] = clocks
        log.info("%s: %s", path, clocks.summary())
        return clocks

    def _build_features(self, path: Path, recording: Recording, times: np.ndarray,
                        image_index: np.ndarray) -> dict[str, str]:
        """Cache the model's inputs for every sample (entries that exist are reused)."""
        base = f"{path_fingerprint(path)}-{array_fingerprint(times)}"
        if self.hparams.reader_options:
            options = repr(sorted(self.hparams.reader_options.items())).encode()
            base += f"-{zlib.crc32(options):08x}"
        keys: dict[str, str] = {}
        if self.audio_recipe is not None:
            # stored without a second resize (applied on reading): avfdti_224 and avfdti_13 share avfdti's entries
            recipe, audio = stored_recipe(self.audio_recipe), recording.audio
            key = (f"mel-{recipe.key()}-{self.hparams.window_seconds:g}-{int(self.hparams.faithful_window_order)}"
                   f"-{WINDOW_INDEXING}-{base}")
            keys["audio_mel"] = key

            def mel(i: int) -> np.ndarray:
                window = audio_window(audio, float(times[i]), recipe, self.hparams.window_seconds,
                                      self.hparams.faithful_window_order)
                return mel_features(window, audio.sample_rate, recipe).numpy()

            self.cache.build(key, times.size, (audio.num_channels, *recipe.output_shape), np.float32, mel)
        if self.phase_recipe is not None:
            recipe, audio = self.phase_recipe, recording.audio
            mics = array_fingerprint(audio.mic_positions.astype(np.float64))
            key = f"phase-{recipe.key()}-{mics}-{WINDOW_INDEXING}-{base}"
            clocks = None
            if wants_calibration(self.hparams.clock_calibration, recording.meta):
                clocks = self._clock_calibration(path, recording)
            if clocks is not None:
                key += f"-clk{clocks.key()}"
            keys["audio_phase"] = key
            # float16 halves the cache (values lie in [-1, 1]; 1e-3 resolution is far below the frames' noise)
            self.cache.build(key, times.size, recipe.output_shape(audio.num_channels), np.float16,
                             PhaseWindows(audio, recipe, times, source=str(path), clocks=clocks))
        if self.image_recipe is not None:
            recipe, frames = self.image_recipe, recording.frames
            key = f"img-{recipe.key()}-{base}"
            keys["image"] = key

            def image(i: int) -> np.ndarray:
                return image_features(frames.image(int(image_index[i])), recipe).numpy()

            self.cache.build(key, times.size, (3, *recipe.size), np.uint8, image)
            if self.hparams.dark_mode == "physical":
                from datamodules.simulate.camera import darken_image

                dark_key = f"imgdark-{recipe.key()}-{base}"
                keys["image_dark"] = dark_key

                def dark(i: int) -> np.ndarray:
                    rng = np.random.default_rng([zlib.crc32(recording.sequence_id.encode()), i])
                    return image_features(darken_image(frames.image(int(image_index[i])), rng), recipe).numpy()

                self.cache.build(dark_key, times.size, (3, *recipe.size), np.uint8, dark)
        return keys

    # ------------------------------------------------------------------------------ loaders

    def _dataset(self, split_name: str, light: str, train: bool) -> WindowDataset:
        if not self.sequences:
            self.setup()
        self._require(None, (split_name,))
        sequences = self.sequences[split_name]
        offset = {sequence_id: i for i, sequence_id in enumerate(self.sequence_ids)}
        return WindowDataset(sequences, self.cache, [offset[s.sequence_id] for s in sequences], light,
                             self.hparams.dark_mode, self.hparams.train_dark_probability if train else 0.0,
                             mel_recipe=self.audio_recipe)

    def _loader(self, dataset: WindowDataset, shuffle: bool) -> DataLoader:
        return DataLoader(dataset, batch_size=self.hparams.batch_size, shuffle=shuffle,
                          num_workers=self.hparams.num_workers, drop_last=False,
                          persistent_workers=self.hparams.num_workers > 0)

    def train_dataloader(self) -> DataLoader:
        return self._loader(self._dataset("train", "ideal", train=True), shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self._dataset("val", self.hparams.light, train=False), shuffle=False)

    def test_dataloader(self) -> list[DataLoader]:
        return [self._loader(self._dataset("test", light, train=False), shuffle=False) for light in self.test_lights]

    def predict_dataloader(self) -> list[DataLoader]:
        return self.test_dataloader()
