"""Unit tests of each teacher stage on small hand-made point clouds with a known answer."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from datamodules.recording import ArrayPointClouds, RecordingError
from datamodules.teacher import background, clustering, fusion, sampling, spline
from datamodules.teacher.frames import FrameStats, check_timestamps, check_units, clean_points
from datamodules.teacher.pipeline import TeacherConfig, chunk_bounds

RNG = np.random.default_rng(1234)


def blob(centre, n, sigma=0.1, rng=RNG):
    return np.asarray(centre, dtype=np.float64) + rng.normal(0.0, sigma, (n, 3))


def wall(x0=10.0, size=4.0, step=0.1):
    """A vertical wall (plane x = x0) sampled on a grid: dense static structure."""
    y, z = np.meshgrid(np.arange(-size / 2, size / 2, step), np.arange(0.0, size, step))
    return np.column_stack([np.full(y.size, x0), y.ravel(), z.ravel()])


# ------------------------------------------------------------------------------------------ frames


def test_clean_points_drops_padding_nan_and_far_points_with_counts():
    frame = np.zeros((10, 3))
    frame[:4] = [[1, 2, 3], [4, 5, 6], [np.nan, 0, 0], [2000.0, 0, 0]]
    stats = FrameStats("mid360")
    kept = clean_points(frame, stats, np.zeros(3), max_range_m=1000.0)
    assert kept.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert (stats.padding_rows, stats.nonfinite_points, stats.far_points, stats.points) == (6, 1, 1, 2)
    empty = clean_points(np.zeros((5, 3)), stats, np.zeros(3))
    assert empty.shape == (0, 3) and stats.empty_frames == 1


def test_nan_frames_are_reported_with_counts(caplog):
    stats = FrameStats("avia")
    clean_points(np.array([[np.nan, 1, 1], [1, 1, 1]]), stats, np.zeros(3))
    with caplog.at_level(logging.WARNING):
        stats.report("seq")
    assert "dropped 1 NaN/inf points in 1 of 1 frames" in caplog.text


def test_millimetres_are_refused():
    stats = FrameStats("mid360")
    clean_points(RNG.uniform(5000, 30000, (100, 3)), stats, np.zeros(3))
    with pytest.raises(RecordingError, match="millimetres"):
        check_units(stats, "seq", max_median_range_m=500.0)
    metres = FrameStats("mid360")
    clean_points(RNG.uniform(5, 30, (100, 3)), metres, np.zeros(3))
    check_units(metres, "seq")


def test_timestamps_must_increase():
    stream = ArrayPointClouds([0.0, 0.1, 0.05], [clustering_points(1)] * 3)
    with pytest.raises(RecordingError, match="increase"):
        check_timestamps(stream, "seq mid360")


def clustering_points(n):
    from datamodules.recording import PointCloud

    return PointCloud(np.ones((n, 3), dtype=np.float32))


def test_chunks_of_twenty_with_short_tail_merged():
    assert chunk_bounds(88, 20, 10) == [(0, 20), (20, 40), (40, 60), (60, 88)]
    assert chunk_bounds(95, 20, 10) == [(0, 20), (20, 40), (40, 60), (60, 80), (80, 95)]
    assert chunk_bounds(5, 20, 10) == [(0, 5)]


# -------------------------------------------------------------------------------------- background


def test_static_map_separates_persistent_structure_from_a_passing_object():
    static_map = background.StaticMap(np.zeros(3), voxel_m=0.5, near_range_m=15.0, min_fraction=0.8, min_chunks=4)
    structure = wall(x0=8.0)
    for k in range(10):
        passing = blob([2.0 + k, 3.0, 5.0], 20, 0.05)  # one metre further each chunk
        static_map.add_chunk(np.concatenate([structure + RNG.normal(0, 0.02, structure.shape), passing]))
    static_map.finish()
    assert static_map.known
    assert static_map.is_static(structure).mean() > 0.99
    assert not static_map.is_static(blob([5.0, 3.0, 5.0], 20, 0.05)).any()


def test_static_map_needs_history():
    one = background.StaticMap(np.zeros(3))
    one.add_chunk(wall())
    one.finish()
    assert not one.known
    short = background.StaticMap(np.zeros(3), min_chunks=4)
    for _ in range(2):
        short.add_chunk(wall())
    short.add_chunk(blob([0.0, 5.0, 5.0], 10))
    short.finish()
    assert short.needed_chunks() == 3  # fewer chunks than min_chunks: occupied in all of them
    assert not short.is_static(wall()).any()


def test_cubes_grow_with_range():
    origin = np.zeros(3)
    near = background.range_scaled_keys(np.array([[1.2, 0, 0], [1.6, 0, 0]]), origin, 0.5, 15.0)
    far = background.range_scaled_keys(np.array([[40.1, 0, 0], [41.4, 0, 0]]), origin, 0.5, 15.0)
    assert near[0] != near[1]  # 0.5 m cubes near the sensor
    assert far[0] == far[1]  # 2 m cubes at 30-60 m


# -------------------------------------------------------------------------------------- clustering


def test_dbscan_finds_a_dense_blob_and_leaves_isolated_returns_as_noise():
    points = np.concatenate([blob([0, 0, 5], 40, 0.2), RNG.uniform(-50, 50, (10, 3))])
    labels = clustering.dbscan(points, eps=1.0, min_samples=10)
    assert (labels[:40] == 0).all()
    assert (labels[40:] == -1).all()
    assert np.array_equal(labels, clustering.dbscan(points, eps=1.0, min_samples=10, cube_m=0.0))


def test_merge_joins_clusters_closer_than_the_merge_distance_and_drops_small_components():
    a = blob([0, 0, 0], 30, 0.05)
    b = blob([2.2, 0, 0], 30, 0.05)  # ~2 m from a: merged at 2.5 m
    c = blob([10, 0, 0], 30, 0.05)  # far: its own component
    d = blob([30, 0, 0], 12, 0.05)  # under 20 points: dropped
    points = np.concatenate([a, b, c, d])
    labels = np.repeat([0, 1, 2, 3], [30, 30, 30, 12])
    component, sizes = clustering.merge_clusters(points, labels, merge_distance=2.5, min_size=20)
    assert sorted(sizes.tolist()) == [30, 60]
    assert len(set(component[:60])) == 1 and component[60] != component[0]
    assert (component[90:] == -1).all()


def test_drop_largest_and_smallest():
    keep = clustering.drop_largest_and_smallest(np.array([500.0, 40.0, 20.0, 90.0]))
    assert keep.tolist() == [False, True, False, True]
    assert clustering.drop_largest_and_smallest(np.array([500.0, 40.0])).all()  # too few components


def test_density_prefers_compact_returns():
    compact = blob([0, 0, 5], 40, 0.1)
    spread = RNG.uniform(-5, 5, (40, 3))
    assert clustering.cluster_density(compact) > 5 * clustering.cluster_density(spread)


def drone_chunk(n_frames=20, per_frame=3, start=(3.0, 4.0, 6.0), velocity=(0.5, 0.0, 0.0)):
    """Returns of a drone moving at ``velocity`` m/s, ``per_frame`` per 0.1 s scan."""
    points, frames = [], []
    for j in range(n_frames):
        centre = np.asarray(start) + np.asarray(velocity) * 0.1 * j
        points.append(blob(centre, per_frame, 0.08))
        frames.append(np.full(per_frame, j))
    return np.concatenate(points), np.concatenate(frames)


def test_extract_uav_with_a_static_map_picks_the_moving_drone():
    drone, drone_frames = drone_chunk()
    structure = wall(x0=12.0)
    clutter = RNG.uniform(-40, 40, (30, 3))  # isolated non-static returns
    points = np.concatenate([drone, structure, clutter])
    frames = np.concatenate([drone_frames, RNG.integers(0, 20, structure.shape[0]), RNG.integers(0, 20, 30)])
    static = np.concatenate([np.zeros(len(drone), bool), np.ones(len(structure), bool), np.zeros(30, bool)])
    chosen, result = clustering.extract_uav(points, frames, static)
    assert np.array_equal(chosen, np.arange(len(points)) < len(drone))
    assert result.n_candidates == 1


def test_extract_uav_rejects_the_fringe_of_a_structure_but_keeps_a_drone_flying_near_it():
    structure = wall(x0=12.0)
    for x, kept in ((11.9, False), (11.0, True)):  # touching the wall / 1 m in front of it
        drone, drone_frames = drone_chunk(start=(x, 0.0, 2.0), velocity=(0.0, 0.0, 0.0))
        points = np.concatenate([drone, structure])
        frames = np.concatenate([drone_frames, RNG.integers(0, 20, structure.shape[0])])
        static = np.arange(len(points)) >= len(drone)
        chosen, _ = clustering.extract_uav(points, frames, static)
        assert chosen.any() == kept
        assert not chosen[len(drone):].any()


def test_extract_uav_rejects_objects_wider_than_a_drone_and_single_scan_bursts():
    side = np.column_stack([np.linspace(5.0, 9.5, 10), np.full(10, 2.0), np.full(10, 0.8)])
    car = np.concatenate([side + RNG.normal(0, 0.02, side.shape) for _ in range(5)])  # 4.5 m long in every scan
    burst = blob([0.0, 8.0, 6.0], 30, 0.1)
    points = np.concatenate([car, burst])
    frames = np.concatenate([np.repeat(np.arange(5), 10), np.zeros(30, int)])
    chosen, result = clustering.extract_uav(points, frames, np.zeros(len(points), bool), min_samples=3)
    assert not chosen.any() and result.n_candidates == 0


def test_extract_uav_without_static_map_follows_the_paper_rule():
    """Largest (background) and smallest (partial background) dropped; the densest remainder wins."""
    background_blob = RNG.uniform([-30, -30, 0], [30, 30, 0.5], (3000, 3))  # big, sparse ground
    partial = blob([20.0, 20.0, 1.0], 22, 0.3)
    clutter = RNG.uniform([-10, 10, 0], [-5, 15, 4], (200, 3))  # a loose tree-like component
    drone, drone_frames = drone_chunk(per_frame=4)
    points = np.concatenate([background_blob, partial, clutter, drone])
    frames = np.concatenate([RNG.integers(0, 20, 3222), drone_frames])
    chosen, result = clustering.extract_uav(points, frames, None, max_frame_extent_m=100.0)
    assert result.n_components >= 3
    assert chosen[-len(drone):].all() and not chosen[:-len(drone)].any()


# ---------------------------------------------------------------------------------------- sampling


def test_farthest_point_sampling_keeps_the_extremes_and_bounds_the_count():
    line = np.column_stack([np.linspace(0, 10, 500), np.zeros(500), np.zeros(500)])
    picked = sampling.farthest_point_sampling(line, max_points=5)
    assert picked.size == 5
    xs = np.sort(line[picked, 0])
    assert xs[0] == 0.0 and xs[-1] == 10.0
    np.testing.assert_allclose(xs, [0.0, 2.5, 5.0, 7.5, 10.0], atol=0.05)
    assert np.array_equal(picked, sampling.farthest_point_sampling(line, max_points=5))  # deterministic
    assert sampling.farthest_point_sampling(line[:7], max_points=100).tolist() == list(range(7))


# ------------------------------------------------------------------------------------------ fusion


def test_fusion_removes_isolated_returns_and_gives_one_centroid_per_frame():
    frames = []
    for j in range(40):
        t = 100.0 + 0.1 * j
        centre = np.array([2.0 + 0.05 * j, 1.0, 8.0])
        pts = blob(centre, 4, 0.05)
        sensor = "avia" if j % 2 else "mid360"
        if j % 5 == 0:  # a solar false return far away in the same frame
            pts = np.concatenate([pts, [[200.0, 50.0, 300.0]]])
        frames.append(fusion.FramePoints(t, sensor, pts))
    frames.append(fusion.FramePoints(104.5, "avia", np.array([[0.0, -100.0, 250.0]])))  # an isolated frame
    evidence = list(fusion.denoise_fused(frames, eps=1.0, min_samples=10, block_s=2.0, pad_s=2.0))
    assert len(evidence) == 40
    assert all(e.count == 4 for e in evidence)
    for e in evidence:
        j = round((e.time - 100.0) / 0.1)
        np.testing.assert_allclose(e.xyz, [2.0 + 0.05 * j, 1.0, 8.0], atol=0.1)
    with pytest.raises(ValueError, match="time order"):
        list(fusion.denoise_fused(frames[::-1]))


# ------------------------------------------------------------------------------------------ spline


def path(t):
    return np.stack([2.0 * np.sin(0.3 * t), 5.0 + 0.8 * t, 6.0 + 0.5 * np.cos(0.5 * t)], axis=1)


def test_spline_follows_the_path_and_leaves_gaps_without_evidence():
    t = np.arange(0.0, 20.0, 0.1)
    evidence = (t < 8.0) | (t > 12.0)  # 4 s without evidence
    noisy = path(t[evidence]) + RNG.normal(0, 0.1, (int(evidence.sum()), 3))
    labels = np.arange(0.0, 20.0, 0.1) + 0.05
    track = spline.fit_track(t[evidence], noisy, np.full(int(evidence.sum()), 5), labels, max_gap_s=1.0,
                             max_extrapolation_s=0.5)
    gap = (labels > 8.5) & (labels < 11.5)
    assert not track.valid[gap].any() and np.isnan(track.xyz[gap]).all()
    inside = track.valid & ~gap
    error = np.linalg.norm(track.xyz[inside] - path(labels[inside]), axis=1)
    assert error.mean() < 0.1
    assert track.valid[(labels < 7.9) | (labels > 12.1)].all()
    q = track.quality
    assert set(q) == {"support_points", "nearest_evidence_s", "residual_m"}
    assert q["nearest_evidence_s"][np.argmin(np.abs(labels - 10.05))] == pytest.approx(2.05, abs=0.01)
    assert q["support_points"][np.argmin(np.abs(labels - 3.05))] == 5 * 10


def test_spline_drops_an_outlier_frame():
    t = np.arange(0.0, 5.0, 0.1)
    xyz = path(t)
    xyz[25] += [0.0, 0.0, 8.0]  # one frame on the wrong cluster
    track = spline.fit_track(t, xyz, np.full(t.size, 5), t)
    assert np.linalg.norm(track.xyz[25] - path(t[25:26])[0]) < 0.2


def test_spline_without_evidence_labels_nothing_and_one_frame_labels_only_near_it():
    labels = np.arange(0.0, 3.0, 0.1)
    empty = spline.fit_track(np.zeros(0), np.zeros((0, 3)), np.zeros(0), labels)
    assert not empty.valid.any() and np.isinf(empty.quality["nearest_evidence_s"]).all()
    single = spline.fit_track(np.array([1.0]), np.array([[1.0, 2.0, 3.0]]), np.array([7]), labels,
                              max_extrapolation_s=0.3)
    assert np.array_equal(single.valid, np.abs(labels - 1.0) <= 0.3 + 1e-9)
    np.testing.assert_allclose(single.xyz[single.valid], [[1.0, 2.0, 3.0]] * int(single.valid.sum()))


def test_config_overrides_from_strings():
    config = TeacherConfig.from_overrides({"max_gap_s": "2.5", "static_filter": "false", "chunk_frames": "10",
                                           "frame_time_offset_s": "none"})
    assert (config.max_gap_s, config.static_filter, config.chunk_frames) == (2.5, False, 10)
    with pytest.raises(ValueError, match="unknown teacher parameter"):
        TeacherConfig.from_overrides({"eps": "1"})
