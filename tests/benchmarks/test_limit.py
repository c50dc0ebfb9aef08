"""The physical-limit (CRLB) job: suite key, jobs, per-window bounds and the refusal of unknown geometry."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from benchmarks.jobs import run_job
from benchmarks.limit import BOUND_METHOD, BoundError, bound_options, prior_spread, recording_inputs
from benchmarks.suite import SuiteError, expand_jobs, load_suite
from datamodules.formats.mcap_file import write_mcap
from datamodules.recording import ArrayAudio
from datamodules.simulate.simulator import SimulationConfig, simulate_recording
from tests.helpers.suites import REPO, write_suite


def test_bound_key_defaults_to_the_data_kind_and_checks_the_band():
    assert bound_options(None, "simulated", "s") == {"band_hz": None}
    assert bound_options(None, "real", "s") is None
    assert bound_options(False, "simulated", "s") is None
    assert bound_options({"band_hz": [100, 4000]}, "real", "s") == {"band_hz": [100.0, 4000.0]}
    with pytest.raises(BoundError, match="band_hz"):
        bound_options({"band_hz": [4000, 100]}, "simulated", "s")
    with pytest.raises(BoundError, match="bound must be"):
        bound_options({"band": [1, 2]}, "simulated", "s")


def test_suites_expand_one_bound_job_per_protocol_and_seed(tmp_path):
    quick = expand_jobs(load_suite(REPO / "configs" / "benchmark" / "quick.yaml"))
    bounds = [job for job in quick if job.kind == "bound"]
    assert {(job.protocol, job.seed) for job in bounds} == {("by_sequence", 0), ("random_windows", 0)}
    assert all(job.method == BOUND_METHOD and job.category == "reference" for job in bounds)
    assert not [job for job in expand_jobs(load_suite(REPO / "configs" / "benchmark" / "mmaud_v1.yaml"))
                if job.kind == "bound"]
    bad = write_suite(tmp_path / "suite.yaml", root=str(tmp_path), cache=str(tmp_path), bound={"band_hz": 5})
    with pytest.raises(SuiteError, match="suite.yaml: bound.band_hz"):
        load_suite(bad)


def test_prior_spread_is_the_rms_axis_deviation():
    positions = np.array([[0.0, 0.0, 0.0], [2.0, 4.0, 6.0]])
    assert prior_spread(positions) == pytest.approx(np.sqrt((1 + 4 + 9) / 3))


def test_a_recording_without_microphone_positions_is_refused(tmp_path):
    recording = simulate_recording(SimulationConfig(duration=2.0, lidar_sensors=(), camera=False), seed=1)
    audio = recording.audio
    recording.audio = ArrayAudio(audio.samples, audio.sample_rate, audio.t0, np.zeros_like(audio.mic_positions))
    path = tmp_path / "zeros.mcap"
    write_mcap(recording, path)
    with pytest.raises(BoundError, match=r"zeros\.mcap: microphone positions unknown or all zero"):
        recording_inputs(path, {})


def test_the_bound_job_bounds_every_test_window(labelled_dir, feature_cache, tmp_path):
    suite = load_suite(write_suite(tmp_path / "suite.yaml", root=str(labelled_dir), cache=str(feature_cache),
                                    bound=True))
    job = next(job for job in expand_jobs(suite) if job.kind == "bound")
    row = run_job(job)
    frame = pd.read_csv(row["predictions_path"])
    assert set(frame["light"]) == {"ideal", "dark"} and (frame["snr_source"] == "simulator").all()
    bound = frame.loc[frame["light"] == "ideal", "bound_m"].to_numpy()
    assert len(bound) == row["n_test_windows"] and np.all(np.isfinite(bound)) and np.all(bound > 0)
    assert row["E_ideal"] == pytest.approx(np.sqrt(np.mean(bound ** 2)), rel=1e-3) == row["E_dark"]
    assert row["bound_median_m"] == pytest.approx(np.median(bound), rel=1e-3) and row["bound_band_hz"] == "full"
    assert row["E_ideal_mavic2"] == pytest.approx(row["E_ideal"])  # the one test flight is a Mavic 2
    assert Path(row["predictions_path"]).parent == Path(job.job_dir)
