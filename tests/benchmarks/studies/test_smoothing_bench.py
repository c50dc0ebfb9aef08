"""The smoothing benchmark's real-data reports, on five small synthetic tracks laid out like MMAUD V1 TAME."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from benchmarks.studies.smoothing_bench import DRONES_V1, accuracy, choose_online


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("tame")
    rng = np.random.default_rng(0)
    for k, drone in enumerate(DRONES_V1):
        t = 1.69e9 + np.arange(80) * 0.1
        s = t - t[0]
        truth = np.stack([3 * np.sin(0.3 * s + k), 2 * np.cos(0.2 * s), 1 + 0.1 * s], axis=1)
        pred = truth + rng.normal(0, 0.3, truth.shape)
        pred[5::17] += 6.0  # outliers
        for name, xyz in (("pred", pred), ("gt", truth)):
            pd.DataFrame({"timestamp": t, "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}).to_csv(
                out / f"{drone}_{name}.csv", index=False)
    return out


def test_choose_online_scores_every_setting_and_picks_leave_one_drone_out(folder):
    report = choose_online(folder, windows=(0.0, 2.0), iterations=(1, 3), lags=(0.0, 1.0))
    rows = [line for line in report.splitlines() if line.startswith("| ") and line[2].isdigit()]
    assert len(rows) == 4  # one per (window, iterations)
    picks = next(line for line in report.splitlines() if line.startswith("leave-one-drone-out picks"))
    assert all(drone in picks for drone in DRONES_V1)
    scores = [float(line.rsplit(" ", 1)[1]) for line in report.splitlines() if "left-out drones" in line]
    assert len(scores) == 2 and all(0 < s < 1.0 for s in scores)


def test_accuracy_passes_the_online_settings_to_the_lag_modes(folder):
    plain = accuracy(folder, lags=(0.0,), window=0.0, iterations=1)
    revised = accuracy(folder, lags=(0.0,), window=2.0, iterations=3)
    def row(table: str, mode: str) -> str:
        return next(line for line in table.splitlines() if line.startswith(f"| {mode} "))

    assert row(plain, "lag=0") != row(revised, "lag=0")
    # offline untouched: the same E and coverage (the last two cells, down-weighted and seconds, aside)
    assert row(plain, "robust").rsplit("|", 3)[0] == row(revised, "robust").rsplit("|", 3)[0]
