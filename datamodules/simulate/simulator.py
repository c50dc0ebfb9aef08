"""Put the pieces together: one simulated flight -> :class:`Recording` -> MCAP files on disk.

Every random draw comes from a ``numpy`` generator seeded by (dataset seed, sequence index,
component), so the same seed gives the same bytes and changing one sensor's settings leaves the
others' draws untouched. All parameters and the realised random values (ambient level, wind,
SNR per microphone, source level offset) are stored in the recording's metadata, with the drone's SNR per
microphone, second and 25 Hz bin (``meta["audio"]["snr_spectrum"]``, :mod:`datamodules.snr`) that the
localisation bound needs.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from datamodules.atomic import check_output_folder
from datamodules.errors import ConfigError
from datamodules.formats.mcap_file import read_mcap, write_mcap
from datamodules.recording import (
    DRONE_TYPES,
    ArrayAudio,
    ArrayImages,
    ArrayPointClouds,
    Recording,
    RecordingError,
    Track,
    json_safe,
)
from datamodules.simulate import camera as camera_sim
from datamodules.simulate import lidar as lidar_sim
from datamodules.simulate import scene as scene_sim
from datamodules.simulate.acoustics import AudioConfig, render_audio
from datamodules.simulate.clocks import ClockConfig, draw_clocks
from datamodules.simulate.drones import drone_spec
from datamodules.simulate.microphones import mic_geometry
from datamodules.simulate.trajectory import TrajectoryConfig, generate_trajectory
from datamodules.workers import interruptible_pool

log = logging.getLogger(__name__)

SIMULATOR_VERSION = "1"
#: MMAUD V1 was recorded on 2023-08-24 (TAME ground-truth timestamps); simulated flights start there.
DEFAULT_EPOCH = 1692845357.0
COMPONENTS = ("trajectory", "audio", "mid360", "avia", "camera", "ground_truth", "clocks")


@dataclass
class SimulationConfig:
    """What to simulate for one flight (every sensor's own parameters live in its config)."""

    duration: float = 60.0
    drone: str | None = None  #: None: the dataset cycles through the five types
    scene: str = "rooftop"  #: 'rooftop' (MMAUD V1) or 'carpark'
    light: str = "ideal"  #: camera condition: 'ideal' or 'dark' (physical low-light rendering)
    lidar_sensors: tuple[str, ...] = ("mid360", "avia")
    camera: bool = True
    epoch: float = DEFAULT_EPOCH
    sequence_spacing: float = 3600.0  #: seconds between the start times of successive sequences
    preroll: float = 1.0  #: seconds of flight before the first sample (room for the sound to arrive)
    ground_truth_rate: float = 10.0  #: Hz; MMAUD/TAME ground truth is 10 Hz [V S2]
    prism_noise_m: float = 0.002  #: Leica MS60 kinematic noise, mm-level [M]
    lidar_rate: float = 10.0  #: Hz, Livox default publish rate [V S42]
    avia_offset_s: float = 0.014  #: the UG2 Avia stamps trail the Mid-360 by about 14 ms [V]
    camera_offset_s: float = 0.033
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    audio: AudioConfig = field(default_factory=AudioConfig)
    clocks: ClockConfig | None = None  #: separate node clocks (None: one shared, exact clock)

    def check(self) -> None:
        """Refuse settings that cannot make a recording (non-positive or too short duration, rate <= 0).

        Raises:
            ConfigError: naming the setting, its value and what is allowed.
        """
        shortest = 2.0 / min(self.lidar_rate, self.ground_truth_rate)
        if not np.isfinite(self.duration) or self.duration < shortest:
            raise ConfigError(f"duration (--seconds) must be at least {shortest:g} s (two LiDAR and ground-truth "
                              f"periods), got {self.duration:g}")
        rate = self.audio.sample_rate
        if not np.isfinite(rate) or rate <= 0:
            raise ConfigError(f"audio sample rate (--sample-rate) must be a positive number of Hz, got {rate:g}")

    def fingerprint(self) -> str:
        """Short hash of every parameter, used to recognise a recording made with these settings."""
        settings = dataclasses.asdict(self)
        if self.clocks is None:  # recordings made before node clocks existed keep their fingerprint
            del settings["clocks"]
        text = json.dumps(settings, sort_keys=True, default=str)
        return hashlib.sha256(f"{SIMULATOR_VERSION}:{text}".encode()).hexdigest()[:16]


@contextmanager
def _timed(stage: str) -> Iterator[None]:
    """Log a stage's duration at DEBUG level (``stage`` and ``seconds`` as record attributes)."""
    start = time.perf_counter()
    yield
    seconds = time.perf_counter() - start
    log.debug("%s took %.2f s", stage, seconds, extra={"stage": stage, "seconds": seconds})


def _rngs(seed: int, index: int) -> dict[str, np.random.Generator]:
    children = np.random.SeedSequence([seed, index]).spawn(len(COMPONENTS))
    return {name: np.random.default_rng(child) for name, child in zip(COMPONENTS, children, strict=True)}


def simulate_recording(config: SimulationConfig, seed: int, index: int = 0, sequence_id: str | None = None
                       ) -> Recording:
    """Simulate one flight; ``index`` selects the sequence within a seeded dataset."""
    drone = config.drone or DRONE_TYPES[index % len(DRONE_TYPES)]
    spec = drone_spec(drone)
    rngs = _rngs(seed, index)
    duration, preroll = float(config.duration), float(config.preroll)
    t0 = config.epoch + index * config.sequence_spacing
    # recording clock: 0 = first audio sample; the flight starts ``preroll`` earlier
    with _timed("trajectory"):
        trajectory = generate_trajectory(duration + preroll + 1.0, rngs["trajectory"], config.trajectory)
        trajectory = trajectory.shifted(preroll)

    audio_config, clocks = config.audio, None
    if config.clocks is not None and config.clocks.active():
        clocks = draw_clocks(config.clocks, mic_geometry(config.audio.microphones).shape[0], duration, rngs["clocks"])
        audio_config = dataclasses.replace(audio_config, clock_offset_s=clocks.effective_offsets_s.tolist(),
                                           clock_drift_ppm=clocks.drifts_ppm.tolist())
    with _timed("audio"):
        audio = render_audio(spec, trajectory, duration, rngs["audio"], audio_config)
    audio_stream = ArrayAudio(audio.samples, audio.sample_rate, t0, audio.mic_positions,
                              sample_format=f"S{config.audio.bits}LE" if config.audio.bits in (16, 32) else None)

    scene = scene_sim.make_scene(config.scene)
    lidar = {}
    for sensor in config.lidar_sensors:
        model = lidar_sim.LidarModel.preset(sensor)
        offset = config.avia_offset_s if sensor == "avia" else 0.0
        frame_times = np.arange(offset, duration - 1.0 / config.lidar_rate + 1e-9, 1.0 / config.lidar_rate)
        with _timed(sensor):
            clouds = lidar_sim.simulate_lidar(model, scene, spec, trajectory, frame_times, rngs[sensor])
        lidar[sensor] = ArrayPointClouds(t0 + frame_times, clouds)

    frames = None
    if config.camera:
        model = camera_sim.CameraModel()
        frame_times = np.arange(config.camera_offset_s, duration, 1.0 / model.frame_rate)
        with _timed("camera"):
            images = camera_sim.simulate_camera(model, spec, trajectory, frame_times, config.light, rngs["camera"])
        frames = ArrayImages(t0 + frame_times, images)

    gt_times = np.arange(0.0, duration, 1.0 / config.ground_truth_rate)
    gt_xyz = trajectory.position(gt_times)
    gt_xyz = gt_xyz + rngs["ground_truth"].normal(0.0, config.prism_noise_m, gt_xyz.shape)

    meta: dict[str, Any] = {
        "source_format": "simulator",
        "simulator_version": SIMULATOR_VERSION,
        "seed": int(seed),
        "index": int(index),
        "fingerprint": config.fingerprint(),
        "scene": config.scene,
        "light": config.light,
        "config": dataclasses.asdict(config),
        "audio": {
            "snr_db": audio.snr_db.round(2).tolist(),
            "snr_db_mean": round(float(np.mean(audio.snr_db)), 2),
            "ambient_dba": round(audio.ambient.level_dba, 2),
            "ambient_slope": round(audio.ambient.slope, 3),
            "wind_speed": round(audio.ambient.wind_speed, 3),
            "hvac_dba": None if audio.ambient.hvac_dba is None else round(audio.ambient.hvac_dba, 2),
            "source_level_offset_db": round(audio.flight_level_db, 2),
            "full_scale_pa": audio.full_scale_pa,
            "clipped_samples": audio.clipped_samples,
            **({} if audio.snr_spectrum is None else {"snr_spectrum": audio.snr_spectrum.to_meta()}),
        },
        "sensor_poses": {sensor: list(lidar_sim.LidarModel.preset(sensor).position)
                         for sensor in config.lidar_sensors},
    }
    if clocks is not None:  # the truth, for evaluation only; readers and models see only nodes_share_clock
        meta["clocks_truth"] = clocks.meta()
        meta["nodes_share_clock"] = False
    if audio.clipped_samples:
        log.warning("%s: %d audio samples clipped at full scale", sequence_id, audio.clipped_samples)
    return Recording(
        sequence_id=sequence_id or f"sim{seed}-{index:04d}-{drone}",
        drone=drone,
        audio=audio_stream,
        lidar=lidar,
        frames=frames,
        ground_truth=Track(t0 + gt_times, gt_xyz),
        meta=json_safe(meta),
    )


# ============================================================================================ dataset


def recording_path(out_dir: Path, seed: int, index: int) -> Path:
    return Path(out_dir) / f"sim{seed}_{index:04d}.mcap"


def _existing_matches(path: Path, config: SimulationConfig, seed: int, index: int) -> bool:
    """True if ``path`` already holds this very recording; raise if it holds a different one."""
    try:
        meta = read_mcap(path).meta
    except RecordingError as error:
        raise RecordingError(f"{path} exists but is not a readable recording ({error}); remove it") from error
    same = (meta.get("fingerprint") == config.fingerprint() and meta.get("seed") == seed
            and meta.get("index") == index)
    if not same:
        raise RecordingError(
            f"{path} already holds a different recording (seed {meta.get('seed')}, index {meta.get('index')}, "
            f"settings {meta.get('fingerprint')}; asked for seed {seed}, index {index}, settings "
            f"{config.fingerprint()}); choose another --out or remove it"
        )
    return True


def _simulate_one(args: tuple[Path, SimulationConfig, int, int]) -> Path:
    path, config, seed, index = args
    recording = simulate_recording(config, seed, index)
    write_mcap(recording, path)
    return path


def simulate_dataset(
    out_dir: str | Path,
    sequences: int,
    config: SimulationConfig,
    seed: int = 0,
    workers: int = 1,
    progress: bool = True,
) -> list[Path]:
    """Simulate ``sequences`` flights into ``out_dir`` (one MCAP each), resuming finished ones."""
    from tqdm import tqdm

    if sequences < 1:
        raise ConfigError(f"number of sequences (--sequences) must be at least 1, got {sequences}")
    if workers < 1:
        raise ConfigError(f"workers (--workers) must be at least 1, got {workers}")
    config.check()
    out_dir = check_output_folder(out_dir, "the simulator's output folder (--out)")  # before any simulating
    paths = [recording_path(out_dir, seed, i) for i in range(sequences)]
    todo = [(p, config, seed, i) for i, p in enumerate(paths) if not (p.exists() and
                                                                       _existing_matches(p, config, seed, i))]
    if len(todo) < len(paths):
        log.info("%d of %d recordings already present in %s", len(paths) - len(todo), len(paths), out_dir)
    bar = tqdm(total=len(todo), desc="simulate", unit="rec", disable=not progress)
    finished = 0
    try:
        if workers > 1 and len(todo) > 1:
            # leaving the block terminates the workers at once: Ctrl-C starts no further recording
            with interruptible_pool(min(workers, len(todo))) as pool:
                for _ in pool.imap_unordered(_simulate_one, todo):
                    finished += 1
                    bar.update()
        else:
            for job in todo:
                _simulate_one(job)
                finished += 1
                bar.update()
    except KeyboardInterrupt:
        bar.close()
        log.warning("interrupted: %d of %d recordings complete in %s, %d not started or discarded; run the same "
                    "command again to resume", len(paths) - len(todo) + finished, len(paths), out_dir,
                    len(todo) - finished)
        raise
    bar.close()
    return paths
