"""Shared test fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path:
    """Where the real MMAUD samples live: ``$AAUTE_SHARED_DATA`` or ``<repo>/../shared/data``."""
    return Path(os.environ.get("AAUTE_SHARED_DATA", REPO.parent / "shared" / "data"))


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
