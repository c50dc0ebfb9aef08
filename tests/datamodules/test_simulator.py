"""The whole simulator: recordings, determinism, MCAP output, the ``aaute simulate`` command."""

from __future__ import annotations

import numpy as np
import pytest

from datamodules.cli import main
from datamodules.formats import open_recording
from datamodules.formats.mcap_file import write_mcap
from datamodules.recording import ORIGIN_DRONE, ORIGIN_FALSE
from datamodules.simulate.drones import drone_spec
from datamodules.simulate.simulator import SimulationConfig, simulate_recording
from tests.helpers.recording_checks import assert_same_recording


@pytest.fixture(scope="module")
def short_recording():
    return simulate_recording(SimulationConfig(duration=3.0, drone="m300"), seed=5, index=0)


def test_recording_holds_every_sensor_on_one_clock(short_recording):
    rec = short_recording
    assert rec.drone == "m300" and rec.audio.num_channels == 4 and rec.audio.sample_rate == 48000
    assert rec.audio.duration == pytest.approx(3.0)
    assert set(rec.lidar) == {"mid360", "avia"}
    start, end = rec.audio.t0, rec.audio.t_end
    for stream in (*rec.lidar.values(), rec.frames, rec.ground_truth):
        assert start <= stream.timestamps[0] and stream.timestamps[-1] < end
        assert np.allclose(np.diff(stream.timestamps), 0.1)
    meta = rec.meta
    assert meta["source_format"] == "simulator" and len(meta["audio"]["snr_db"]) == 4
    assert 45.0 <= meta["audio"]["ambient_dba"] <= 62.0


def test_drone_returns_lie_on_the_ground_truth(short_recording):
    rec = short_recording
    size = max(drone_spec("m300").size_m)
    drone_points = 0
    for sensor, clouds in rec.lidar.items():
        for i, t in enumerate(clouds.timestamps):
            cloud = clouds[i]
            on_drone = cloud.points[cloud.origin == ORIGIN_DRONE]
            drone_points += len(on_drone)
            if len(on_drone):
                truth = rec.ground_truth.interpolate(np.array([t + 0.05]))[0]
                # within the body plus 0.1 s of flight at up to 5 m/s
                assert np.linalg.norm(on_drone - truth, axis=1).max() < size + 0.6, sensor
            false = cloud.points[cloud.origin == ORIGIN_FALSE]
            assert len(false) < 20
    assert drone_points > 0


def test_same_seed_same_bytes_other_index_other_flight(tmp_path, short_recording):
    config = SimulationConfig(duration=3.0, drone="m300")
    again = simulate_recording(config, seed=5, index=0)
    a = write_mcap(short_recording, tmp_path / "a.mcap")
    b = write_mcap(again, tmp_path / "b.mcap")
    assert a.read_bytes() == b.read_bytes()
    assert_same_recording(short_recording, open_recording(a))
    other = simulate_recording(config, seed=5, index=1)
    assert not np.allclose(other.ground_truth.xyz, short_recording.ground_truth.xyz)


def test_simulate_command_resumes_and_refuses_a_different_recording(tmp_path, capsys):
    out = tmp_path / "sim"
    common = ["simulate", "--out", str(out), "--sequences", "2", "--seed", "3", "--no-camera"]
    args = [*common, "--seconds", "1.5"]
    assert main(args) == 0
    files = sorted(out.glob("*.mcap"))
    assert [f.name for f in files] == ["sim3_0000.mcap", "sim3_0001.mcap"]
    stamps = [f.stat().st_mtime_ns for f in files]
    table = capsys.readouterr().out
    assert "sim3-0000-avata" in table and "sim3-0001-m300" in table
    assert main(args) == 0  # nothing to do: the same recordings are there
    assert [f.stat().st_mtime_ns for f in files] == stamps
    assert main([*common, "--seconds", "2.0"]) == 2  # other settings, same folder
    assert [f.stat().st_mtime_ns for f in files] == stamps
    assert not list(out.glob(".*tmp*"))


def test_simulate_command_sets_the_ambient(tmp_path):
    out = tmp_path / "quiet"
    args = ["simulate", "--out", str(out), "--sequences", "1", "--seconds", "1.0", "--no-camera",
            "--ambient-dba", "45", "45", "--wind", "0", "0", "--no-hvac"]
    assert main(args) == 0
    audio = open_recording(next(out.glob("*.mcap"))).meta["audio"]
    assert audio["ambient_dba"] == 45.0 and audio["wind_speed"] == 0.0 and audio["hvac_dba"] is None
    assert main(["simulate", "--out", str(tmp_path / "bad"), "--wind", "3", "1"]) == 2
    assert not (tmp_path / "bad").exists()
