"""The LiDAR teacher end to end: a :class:`Recording` in, a pseudo-label :class:`Track` out.

Stages (each in its own module, every threshold a :class:`TeacherConfig` field):

1. :mod:`~datamodules.teacher.frames`: drop padding / NaN points, check units and timestamps;
2. Mid-360 in chunks of 20 scans: :mod:`~datamodules.teacher.background` (static cubes, this
   project's addition) then :mod:`~datamodules.teacher.clustering` (the paper's DBSCAN, merge,
   drop largest/smallest, density) -> the chunk's UAV returns, given back to their scans;
3. Avia per frame: :mod:`~datamodules.teacher.sampling` (farthest point sampling);
4. :mod:`~datamodules.teacher.fusion`: both sensors by time, DBSCAN against solar returns,
   one centroid per frame;
5. :mod:`~datamodules.teacher.spline`: B-spline through the centroids at the label times, gaps
   where there is no evidence, per-label quality.

Frames are streamed: the Mid-360 is read twice (a first pass builds the static-background map),
and memory holds one chunk, the fusion window and the map, never the recording's points. Nothing
is hard-coded about the rig: ranges are measured from each sensor's position
(``meta["sensor_poses"]``, else the origin), and no height threshold is used.
"""

from __future__ import annotations

import dataclasses
import heapq
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from datamodules.recording import LIDAR_SENSORS, PointCloudStream, Recording, RecordingError, Track, check_monotonic
from datamodules.teacher import background, clustering, fusion, sampling, spline
from datamodules.teacher.frames import FrameStats, check_timestamps, check_units, clean_points

log = logging.getLogger(__name__)


@dataclass
class TeacherConfig:
    """Every threshold of the teacher. [B] = AAUTE paper's value, [D] = Deng et al.'s code,
    [L] = Liang et al.'s code (``reference/mmaud_and_teacher.md`` section 3), [P] = this project."""

    # --- input hygiene
    unit_scale: float = 1.0  #: factor to metres of the stored coordinates (0.001 for millimetres) [P]
    max_range_m: float = 1000.0  #: returns farther from their sensor are dropped (Avia gate 450 m) [P]
    max_median_range_m: float = 500.0  #: a larger median range means wrong units: error [P]
    #: time of a frame's returns relative to its stamp (s); None = half the frame period, because Livox
    #: drivers stamp a frame with its first point and the returns spread over the 0.1 s frame [P]
    frame_time_offset_s: float | None = None
    # --- Mid-360 chunks and clustering
    chunk_frames: int = 20  #: consecutive scans per chunk [B]
    min_chunk_frames: int = 10  #: a shorter last chunk joins the one before [P]
    dbscan_eps: float = 1.0  #: [B]
    dbscan_min_samples: int = 10  #: [B]
    dbscan_cube_m: float = 0.25  #: returns sharing a cube this size are one weighted DBSCAN sample (speed) [P]
    merge_distance_m: float = 2.5  #: [B]
    min_component_size: int = 20  #: [B]
    drop_extremes: bool = True  #: drop the largest and the smallest component [B]
    drop_extremes_min_components: int = 3  #: ... only with at least this many [P]
    density_voxel_m: float = 0.5  #: cube of the density rule ([L] uses 0.2 m; see cluster_density) [P]
    min_frames: int = 2  #: a UAV component has returns in at least this many scans of its chunk [P]
    min_density: float = 0.0  #: minimum density of a UAV component (returns / m^3; 0 = off) [P]
    max_frame_extent_m: float = 2.0  #: widest spread of a UAV component's returns in one scan [P]
    # --- static background (this project's addition, see datamodules.teacher.background)
    static_filter: bool = True  #: False runs the paper's steps literally on every return (slow)
    static_voxel_m: float = 0.5  #: cube side near the sensor (m) [P]
    static_near_range_m: float = 15.0  #: cubes double in size with every doubling of range beyond this [P]
    static_min_fraction: float = 0.8  #: share of the recording's chunks a static cube is occupied in [P]
    static_min_chunks: int = 4  #: ... and at least this many chunks [P]
    static_dilation: int = 1  #: neighbour cubes of a static cube that make a return static too [P]
    contact_m: float = 0.3  #: a return this close to a static one touches static structure [P]
    max_contact_share: float = 0.5  #: a UAV component may touch static structure with at most this share [P]
    avia_static_filter: bool = False  #: the Avia looks at open sky; set True if it sees structures [P]
    # --- Avia
    avia_max_points: int = 100  #: farthest point sampling bound per frame [D]
    # --- fusion and solar-noise DBSCAN
    fusion_eps: float = 1.0  #: [D]; the AAUTE paper gives none
    fusion_min_samples: int = 10  #: [D]
    fusion_block_s: float = 2.0  #: frames decided per DBSCAN block [P]
    fusion_pad_s: float = 2.0  #: context on each side of a block [P]
    # --- spline, gaps and quality (see datamodules.teacher.spline)
    spline_degree: int = 3  #: cubic [D]
    smoothing: float = 1.0  #: multiplies FITPACK's s = m for 1/sigma weights [P]
    point_sigma_m: float = 0.3  #: scatter of single returns about the drone centre (m) [P]
    floor_sigma_m: float = 0.1  #: noise floor of a frame centroid (m) [P]
    outlier_m: float = 1.5  #: evidence this far from its neighbours' median is dropped (m) [P]
    outlier_window_s: float = 0.5  #: half-window of that median (s) [P]
    max_gap_s: float = 1.0  #: longest stretch without evidence the spline bridges [P]
    max_extrapolation_s: float = 0.5  #: labels at most this far beyond a segment's evidence [P]
    support_window_s: float = 0.5  #: half-window of a label's support_points / residual_m (s) [P]
    # --- label times
    label_times: str = "ground_truth"  #: 'ground_truth' (its times when present, else the grid) or 'grid'
    grid_rate_hz: float = 10.0  #: rate of the grid over the LiDAR span (MMAUD labels are 10 Hz)

    def __post_init__(self) -> None:
        if self.label_times not in ("ground_truth", "grid"):
            raise ValueError(f"label_times must be 'ground_truth' or 'grid', not {self.label_times!r}")
        if self.chunk_frames < 1 or self.min_chunk_frames < 1:
            raise ValueError("chunk_frames and min_chunk_frames must be positive")

    @classmethod
    def from_overrides(cls, overrides: dict[str, Any]) -> TeacherConfig:
        """A config with some fields replaced (values given as strings are converted to the field's type)."""
        fields = {f.name: f for f in dataclasses.fields(cls)}
        default = cls()
        values = {}
        for name, value in overrides.items():
            if name not in fields:
                raise ValueError(f"unknown teacher parameter {name!r}; known: {sorted(fields)}")
            values[name] = _convert(value, getattr(default, name)) if isinstance(value, str) else value
        return dataclasses.replace(default, **values)


def _convert(text: str, default: Any) -> Any:
    if text.lower() in ("none", "null"):
        return None
    if isinstance(default, bool):
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"not a boolean: {text!r}")
    if isinstance(default, int):
        return int(text)
    if isinstance(default, float) or default is None:
        return float(text)
    return text


@dataclass
class TeacherResult:
    """The track and what led to it."""

    track: Track
    evidence: dict[str, np.ndarray]  #: per-frame centroids: time, xyz, count, sensor
    stats: dict[str, FrameStats]
    chunks: list[clustering.ChunkResult] = field(default_factory=list)
    seconds: float = 0.0


# ----------------------------------------------------------------------------------------- chunks


@dataclass
class _Chunk:
    index: int
    first_frame: int
    times: np.ndarray
    points: np.ndarray
    frame_index: np.ndarray


def chunk_bounds(n_frames: int, chunk_frames: int, min_chunk_frames: int) -> list[tuple[int, int]]:
    """Consecutive, non-overlapping chunks of ``chunk_frames``; a short tail joins the last chunk."""
    bounds = [(a, min(a + chunk_frames, n_frames)) for a in range(0, n_frames, chunk_frames)]
    if len(bounds) > 1 and bounds[-1][1] - bounds[-1][0] < min_chunk_frames:
        bounds[-2] = (bounds[-2][0], bounds[-1][1])
        bounds.pop()
    return bounds


def _sensor_position(recording: Recording, sensor: str) -> np.ndarray:
    poses = recording.meta.get("sensor_poses") or {}
    pose = poses.get(sensor)
    return np.zeros(3) if pose is None else np.asarray(pose, dtype=np.float64)[:3]


def _frame_offset(times: np.ndarray, config: TeacherConfig) -> float:
    if config.frame_time_offset_s is not None:
        return float(config.frame_time_offset_s)
    return 0.5 * float(np.median(np.diff(times))) if times.size > 1 else 0.0


class _Sensor:
    """One LiDAR stream with its timestamps, position and hygiene counters."""

    def __init__(self, recording: Recording, name: str, stream: PointCloudStream, config: TeacherConfig):
        self.name, self.stream, self.config = name, stream, config
        self.what = f"{recording.sequence_id} {name}"
        self.times = check_timestamps(stream, self.what)
        self.position = _sensor_position(recording, name)
        self.offset = _frame_offset(self.times, config)
        self.stats = FrameStats(name)
        self.bounds = chunk_bounds(len(self.times), config.chunk_frames, config.min_chunk_frames)

    def chunks(self, progress: Callable[[int], None], count: bool = True) -> Iterator[_Chunk]:
        """The chunks in order; ``count`` False reads again without counting (a second pass)."""
        stats = self.stats if count else FrameStats(self.name)
        c = self.config
        for index, (a, b) in enumerate(self.bounds):
            frames = []
            for i in range(a, b):
                frames.append(clean_points(self.stream[i].points, stats, self.position, c.unit_scale, c.max_range_m))
                if count and len(stats.median_ranges) < 20:
                    check_units(stats, self.what, c.max_median_range_m)
            points = np.concatenate(frames)
            frame_index = np.repeat(np.arange(b - a), [f.shape[0] for f in frames])
            progress(b - a)
            yield _Chunk(index, a, self.times[a:b], points, frame_index)


def _survey(sensor: _Sensor, progress: Callable[[int], None]) -> background.StaticMap:
    """First pass: the static-background map of the sensor's whole recording."""
    c = sensor.config
    static_map = background.StaticMap(sensor.position, c.static_voxel_m, c.static_near_range_m,
                                      c.static_min_fraction, c.static_min_chunks, c.static_dilation)
    for chunk in sensor.chunks(progress):
        static_map.add_chunk(chunk.points)
    static_map.finish()
    if not static_map.known:
        log.warning("%s: %d chunk(s) are too few to tell static background from a drone; its returns are not "
                    "used (static_filter=False runs the paper's steps on them anyway)", sensor.what,
                    static_map.n_chunks)
    elif static_map.n_chunks < c.static_min_chunks:
        log.warning("%s: only %d chunks; a cube occupied in all of them counts as background, so a drone "
                    "hovering throughout is lost", sensor.what, static_map.n_chunks)
    return static_map


def _mid360_frames(sensor: _Sensor, chunks_out: list, progress: Callable[[int], None]) -> Iterator[fusion.FramePoints]:
    """The Mid-360's dynamic part: per scan, the returns of its chunk's UAV component."""
    c = sensor.config
    static_map = _survey(sensor, progress) if c.static_filter else None
    if static_map is not None and not static_map.known:
        return
    for chunk in sensor.chunks(progress, count=static_map is None):
        static = None if static_map is None else static_map.is_static(chunk.points)
        mask, result = clustering.extract_uav(
            chunk.points, chunk.frame_index, static, eps=c.dbscan_eps, min_samples=c.dbscan_min_samples,
            cube_m=c.dbscan_cube_m,
            merge_distance=c.merge_distance_m, min_component_size=c.min_component_size,
            drop_extremes=c.drop_extremes, drop_extremes_min_components=c.drop_extremes_min_components,
            contact_m=c.contact_m, max_contact_share=c.max_contact_share, density_voxel_m=c.density_voxel_m,
            min_frames=c.min_frames,
            max_frame_extent_m=c.max_frame_extent_m, min_density=c.min_density)
        chunks_out.append(result)
        if not mask.any():
            continue
        chosen_frames = chunk.frame_index[mask]
        chosen = chunk.points[mask]
        for j in np.unique(chosen_frames):
            yield fusion.FramePoints(float(chunk.times[j]) + sensor.offset, sensor.name, chosen[chosen_frames == j])


def _avia_frames(sensor: _Sensor, progress: Callable[[int], None]) -> Iterator[fusion.FramePoints]:
    """The Avia's frames after farthest point sampling (static returns dropped first if asked)."""
    c = sensor.config
    static_map = _survey(sensor, progress) if c.avia_static_filter else None
    for chunk in sensor.chunks(progress, count=static_map is None):
        keep = np.ones(chunk.points.shape[0], dtype=bool)
        if static_map is not None and static_map.known:
            keep = ~static_map.is_static(chunk.points)
        for j in range(chunk.times.size):
            points = chunk.points[keep & (chunk.frame_index == j)]
            if points.shape[0] == 0:
                continue
            points = points[sampling.farthest_point_sampling(points, c.avia_max_points)]
            yield fusion.FramePoints(float(chunk.times[j]) + sensor.offset, sensor.name, points)


# --------------------------------------------------------------------------------------- labelling


def label_times(recording: Recording, config: TeacherConfig, lidar_span: tuple[float, float]) -> np.ndarray:
    """Where the track is evaluated: the ground-truth times if asked and present, else a grid."""
    gt = recording.ground_truth
    if config.label_times == "ground_truth" and gt is not None and len(gt):
        check_monotonic(gt.timestamps, f"{recording.sequence_id} ground truth")
        return np.asarray(gt.timestamps, dtype=np.float64)
    start, stop = lidar_span
    step = 1.0 / config.grid_rate_hz
    return start + step * np.arange(int(np.floor((stop - start) / step + 1e-9)) + 1)


def run_teacher(recording: Recording, config: TeacherConfig | None = None,
                progress: Callable[[int, int], None] | None = None) -> TeacherResult:
    """Pseudo-label one recording, keeping the intermediate evidence and counters.

    Args:
        recording: any recording with at least one LiDAR stream.
        config: thresholds (defaults: the paper's values, see :class:`TeacherConfig`).
        progress: called as ``progress(frames_done, frames_total)`` while frames are read.

    Raises:
        RecordingError: no LiDAR, no returns at all, wrong units, timestamps not increasing.
    """
    config = config or TeacherConfig()
    started = time.perf_counter()
    streams = {name: s for name, s in recording.lidar.items() if s is not None and len(s)}
    if not streams:
        raise RecordingError(f"{recording.sequence_id}: no LiDAR frames (expected {' and/or '.join(LIDAR_SENSORS)}); "
                             f"the teacher needs LiDAR")
    sensors = {name: _Sensor(recording, name, stream, config) for name, stream in streams.items()}
    passes = {"mid360": 1 + int(config.static_filter), "avia": 1 + int(config.avia_static_filter)}
    total = sum(len(s.times) * passes[name] for name, s in sensors.items())
    done = [0]

    def advance(frames: int) -> None:
        done[0] += frames
        if progress is not None:
            progress(done[0], total)

    chunks: list[clustering.ChunkResult] = []
    generators = []
    if "mid360" in sensors:
        generators.append(_mid360_frames(sensors["mid360"], chunks, advance))
    if "avia" in sensors:
        generators.append(_avia_frames(sensors["avia"], advance))
    merged = heapq.merge(*generators, key=lambda f: f.time)
    evidence = list(fusion.denoise_fused(merged, config.fusion_eps, config.fusion_min_samples,
                                         config.fusion_block_s, config.fusion_pad_s, config.dbscan_cube_m))
    for sensor in sensors.values():
        sensor.stats.report(recording.sequence_id)
    if sum(s.stats.points for s in sensors.values()) == 0:
        raise RecordingError(f"{recording.sequence_id}: every LiDAR frame is empty (padding, zeros or NaN only); "
                             f"there is no evidence to pseudo-label")
    span = (min(float(s.times[0]) for s in sensors.values()), max(float(s.times[-1]) for s in sensors.values()))
    times = label_times(recording, config, span)
    ev = {
        "time": np.array([e.time for e in evidence], dtype=np.float64),
        "xyz": np.array([e.xyz for e in evidence], dtype=np.float64).reshape(-1, 3),
        "count": np.array([e.count for e in evidence], dtype=np.int64),
        "sensor": np.array([e.sensor for e in evidence], dtype=object),
    }
    track = spline.fit_track(
        ev["time"], ev["xyz"], ev["count"], times, max_gap_s=config.max_gap_s,
        max_extrapolation_s=config.max_extrapolation_s, degree=config.spline_degree, smoothing=config.smoothing,
        point_sigma_m=config.point_sigma_m, floor_sigma_m=config.floor_sigma_m, outlier_m=config.outlier_m,
        outlier_window_s=config.outlier_window_s,
        support_window_s=config.support_window_s)
    seconds = time.perf_counter() - started
    labelled = int(track.valid.sum())
    if not evidence:
        log.warning("%s: no LiDAR evidence of a drone; every label time is a gap", recording.sequence_id)
    log.info("%s: %d of %d label times labelled from %d evidence frames (%.1f s)", recording.sequence_id, labelled,
             len(track), len(evidence), seconds)
    stats = {name: s.stats for name, s in sensors.items()}
    return TeacherResult(track, ev, stats, chunks, seconds)


def label_recording(recording: Recording, config: TeacherConfig | None = None) -> Track:
    """The pseudo-label track of ``recording`` (``valid`` False in gaps, per-label ``quality``)."""
    return run_teacher(recording, config).track
