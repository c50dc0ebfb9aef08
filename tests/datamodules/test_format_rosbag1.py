"""The ROS 1 bag reader, on bags written at test time by rosbags' own writer."""

from __future__ import annotations

import logging
import sys

import numpy as np
import pytest

from datamodules.formats import discover_recordings, open_recording
from datamodules.formats.mcap_file import read_mcap
from datamodules.recording import RecordingError, ns_to_seconds

# skips this module when the optional 'rosbags' package is not installed
from tests.helpers.bags import CHANNELS, FS, MSG, SCANS, T0_NS, TS, BagWriter, ros_header, solid_png, write_flight


def assert_matches(rec, truth: dict) -> None:
    assert rec.audio.num_channels == CHANNELS and rec.audio.sample_rate == FS
    assert rec.audio.t0 == ns_to_seconds(T0_NS)  # stamps mark the end of each 0.1 s message
    assert np.array_equal(rec.audio.read(0, rec.audio.num_samples), truth["audio"].astype(np.float32))
    for sensor in ("avia", "mid360"):
        clouds = rec.lidar[sensor]
        assert np.array_equal(clouds.timestamps, [t for t, _, _ in truth[sensor]])  # header stamps, not log times
        for i in reversed(range(len(clouds))):  # random access
            _, xyz, intensity = truth[sensor][i]
            assert np.array_equal(clouds[i].points, xyz) and np.array_equal(clouds[i].intensity, intensity)
    assert [rec.frames[i].data for i in range(len(rec.frames))] == truth["images"]
    assert rec.frames[0].format == "png"
    assert np.array_equal(rec.ground_truth.timestamps, [t for t, _ in truth["gt"]])
    assert np.array_equal(rec.ground_truth.xyz, np.array([x for _, x in truth["gt"]]))


@pytest.mark.parametrize("compression", [None, "BZ2", "LZ4"])
def test_flight_bags_read_into_one_recording(tmp_path, compression, caplog):
    truth = write_flight(tmp_path / "mavic2_flight", compression)
    with caplog.at_level(logging.WARNING, logger="datamodules.formats.rosbag1"):
        rec = open_recording(tmp_path / "mavic2_flight")
    assert rec.sequence_id == "mavic2_flight" and rec.drone == "mavic2"
    assert rec.meta["source_format"] == "rosbag1" and rec.meta["audio_source"]["parameters_from"] == "/audio/audio_info"
    assert rec.meta["topics"] == {"audio": "/audio/audio", "audio_info": "/audio/audio_info", "avia": "/livox/avia",
                                  "mid360": "/livox/lidar_360", "image": "/camera/left/image_raw/compressed",
                                  "ground_truth": "/leica/position"}
    assert rec.meta["frame_ids"] == {"avia": "livox_frame", "mid360": "mid360_frame", "image": ""}
    assert rec.meta["audio_gaps"] == 0
    assert any("several camera topics" in r.getMessage() for r in caplog.records)
    assert_matches(rec, truth)


def test_converts_to_mcap_and_info(tmp_path, capsys):
    from datamodules.cli import main
    from datamodules.convert import convert

    truth = write_flight(tmp_path / "flight", "BZ2")
    (written,) = convert(tmp_path / "flight", tmp_path / "out")
    assert written.name == "flight.mcap"
    back = read_mcap(written)
    assert_matches(back, truth)
    assert back.audio.sample_format == "S16LE" and back.meta["source_format"] == "rosbag1"
    assert main(["info", str(tmp_path / "flight")]) == 0
    row = capsys.readouterr().out.splitlines()[2]
    assert "rosbag1" in row and "4ch 48000Hz 3.0s" in row and f"{SCANS} @10.0Hz" in row


def test_unstamped_audio_with_parameters_and_a_dropped_message(tmp_path, caplog):
    truth = write_flight(tmp_path / "f", audio="plain", info=False, drop=(12,), sample_format="S32LE", channels=3,
                         lidar=False, gt=False)
    with caplog.at_level(logging.WARNING, logger="datamodules.formats.rosbag1"):
        rec = open_recording(tmp_path / "f", channels=3, sample_format="S32LE")
    audio = rec.audio
    assert audio.num_channels == 3 and audio.sample_format == "S32LE" and audio.num_samples == 30 * MSG
    assert rec.meta["audio_gaps"] == 1 and rec.meta["audio_gap_seconds"] == pytest.approx(0.1)
    assert any("1 gap(s) in the audio" in r.getMessage() for r in caplog.records)
    samples = audio.read(0, audio.num_samples)
    expected = truth["audio"].astype(np.float32)
    expected[:, 12 * MSG:13 * MSG] = 0.0
    assert np.array_equal(samples, expected)
    with pytest.raises(RecordingError, match=r"advance at about 48000 samples/s but the sample rate is 46080"):
        open_recording(tmp_path / "f", channels=3, sample_format="S32LE", sample_rate=46080)
    with pytest.raises(RecordingError, match=r"not whole 7-channel S32LE frames"):
        open_recording(tmp_path / "f", channels=7, sample_format="S32LE")


def test_bag_without_audio(tmp_path):
    write_flight(tmp_path / "f", audio="", gt=False)
    with pytest.raises(RecordingError, match=r"no audio topic.*topics: .*/livox/avia \(livox_ros_driver/msg/CustomMsg, "
                                             rf"{SCANS} msgs\)"):
        open_recording(tmp_path / "f")
    rec = open_recording(tmp_path / "f", mapping={"audio": None})
    assert rec.audio is None and len(rec.lidar["avia"]) == SCANS and rec.ground_truth is None


def test_mapping_from_yaml_and_its_errors(tmp_path):
    write_flight(tmp_path / "f", gt=False)
    mapping = tmp_path / "topics.yaml"
    mapping.write_text("image: /camera/right/image_raw/compressed\nmid360: null\nsample_rate: 48000\n")
    rec = open_recording(tmp_path / "f", mapping=mapping)
    assert "mid360" not in rec.lidar and rec.frames[0].data == solid_png(1)
    mapping.write_text("avia: /livox/lidar\n")
    with pytest.raises(RecordingError, match=r"avia: /livox/lidar names no topic.*/livox/avia \(livox_ros_driver"):
        open_recording(tmp_path / "f", mapping=mapping)
    with pytest.raises(RecordingError, match=r"/audio/audio_info is audio_common_msgs/msg/AudioInfo, expected one of"):
        open_recording(tmp_path / "f", mapping={"avia": "/audio/audio_info"})
    with pytest.raises(RecordingError, match=r"unknown mapping key\(s\) \['lidar'\]"):
        open_recording(tmp_path / "f", mapping={"lidar": "/livox/avia"})
    (tmp_path / "f" / "aaute_layout.yaml").write_text("sample_rate: 44100\n")  # read from the bags' folder
    with pytest.raises(RecordingError, match=r"sample_rate 44100 given but /audio/audio_info says 48000"):
        open_recording(tmp_path / "f")


def test_bags_of_two_flights_in_one_folder_are_refused(tmp_path):
    write_flight(tmp_path / "a", gt=False)
    write_flight(tmp_path / "b", gt=False, seed=1)
    (tmp_path / "b" / "2023-08-24-10-49-05_mavic2.bag").rename(tmp_path / "a" / "other.bag")
    with pytest.raises(RecordingError, match=r"topic /\S+ appears in both .*\(put each flight's bags in its own"):
        open_recording(tmp_path / "a")
    assert discover_recordings(tmp_path) == [tmp_path / "a"]


def test_non_monotonic_header_stamps(tmp_path):
    folder = tmp_path / "f"
    folder.mkdir()
    bag = BagWriter(folder / "x.bag", None)
    for k, stamp in enumerate((3, 2, 4)):
        msg = TS.types["geometry_msgs/msg/PointStamped"](header=ros_header(T0_NS + stamp * 10**8),
                                                         point=TS.types["geometry_msgs/msg/Point"](1.0, 2.0, 3.0))
        bag.write("/leica/position", "geometry_msgs/msg/PointStamped", msg, T0_NS + k)
    bag.close()
    with pytest.raises(RecordingError, match=r"x\.bag /leica/position: timestamps must increase"):
        open_recording(folder / "x.bag", mapping={"audio": None})


def test_corrupt_and_missing_package(tmp_path, monkeypatch):
    (tmp_path / "broken.bag").write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 64)
    with pytest.raises(RecordingError, match=r"broken\.bag: not a readable ROS 1 bag"):
        open_recording(tmp_path / "broken.bag")
    monkeypatch.setitem(sys.modules, "rosbags.rosbag1", None)
    from datamodules.formats.rosbag1 import MissingDependencyError

    with pytest.raises(MissingDependencyError, match=r"pip install \.\[rosbag\]"):
        open_recording(tmp_path / "broken.bag")
