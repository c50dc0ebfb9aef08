"""The teacher on simulated recordings with ground truth and per-point origin labels, and on bad input."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from datamodules.recording import ORIGIN_DRONE, ArrayPointClouds, PointCloud, Recording, RecordingError, Track
from datamodules.simulate.acoustics import AudioConfig
from datamodules.simulate.simulator import SimulationConfig, simulate_recording
from datamodules.simulate.trajectory import TrajectoryConfig
from datamodules.teacher import TeacherConfig, label_recording, run_teacher, score_recording
from datamodules.teacher.evaluate import drone_returns_near

#: flight regions (rig frame): the MMAUD region's middle distances, the cone above the rig (Avia only),
#: and far outside both LiDARs' view (beyond the Mid-360's 100 m gate, outside the Avia's cone)
MID = ((-2.0, 10.0, 2.0), (8.0, 20.0, 12.0))
HIGH = ((-3.0, -3.0, 8.0), (3.0, 3.0, 25.0))
NEAR = ((-8.0, -8.0, 0.5), (8.0, 8.0, 6.0))
OUT_OF_VIEW = ((70.0, 70.0, 0.5), (90.0, 90.0, 5.0))


def simulate(drone: str, region, seconds: float = 30.0, seed: int = 7, index: int = 0,
             sensors: tuple[str, ...] = ("mid360", "avia")) -> Recording:
    config = SimulationConfig(duration=seconds, drone=drone, camera=False, lidar_sensors=sensors,
                              audio=AudioConfig(sample_rate=8000.0),
                              trajectory=TrajectoryConfig(region_min=region[0], region_max=region[1]))
    recording = simulate_recording(config, seed, index)
    recording.audio = None
    return recording


@pytest.fixture(scope="module")
def m300_mid() -> Recording:
    return simulate("m300", MID, seconds=20.0, seed=3, index=1)


@pytest.mark.parametrize(("drone", "region", "seed"), [("m300", MID, 3), ("phantom4", HIGH, 5), ("mavic3", NEAR, 8)],
                         ids=["m300-mid", "phantom4-high-avia", "mavic3-near"])
def test_accuracy_and_coverage_within_lidar_range(drone, region, seed):
    recording = simulate(drone, region, seed=seed, index=seed)
    track = label_recording(recording)
    score = score_recording(recording, track, max_range_m=40.0, thresholds=(1, 10, 20))
    print(f"\n{drone}: mean {score.mean_m:.3f} m, median {score.median_m:.3f} m, p95 {score.p95_m:.3f} m, "
          f"coverage {score.coverage:.3f} (of times with >=1/10/20 drone returns in the chunk: "
          f"{score.coverage_returns[1]:.3f}/{score.coverage_returns[10]:.3f}/{score.coverage_returns[20]:.3f})")
    assert score.n_times_returns[20] > 100
    assert score.mean_m <= 0.5
    assert score.coverage_returns[20] >= 0.9


def test_drone_out_of_view_gives_gaps_not_labels():
    recording = simulate("m300", OUT_OF_VIEW, seconds=20.0, seed=2, index=3)
    returns = drone_returns_near(recording, recording.ground_truth.timestamps)
    assert returns is not None and returns.sum() == 0  # the simulator put the drone out of view
    result = run_teacher(recording)
    assert not result.track.valid.any()
    assert np.isnan(result.track.xyz).all()
    assert result.evidence["time"].size == 0


def test_drone_above_the_mid360_without_avia_gives_gaps():
    recording = simulate("phantom4", HIGH, seconds=20.0, seed=5, index=5, sensors=("mid360",))
    assert not run_teacher(recording).track.valid.any()


def test_label_times_default_to_a_grid_without_ground_truth(m300_mid):
    recording = dataclasses.replace(m300_mid, ground_truth=None)
    track = label_recording(recording, TeacherConfig(grid_rate_hz=5.0))
    steps = np.diff(track.timestamps)
    np.testing.assert_allclose(steps, 0.2, atol=1e-6)
    start = recording.lidar["mid360"].timestamps[0]
    assert track.timestamps[0] == pytest.approx(start)


# --------------------------------------------------------------------------------------- bad input


def with_lidar(recording: Recording, sensor: str, edit) -> Recording:
    """A copy of ``recording`` whose ``sensor`` frames were changed by ``edit(i, cloud) -> PointCloud``."""
    stream = recording.lidar[sensor]
    clouds = [edit(i, stream[i]) for i in range(len(stream))]
    return dataclasses.replace(recording, lidar={**recording.lidar, sensor: ArrayPointClouds(stream.timestamps,
                                                                                              clouds)})


def test_nan_frames_are_dropped_with_a_warning_and_counts(m300_mid, caplog):
    def poison(i, cloud):
        if i % 10:
            return cloud
        points = cloud.points.copy()
        points[:5] = np.nan
        return PointCloud(points, cloud.intensity, cloud.origin)

    recording = with_lidar(m300_mid, "mid360", poison)
    with caplog.at_level(logging.WARNING):
        result = run_teacher(recording)
    assert "dropped 100 NaN/inf points in 20 of 200 frames" in caplog.text
    assert result.stats["mid360"].nonfinite_points == 100
    assert result.track.valid.any()


def test_all_zero_frames_give_a_clear_error_not_labels(m300_mid):
    def zeros(i, cloud):
        return PointCloud(np.zeros_like(cloud.points))

    recording = with_lidar(with_lidar(m300_mid, "mid360", zeros), "avia", zeros)
    with pytest.raises(RecordingError, match="every LiDAR frame is empty"):
        run_teacher(recording)


def test_some_all_zero_frames_leave_gaps(m300_mid):
    dead = slice(60, 110)  # 5 s without any return from either sensor

    def drop(i, cloud):
        return PointCloud(np.zeros((100, 3), np.float32)) if dead.start <= i < dead.stop else cloud

    recording = with_lidar(with_lidar(m300_mid, "mid360", drop), "avia", drop)
    track = label_recording(recording)
    lidar_t = m300_mid.lidar["mid360"].timestamps
    inside = (track.timestamps > lidar_t[dead.start] + 1.0) & (track.timestamps < lidar_t[dead.stop] - 1.0)
    assert inside.sum() > 20 and not track.valid[inside].any()


def test_recording_without_lidar_is_refused(m300_mid):
    with pytest.raises(RecordingError, match="no LiDAR"):
        run_teacher(dataclasses.replace(m300_mid, lidar={}))


def test_millimetres_are_refused_and_unit_scale_fixes_them(m300_mid):
    def to_mm(i, cloud):
        return PointCloud(cloud.points * 1000.0, cloud.intensity, cloud.origin)

    recording = with_lidar(with_lidar(m300_mid, "mid360", to_mm), "avia", to_mm)
    recording = dataclasses.replace(recording, meta={**recording.meta, "sensor_poses": {
        k: [1000.0 * v for v in pose] for k, pose in recording.meta["sensor_poses"].items()}})
    with pytest.raises(RecordingError, match="millimetres"):
        run_teacher(recording)
    fixed = dataclasses.replace(recording, meta={**recording.meta, "sensor_poses": m300_mid.meta["sensor_poses"]})
    track = label_recording(fixed, TeacherConfig(unit_scale=0.001))
    assert score_recording(m300_mid, track).mean_m < 0.5


def test_non_monotonic_timestamps_are_refused(m300_mid):
    stream = m300_mid.lidar["avia"]
    times = stream.timestamps.copy()
    times[[10, 11]] = times[[11, 10]]
    recording = dataclasses.replace(m300_mid, lidar={**m300_mid.lidar, "avia": ArrayPointClouds(times, stream.clouds)})
    with pytest.raises(RecordingError, match="increase"):
        run_teacher(recording)
    gt = m300_mid.ground_truth
    backwards = Track(gt.timestamps[::-1], gt.xyz[::-1])
    with pytest.raises(RecordingError, match="increase"):
        run_teacher(dataclasses.replace(m300_mid, ground_truth=backwards))


def test_evidence_comes_from_the_drone(m300_mid):
    """Every evidence frame lies at the drone: the teacher never labels background or false returns."""
    result = run_teacher(m300_mid)
    truth = m300_mid.ground_truth.interpolate(result.evidence["time"])
    assert np.linalg.norm(result.evidence["xyz"] - truth, axis=1).max() < 1.5
    drone_points = sum(int(np.sum(c.origin == ORIGIN_DRONE)) for c in m300_mid.lidar["mid360"].clouds)
    assert result.evidence["count"].sum() <= drone_points + sum(len(c) for c in m300_mid.lidar["avia"].clouds)
