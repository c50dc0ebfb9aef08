"""Shared test fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers.real_data import shared_data_dir


@pytest.fixture(scope="session", autouse=True)
def private_cache(tmp_path_factory):
    """``$AAUTE_CACHE`` inside the test session's temporary folder: no test writes the user's weights registry."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("AAUTE_CACHE", str(tmp_path_factory.mktemp("aaute_cache")))
        yield


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real-data folder; tests using it skip with a reason when it is absent."""
    path = shared_data_dir()
    if not path.is_dir():
        pytest.skip(f"real MMAUD samples not found at {path} (set AAUTE_SHARED_DATA)")
    return path


@pytest.fixture(scope="session")
def simulated_dir(tmp_path_factory) -> Path:
    """Three short simulated recordings (an Avata, an M300 and a Mavic 2, 4 s each) in one folder."""
    from datamodules.simulate.simulator import SimulationConfig, simulate_dataset

    out = tmp_path_factory.mktemp("simulated")
    config = SimulationConfig(duration=4.0)
    simulate_dataset(out, 3, config, seed=11, progress=False)
    return out


@pytest.fixture(scope="session")
def labelled_dir(simulated_dir, tmp_path_factory) -> Path:
    """The simulated recordings with stand-in pseudo-labels (ground truth + 0.25 m, a 0.7 s gap)."""
    import shutil

    import numpy as np

    from datamodules.formats import open_recording
    from datamodules.formats.mcap_file import replace_track
    from datamodules.recording import Track

    out = tmp_path_factory.mktemp("labelled") / "data"
    shutil.copytree(simulated_dir, out)
    for path in sorted(out.glob("*.mcap")):
        gt = open_recording(path).ground_truth
        valid = np.ones(len(gt), dtype=bool)
        valid[25:32] = False
        replace_track(path, "/pseudo_label", Track(gt.timestamps, gt.xyz + 0.25, valid=valid))
    return out


@pytest.fixture(scope="session")
def feature_cache(tmp_path_factory) -> Path:
    """One feature cache for the whole session (entries are keyed by recording and recipe)."""
    return tmp_path_factory.mktemp("feature_cache")
