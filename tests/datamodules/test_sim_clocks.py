"""Node clocks in the simulator: offsets and drifts applied to everything a microphone hears, truth in meta."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from datamodules.simulate.clocks import ClockConfig, draw_clocks, resample_at_clock, stamp_residuals
from datamodules.simulate.simulator import SimulationConfig, simulate_recording

FS = 48000.0


def test_resampling_reads_each_channel_at_its_clock():
    t = np.arange(24000) / FS
    x = np.stack([np.sin(2 * np.pi * 700 * t), np.sin(2 * np.pi * 1300 * t)])
    y = resample_at_clock(x, FS, np.array([0.0, 0.37e-3]), np.array([0.0, 50.0]))
    assert np.array_equal(y[0], x[0])
    expected = np.sin(2 * np.pi * 1300 * (t * (1 + 50e-6) + 0.37e-3))
    assert np.abs(y[1, 50:-50] - expected[50:-50]).max() < 1e-3


def test_fixed_values_ramp_over_nodes_and_ranges_are_drawn():
    rng = np.random.default_rng(0)
    clocks = draw_clocks(ClockConfig(offset_ms=0.5, drift_ppm=[0, 10, 20, 30]), 4, 10.0, rng)
    assert np.allclose(clocks.offsets_s, [0, 0.5e-3, 1e-3, 1.5e-3]) and np.allclose(clocks.drifts_ppm, [0, 10, 20, 30])
    drawn = draw_clocks(ClockConfig(offset_range_ms=3.0, drift_range_ppm=20.0), 4, 10.0, rng)
    assert np.all(np.abs(drawn.offsets_s) <= 3e-3) and np.ptp(drawn.offsets_s) > 0
    assert np.all(np.abs(drawn.drifts_ppm) <= 20)
    residuals = stamp_residuals(4, 60.0, 2e-3, 0.1, rng)  # median of exponential latencies: ln 2 x mean
    assert np.allclose(residuals, 2e-3 * np.log(2), rtol=0.15)
    with pytest.raises(ValueError, match="offset_range_ms must be a finite number >= 0"):
        draw_clocks(ClockConfig(offset_range_ms=-1.0), 4, 1.0, rng)
    assert not ClockConfig().active() and not ClockConfig(offset_ms=[0, 0, 0, 0]).active()


def test_a_late_node_hears_the_drone_and_the_noise_early():
    """Node 1 sampling 1 ms late (true time k/fs + 1 ms) records what the shared clock has 48 samples later."""
    config = SimulationConfig(duration=1.5, camera=False, lidar_sensors=())
    shared = simulate_recording(config, seed=3).audio.read(0, int(1.5 * FS))
    late = simulate_recording(dataclasses.replace(config, clocks=ClockConfig(offset_ms=[0, 1.0, 0, 0])), seed=3)
    samples = late.audio.read(0, int(1.5 * FS))
    assert np.array_equal(samples[0], shared[0]) and np.array_equal(samples[2:], shared[2:])
    moved, reference = samples[1, :-48], shared[1, 48:]
    assert np.corrcoef(moved, reference)[0, 1] > 0.999
    assert np.corrcoef(samples[1], shared[1])[0, 1] < 0.99  # not the same as unshifted
    assert late.meta["clocks_truth"]["offsets_s"] == pytest.approx([0, 1e-3, 0, 0])
    assert late.meta["nodes_share_clock"] is False and "clocks_truth" not in simulate_recording(config, 3).meta


def test_simulate_command_takes_clock_options(tmp_path):
    from datamodules.cli import main
    from datamodules.formats.mcap_file import read_mcap

    assert main(["simulate", "--out", str(tmp_path), "--sequences", "1", "--seconds", "0.5", "--no-camera",
                 "--clock-offset-ms", "0.3", "--clock-drift-range-ppm", "20", "--stamp-jitter-ms", "1"]) == 0
    truth = read_mcap(next(tmp_path.glob("*.mcap"))).meta["clocks_truth"]
    assert truth["offsets_s"] == pytest.approx([0, 0.3e-3, 0.6e-3, 0.9e-3])
    assert all(abs(d) <= 20 for d in truth["drifts_ppm"]) and all(r > 0 for r in truth["stamp_residuals_s"])
    assert main(["simulate", "--out", str(tmp_path / "x"), "--clock-offset-range-ms", "-1"]) == 2
