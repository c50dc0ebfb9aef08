"""Live clock calibration follows drifting clocks: estimates from successive stretches, combined."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from datamodules.features import phase_recipe
from datamodules.simulate.clocks import resample_at_clock
from datamodules.simulate.simulator import simulate_recording
from tests.helpers.flights import flying_m300
from zoo.deploy.live_clocks import CalibratingPhase

OFFSETS = np.array([0.0, 0.3e-3, 0.8e-3, 0.0])  #: per node (s)
DRIFTS = np.array([0.0, 40.0, 0.0, 0.0])  #: per node (ppm): node 1 is 0.48 ms further off after 12 s
BLOCK = 4800


@pytest.fixture(scope="module")
def drifting():
    """12 s of a loud drone flying in quiet air, recorded by nodes whose clocks are offset and one drifts."""
    audio = simulate_recording(flying_m300(12.0), seed=6).audio
    samples = resample_at_clock(audio.read(0, audio.num_samples), audio.sample_rate, OFFSETS, DRIFTS)
    return samples, audio.sample_rate, audio.mic_positions


def _run(samples: np.ndarray, rate: float, mics: np.ndarray, follow: bool, block: int = BLOCK) -> CalibratingPhase:
    front = CalibratingPhase(phase_recipe("gcc_phat_2s_static"), rate, mics, 4.0, "drifting", background=False,
                             follow=follow)
    for stop in range(block, samples.shape[1] + 1, block):
        front.push(samples[:, stop - block:stop])
    return front


def test_estimates_from_every_stretch_follow_a_drifting_clock(drifting, caplog):
    samples, rate, mics = drifting
    with caplog.at_level(logging.INFO, logger="zoo.deploy.live_clocks"):
        followed = _run(samples, rate, mics, follow=True)
    once = _run(samples, rate, mics, follow=False)
    assert len(once.estimates) == 1 and len(once.history) == 1 and once.calibrated_at == pytest.approx(4.0)
    assert len(followed.estimates) == 3 and [s for s, _, _ in followed.estimates] == [0.0, 4.0, 8.0]
    assert [round(t, 1) for t, _ in followed.history] == [4.0, 8.0, 12.0]
    assert "3 estimates" in caplog.text
    truth = OFFSETS + DRIFTS * 1e-6 * 11.0  # near the end of the stream
    followed_error = np.abs(followed.calibration.offsets_at(11.0) - truth).max()
    once_error = np.abs(once.calibration.offsets_at(11.0) - truth).max()
    assert followed_error < 2e-5 < once_error  # one 4 s stretch fits the drift too, less exactly
    assert followed.calibration.drifts_ppm[1] == pytest.approx(40.0, abs=8.0)
    # the frames after the last estimate are corrected by the combined clocks
    assert followed.clocks is followed.calibration
    # one block holding every stretch: each is estimated, the same as from 0.1 s blocks
    whole = _run(samples, rate, mics, follow=True, block=samples.shape[1])
    assert len(whole.estimates) == 3
    np.testing.assert_array_equal(whole.calibration.offsets_s, followed.calibration.offsets_s)


def test_the_estimating_worker_runs_every_thread_pool_on_one_thread():
    """The worker's limit reaches torch and every BLAS / OpenMP library, SciPy's lazily loaded one included
    (run in a fresh interpreter, as the worker is spawned, since the limit holds for the process)."""
    import subprocess
    import sys

    code = ("import torch; from threadpoolctl import threadpool_info; "
            "from zoo.deploy.live_clocks import limit_to_one_thread; limit_to_one_thread(); import scipy.linalg; "
            "print(torch.get_num_threads(), max(p['num_threads'] for p in threadpool_info()))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["1", "1"], out
