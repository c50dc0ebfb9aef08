"""Benchmark of the LiDAR teacher: accuracy and coverage on simulated flights, speed, memory.

Run ``python -m benchmarks.studies.teacher_bench`` (``--quick`` for a short run). Prints three tables:

1. accuracy and coverage per drone and range band (distance of the drone to the nearest LiDAR at
   each ground-truth time) on simulated recordings of several flight regions, pooled over seeds;
   coverage is given against all ground-truth times and against the times at which the drone
   produced at least k LiDAR returns in the surrounding 2 s chunk (k = 1, 10, 20; known from the
   simulator's per-point origin labels), plus the labels given for a drone out of LiDAR view;
2. speed: CPU seconds per minute of LiDAR for Mid-360 frames of about 20,000 real returns (the
   simulated rooftop seen at 4.5 times the Mid-360's point rate) plus the Avia, in memory and read
   from an MCAP file;
3. memory: peak traced allocation while labelling 1 and 5 minutes of those frames (the 5 minutes
   repeat the first minute lazily, so only the teacher's own memory is measured).

The simulated audio is irrelevant to the teacher; it is rendered at 8 kHz to save time.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from datamodules.recording import DRONE_TYPES, ArrayPointClouds, PointCloud, PointCloudStream, Recording
from datamodules.simulate import lidar as lidar_sim
from datamodules.simulate import scene as scene_sim
from datamodules.simulate.acoustics import AudioConfig
from datamodules.simulate.drones import drone_spec
from datamodules.simulate.simulator import SimulationConfig, simulate_recording
from datamodules.simulate.trajectory import TrajectoryConfig, generate_trajectory
from datamodules.teacher import TeacherConfig, run_teacher
from datamodules.teacher.evaluate import (
    drone_returns_near,
    evaluate_track,
    pool_scores,
    sensor_distance,
)

log = logging.getLogger(__name__)

#: flight regions (rig frame, metres): min corner, max corner
REGIONS = {
    "mmaud": ((-2.0, -5.0, 0.5), (8.0, 25.0, 25.0)),  # the MMAUD flight region (simulator default)
    "near": ((-8.0, -8.0, 0.5), (8.0, 8.0, 6.0)),
    "mid": ((-2.0, 10.0, 0.5), (8.0, 20.0, 12.0)),
    "far": ((-2.0, 25.0, 0.5), (8.0, 37.0, 15.0)),
    "high": ((-3.0, -3.0, 8.0), (3.0, 3.0, 25.0)),  # above the Mid-360's 52 degrees: Avia only
}
OUT_OF_VIEW = ((70.0, 70.0, 0.5), (90.0, 90.0, 5.0))  # beyond the Mid-360 gate, outside the Avia cone
BANDS = ((0.0, 10.0), (10.0, 20.0), (20.0, 30.0), (30.0, 40.0))
THRESHOLDS = (1, 10, 20)


def simulate(drone: str, region: tuple, seconds: float, seed: int, index: int) -> Recording:
    """A simulated flight of ``drone`` within ``region`` (no camera, 8 kHz audio)."""
    lo, hi = region
    config = SimulationConfig(duration=seconds, drone=drone, camera=False, audio=AudioConfig(sample_rate=8000.0),
                              trajectory=TrajectoryConfig(region_min=lo, region_max=hi))
    recording = simulate_recording(config, seed, index)
    recording.audio = None
    return recording


def accuracy_table(seconds: float, seeds: int, config: TeacherConfig) -> None:
    """Table 1: error and coverage per drone and range band, and the out-of-view check."""
    scores: dict[tuple[str, str], list] = {}
    out_of_view = []
    index = 0
    for drone in DRONE_TYPES:
        for region in REGIONS.values():
            for seed in range(seeds):
                index += 1
                recording = simulate(drone, region, seconds, 100 + seed, index)
                track = run_teacher(recording, config).track
                gt = recording.ground_truth
                distance = sensor_distance(recording, gt.xyz)
                returns = drone_returns_near(recording, gt.timestamps)
                for lo, hi in BANDS:
                    mask = (distance >= lo) & (distance < hi)
                    if mask.any():
                        score = evaluate_track(track, gt, mask=mask, returns=returns, thresholds=THRESHOLDS)
                        scores.setdefault((drone, f"{lo:.0f}-{hi:.0f} m"), []).append(score)
                        scores.setdefault(("all", f"{lo:.0f}-{hi:.0f} m"), []).append(score)
                within = evaluate_track(track, gt, mask=distance <= 40.0, returns=returns, thresholds=THRESHOLDS)
                scores.setdefault((drone, "<=40 m"), []).append(within)
                scores.setdefault(("all", "<=40 m"), []).append(within)
        recording = simulate(drone, OUT_OF_VIEW, seconds, 100, 1000 + index)
        returns = drone_returns_near(recording, recording.ground_truth.timestamps)
        track = run_teacher(recording, config).track
        out_of_view.append((drone, int(np.sum(returns)), int(track.valid.sum()), len(track)))

    header = (f"{'drone':9s} {'band':8s} {'gt':>6s} {'lab':>6s} {'mean':>6s} {'med':>6s} {'p95':>6s} "
              f"{'cov':>6s} " + " ".join(f"{'cov>=' + str(k):>8s}" for k in THRESHOLDS))
    print("\n1. Teacher error (m) and coverage on simulated flights "
          f"({len(REGIONS)} regions x {seeds} seed(s) x {seconds:.0f} s per drone)")
    print(header)
    print("-" * len(header))
    for drone in (*DRONE_TYPES, "all"):
        for band in [f"{lo:.0f}-{hi:.0f} m" for lo, hi in BANDS] + ["<=40 m"]:
            if (drone, band) not in scores:
                continue
            s = pool_scores(scores[(drone, band)])
            covs = " ".join(f"{s.coverage_returns.get(k, float('nan')):8.3f}" for k in THRESHOLDS)
            print(f"{drone:9s} {band:8s} {s.n_times:6d} {s.n_labelled:6d} {s.mean_m:6.3f} {s.median_m:6.3f} "
                  f"{s.p95_m:6.3f} {s.coverage:6.3f} {covs}")
    print("\nOut of LiDAR view (drone 100-127 m away, low): drone returns / labels given / label times")
    for drone, n_returns, labelled, total in out_of_view:
        print(f"  {drone:9s} {n_returns:6d} returns  {labelled:4d} / {total} labelled")


class LoopedStream(PointCloudStream):
    """A stream that repeats another's frames ``times`` times, lazily (for the memory benchmark)."""

    def __init__(self, base: PointCloudStream, times: int):
        self.base = base
        period = float(base.timestamps[-1] - base.timestamps[0]) + float(np.median(np.diff(base.timestamps)))
        self.timestamps = np.concatenate([base.timestamps + k * period for k in range(times)])

    def __getitem__(self, index: int) -> PointCloud:
        return self.base[index % len(self.base)]


def dense_recording(seconds: float, seed: int = 0) -> Recording:
    """Mid-360 frames of about 20,000 real returns (4.5 x the point rate) plus a regular Avia, M300 flight."""
    rng = np.random.default_rng(seed)
    trajectory = generate_trajectory(seconds + 2.0, rng)
    spec = drone_spec("m300")
    scene = scene_sim.make_scene("rooftop")
    times = np.arange(0.0, seconds, 0.1)
    mid = lidar_sim.LidarModel.preset("mid360", point_rate_hz=900_000.0)
    avia = lidar_sim.LidarModel.preset("avia")
    t0 = 1.7e9
    lidar = {
        "mid360": ArrayPointClouds(t0 + times, lidar_sim.simulate_lidar(mid, scene, spec, trajectory, times, rng)),
        "avia": ArrayPointClouds(t0 + times + 0.014,
                                 lidar_sim.simulate_lidar(avia, scene, spec, trajectory, times + 0.014, rng)),
    }
    poses = {"mid360": list(mid.position), "avia": list(avia.position)}
    return Recording("dense", "m300", lidar=lidar, meta={"sensor_poses": poses})


def speed_table(seconds: float, config: TeacherConfig, repeats: int = 2) -> Recording:
    """Table 2: CPU seconds per minute of LiDAR (in memory and from MCAP)."""
    from datamodules.formats.mcap_file import read_mcap, write_mcap

    recording = dense_recording(seconds)
    points = np.mean([len(c) for c in recording.lidar["mid360"].clouds])
    per_minute = 60.0 / seconds
    rows = []
    best = min(_cpu(lambda: run_teacher(recording, config)) for _ in range(repeats))
    rows.append(("in memory", best * per_minute))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "dense.mcap"
        write_mcap(recording, path)
        best = min(_cpu(lambda: run_teacher(read_mcap(path), config)) for _ in range(repeats))
        rows.append(("from MCAP", best * per_minute))
    print(f"\n2. Speed: Mid-360 frames of {points:.0f} returns + Avia, {seconds:.0f} s of LiDAR, "
          f"one process ({os.cpu_count()} cores, load {os.getloadavg()[0]:.1f})")
    print(f"{'input':12s} {'CPU s per minute of LiDAR':>26s} {'x real time':>12s}")
    for name, cpu in rows:
        print(f"{name:12s} {cpu:26.2f} {60.0 / cpu:12.1f}")
    return recording


def _cpu(job) -> float:
    start = time.process_time()
    job()
    return time.process_time() - start


def memory_table(recording: Recording, config: TeacherConfig, loops: tuple[int, ...] = (1, 5)) -> None:
    """Table 3: peak traced memory while labelling ``loops`` repetitions of the recording."""
    print("\n3. Memory: peak traced allocation of the teacher (frames are produced lazily)")
    print(f"{'LiDAR minutes':>14s} {'peak MB':>10s}")
    span = float(recording.lidar["mid360"].timestamps[-1] - recording.lidar["mid360"].timestamps[0]) + 0.1
    for times in loops:
        looped = dataclasses.replace(recording, lidar={k: LoopedStream(v, times) for k, v in recording.lidar.items()})
        tracemalloc.start()
        run_teacher(looped, config)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        print(f"{times * span / 60.0:14.1f} {peak / 1e6:10.1f}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short recordings, one seed")
    parser.add_argument("--seconds", type=float, default=60.0, help="length of each simulated flight")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                        help="teacher parameter override (repeatable)")
    parser.add_argument("--skip", action="append", default=[], choices=["accuracy", "speed", "memory"])
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    config = TeacherConfig.from_overrides(dict(p.split("=", 1) for p in args.param))
    seconds, seeds = (30.0, 1) if args.quick else (args.seconds, args.seeds)
    if "accuracy" not in args.skip:
        accuracy_table(seconds, seeds, config)
    recording = None
    if "speed" not in args.skip:
        recording = speed_table(30.0 if args.quick else 60.0, config)
    if "memory" not in args.skip:
        recording = recording or dense_recording(30.0 if args.quick else 60.0)
        memory_table(recording, config)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
