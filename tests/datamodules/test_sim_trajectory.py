"""Simulated flights: inside the region, within the envelope, comparable to real MMAUD V1 flights."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from datamodules.simulate.trajectory import TrajectoryConfig, generate_trajectory

DRONES_V1 = ("Mavic2", "Mavic3", "Phantom4", "Avata", "M300")


def _speeds(times: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.diff(xyz, axis=0), axis=1) / np.diff(times)


@pytest.fixture(scope="module")
def simulated_speeds() -> np.ndarray:
    speeds = []
    for seed in range(5):
        trajectory = generate_trajectory(200.0, np.random.default_rng(seed))
        t = np.arange(0.0, 200.0, 0.1)
        speeds.append(_speeds(t, trajectory.position(t)))
    return np.concatenate(speeds)


def test_flight_stays_in_region_and_envelope():
    config = TrajectoryConfig()
    trajectory = generate_trajectory(300.0, np.random.default_rng(7), config)
    t = np.arange(0.0, 300.0, 0.01)
    xyz = trajectory.position(t)
    assert np.all(xyz >= np.array(config.region_min) - 1e-9) and np.all(xyz <= np.array(config.region_max) + 1e-9)
    speed = np.linalg.norm(trajectory.velocity(t), axis=1)
    assert speed.max() <= config.max_speed + 0.5
    assert np.abs(trajectory.velocity(t)[:, 2]).max() <= config.max_climb_rate + 0.5
    accel = np.linalg.norm(trajectory.acceleration(t[::10]), axis=1)
    assert np.percentile(accel, 99) <= config.max_acceleration + 0.5
    # it moves around the region rather than sitting still
    assert np.ptp(xyz[:, 1]) > 10.0


def test_same_seed_same_flight():
    a = generate_trajectory(30.0, np.random.default_rng(3)).position(np.arange(0, 30, 0.5))
    b = generate_trajectory(30.0, np.random.default_rng(3)).position(np.arange(0, 30, 0.5))
    assert np.array_equal(a, b)


def test_speed_distribution_is_comparable_to_mmaud_v1(shared_data, simulated_speeds):
    folder = shared_data / "mmaud_v1_tame"
    if not folder.is_dir():
        pytest.skip(f"{folder} not found")
    real = []
    for name in DRONES_V1:
        table = pd.read_csv(folder / f"{name}_gt.csv")
        real.append(_speeds(table["timestamp"].to_numpy(), table[["x", "y", "z"]].to_numpy()))
    real = np.concatenate(real)
    sim_q = np.percentile(simulated_speeds, [50, 90, 99])
    real_q = np.percentile(real, [50, 90, 99])
    print(f"speed percentiles 50/90/99 (m/s): simulated {sim_q.round(2)}, MMAUD V1 {real_q.round(2)}")
    ratio = sim_q / real_q
    assert np.all(ratio > 0.5) and np.all(ratio < 2.0), ratio
    # both hover a good part of the time
    assert 0.05 < np.mean(simulated_speeds < 0.2) < 0.6 and 0.05 < np.mean(real < 0.2) < 0.6
