"""Audio of several nodes, one ROS topic each (MMAUD V1's /audio1/audio ... /audio4/audio), in one recording."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import yaml

from datamodules.formats import open_recording
from datamodules.formats.mcap_file import read_mcap
from datamodules.recording import RecordingError
from tests.helpers.bags import FS, write_nodes

POSITIONS = [[1.5, 1.5, 0.2], [-1.5, 1.5, 0.7], [-1.5, -1.5, 1.2], [1.5, -1.5, 1.7]]


def test_four_mono_topics_read_into_four_channels_at_their_times(tmp_path, caplog):
    # node 2 starts 3 messages late, node 4 ends 2 messages early: the common span is messages 3 to 28
    written = write_nodes(tmp_path / "rig.bag", starts=(0, 0, 3, 0), ends=(30, 30, 30, 28), jitter_ns=1)
    with caplog.at_level(logging.WARNING):
        rec = open_recording(tmp_path / "rig.bag")
    audio = rec.audio
    size = FS // 10
    assert audio.num_channels == 4 and audio.sample_rate == FS and audio.num_samples == 25 * size
    expected = np.stack([written[0][3 * size:28 * size], written[1][3 * size:28 * size],
                         written[2][:25 * size], written[3][3 * size:28 * size]]).astype(np.float32)
    assert np.array_equal(audio.read(0, audio.num_samples), expected)
    assert np.array_equal(audio.read(1000, 1010), expected[:, 1000:1010])
    end = audio.num_samples  # nodes are read in one pass per range: a range far from the last one reads afresh
    assert np.array_equal(audio.read(end - 100, end), expected[:, end - 100:])
    assert np.array_equal(audio.read(5000, 5100), expected[:, 5000:5100])
    assert rec.meta["topics"]["audio[2]"] == "/audio3/audio"
    nodes = rec.meta["audio_nodes"]
    assert [n["name"] for n in nodes] == [f"/audio{i}/audio" for i in range(1, 5)]
    assert [n["shift_samples"] for n in nodes] == [3 * size, 3 * size, 0, 3 * size]
    assert nodes[0]["stamps"] == "receive" and nodes[0]["messages"] == 30
    assert rec.meta["nodes_share_clock"] is False
    assert rec.meta["audio_alignment_uncertainty_s"] < 1e-5
    assert rec.meta["mic_positions_known"] is False
    warned = " ".join(r.getMessage() for r in caplog.records)
    assert "node /audio3/audio spans 1692845357.400-1692845360.100 s; 0.000 s at the start and 0.200 s" in warned


def test_offset_between_nodes_moves_the_samples(tmp_path):
    """A node received 2 ms late (and stamped so) is shifted by 96 samples against the others."""
    written = write_nodes(tmp_path / "rig.bag", nodes=2, offsets_ns=(0, 2_000_000), jitter_ns=1)
    rec = open_recording(tmp_path / "rig.bag")
    assert [n["shift_samples"] for n in rec.meta["audio_nodes"]] == [96, 0]
    samples = rec.audio.read(0, 1000)
    assert np.array_equal(samples[0], written[0][96:1096].astype(np.float32))
    assert np.array_equal(samples[1], written[1][:1000].astype(np.float32))


def test_mapping_list_positions_and_conversion(tmp_path, capsys):
    from datamodules.cli import main

    folder = tmp_path / "flight"
    folder.mkdir()
    written = write_nodes(folder / "rig.bag", nodes=3)
    layout = {"audio": ["/audio3/audio", {"topic": "/audio1/audio", "channels": 1}], "mic_positions": POSITIONS[:2],
              "nodes_share_clock": True}
    (folder / "aaute_layout.yaml").write_text(yaml.safe_dump(layout))
    rec = open_recording(folder)
    assert rec.audio.num_channels == 2 and rec.meta["mic_positions_known"] is True
    assert np.array_equal(rec.audio.mic_positions, POSITIONS[:2]) and rec.meta["nodes_share_clock"] is True
    assert np.array_equal(rec.audio.read(0, 100)[0], written[2][:100].astype(np.float32))
    assert main(["convert", str(folder), str(tmp_path / "out.mcap")]) == 0
    back = read_mcap(tmp_path / "out.mcap")
    assert np.array_equal(back.audio.mic_positions, POSITIONS[:2])
    assert np.array_equal(back.audio.read(0, back.audio.num_samples), rec.audio.read(0, rec.audio.num_samples))
    assert back.meta["audio_nodes"][0]["name"] == "/audio3/audio"
    capsys.readouterr()
    assert main(["info", str(tmp_path / "out.mcap"), str(tmp_path / "flight")]) == 0
    rows = capsys.readouterr().out.splitlines()
    assert "mics" in rows[0] and "nodes" in rows[0]
    assert all("given" in row and "2 one-clock ±" in row for row in rows[2:4])


def test_info_says_positions_unknown_and_clocks_apart(tmp_path, capsys):
    from datamodules.cli import main

    write_nodes(tmp_path / "rig.bag")  # receive jitter up to 3 ms leaves the nodes' t0 uncertain by ~0.2 ms
    assert 1e-4 < open_recording(tmp_path / "rig.bag").meta["audio_alignment_uncertainty_s"] < 1e-3
    assert main(["info", str(tmp_path / "rig.bag")]) == 0
    row = capsys.readouterr().out.splitlines()[2]
    assert "4ch 48000Hz 3.0s" in row and "unknown" in row and "4 own-clocks ±" in row


@pytest.mark.parametrize(("case", "match"), [
    ("silent", r"rig.bag: audio node /audio2/audio is silent"),
    ("rate", r"different sample rates \(/audio1/audio 48000 Hz, /audio2/audio 44100 Hz"),
    ("stamps", r"/audio2/audio.*advance at about 44\d\d\d samples/s but the sample rate is 48000"),
    ("missing", r"mapping audio: /audio9/audio names no topic"),
    ("positions", r"mapping mic_positions\): 3 microphone position\(s\) for 2 audio channel"),
    ("millimetres", r"a microphone lies 1500 m from the rig's origin"),
])
def test_bad_nodes_get_one_line(tmp_path, case, match):
    write_nodes(tmp_path / "rig.bag", nodes=2, silent=1 if case == "silent" else None,
                rates=(FS, 44100) if case in ("rate", "stamps") else ())
    mapping = {
        "rate": {"audio": ["/audio1/audio", {"topic": "/audio2/audio", "sample_rate": 44100}]},
        "missing": {"audio": ["/audio1/audio", "/audio9/audio"]},
        "positions": {"mic_positions": POSITIONS[:3]},
        "millimetres": {"mic_positions": [[1500.0, 0, 0], [0, 0, 0]]},
    }.get(case)
    with pytest.raises(RecordingError, match=match) as error:
        open_recording(tmp_path / "rig.bag", mapping=mapping)
    assert "\n" not in str(error.value)


def test_node_dropping_messages_is_filled_and_named(tmp_path, caplog):
    written = write_nodes(tmp_path / "rig.bag", nodes=2, drop={1: (10, 11)}, jitter_ns=1)
    with caplog.at_level(logging.WARNING):
        rec = open_recording(tmp_path / "rig.bag")
    size = FS // 10
    assert rec.meta["audio_gaps"] == 1 and rec.meta["audio_nodes"][1]["gaps"] == 1
    assert any("/audio2/audio: 1 gap(s)" in r.getMessage() for r in caplog.records)
    assert rec.audio.num_samples == 30 * size
    samples = rec.audio.read(0, rec.audio.num_samples)
    assert not samples[1, 10 * size:12 * size].any()
    assert np.array_equal(samples[1, 12 * size:], written[1][12 * size:].astype(np.float32))
    assert np.array_equal(samples[0], written[0].astype(np.float32))
