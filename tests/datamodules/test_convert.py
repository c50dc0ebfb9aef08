"""``aaute convert``: any readable layout to canonical MCAP files, atomically and all-or-nothing."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from datamodules.cli import main
from datamodules.convert import convert, mcap_name
from datamodules.formats import discover_recordings, open_recording
from datamodules.formats.mcap_file import read_mcap, write_mcap
from datamodules.recording import RecordingError
from tests.helpers.layouts import make_derived, make_recording, make_ug2_sequence


@pytest.fixture()
def mixed(tmp_path) -> Path:
    """A root holding a UG2 train sequence, a derived root with two sequences and an MCAP recording."""
    root = tmp_path / "mixed"
    make_ug2_sequence(root / "ug2" / "train" / "seq1", frames=5)
    make_derived(root / "derived", {"0": 6, "3": 4}, images=False)
    write_mcap(make_recording(seconds=1.0), root / "sim" / "rec.mcap")
    return root


def test_every_layout_converts_to_one_mcap_per_sequence(mixed, tmp_path, capsys):
    sources = discover_recordings(mixed)
    assert len(sources) == 4
    written = convert(mixed, tmp_path / "out", sample_rate=46080)
    assert sorted(p.name for p in written) == ["0.mcap", "3.mcap", "test-seq.mcap", "train_seq1.mcap"]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(p.name for p in written)  # no leftovers
    for source in sources:
        original = open_recording(source, sample_rate=46080)
        back = read_mcap(tmp_path / "out" / mcap_name(original.sequence_id))
        assert (back.sequence_id, back.drone, back.meta) == (original.sequence_id, original.drone, original.meta)
        assert (back.audio is None) == (original.audio is None) and set(back.lidar) == set(original.lidar)
        if original.audio is not None:
            assert back.audio.sample_rate == original.audio.sample_rate
            n = original.audio.num_samples
            assert np.array_equal(back.audio.read(0, n), original.audio.read(0, n))
        if original.ground_truth is not None:
            assert np.array_equal(back.ground_truth.timestamps, original.ground_truth.timestamps)
    assert read_mcap(tmp_path / "out" / "0.mcap").audio.sample_rate == 46080
    assert main(["info", str(tmp_path / "out")]) == 0
    table = capsys.readouterr().out.splitlines()
    assert len(table) == 2 + 4
    rows = {line.split()[0]: line for line in table[2:]}
    assert "mcap (ug2)" in rows["train_seq1.mcap"] and "mcap (derived_npy)" in rows["0.mcap"]
    assert "4ch 46080Hz" in rows["3.mcap"] and "5 @10.0Hz" in rows["train_seq1.mcap"]


def test_one_recording_to_a_named_file(mixed, tmp_path):
    (path,) = convert(mixed / "derived" / "audio_npy" / "3", tmp_path / "x" / "three.mcap")
    assert path == tmp_path / "x" / "three.mcap" and read_mcap(path).sequence_id == "3"
    with pytest.raises(RecordingError, match="holds 4 recordings; give a folder"):
        convert(mixed, tmp_path / "all.mcap")


def test_existing_destination_stops_before_anything_is_written(mixed, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "3.mcap").write_bytes(b"keep me")
    with pytest.raises(FileExistsError, match=r"3\.mcap already exists"):
        convert(mixed, out)
    assert [p.name for p in out.iterdir()] == ["3.mcap"] and (out / "3.mcap").read_bytes() == b"keep me"
    convert(mixed, out, overwrite=True)
    assert read_mcap(out / "3.mcap").sequence_id == "3" and len(list(out.iterdir())) == 4


def test_a_bad_source_writes_nothing(mixed, tmp_path):
    np.save(mixed / "derived" / "audio_npy" / "3" / "2.npy", np.zeros((10, 4), np.int16))
    with pytest.raises(RecordingError, match="audio chunks differ"):
        convert(mixed, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_colliding_sequence_ids_are_refused(tmp_path):
    make_ug2_sequence(tmp_path / "src" / "a" / "seq1", frames=3)
    make_ug2_sequence(tmp_path / "src" / "b" / "seq1", frames=3)
    with pytest.raises(RecordingError, match=r"several recordings would be written to .*seq1\.mcap"):
        convert(tmp_path / "src", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_cli_convert(mixed, tmp_path):
    assert main(["convert", str(mixed / "ug2"), str(tmp_path / "out")]) == 0
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["train_seq1.mcap"]
    assert main(["convert", str(tmp_path / "nowhere"), str(tmp_path / "out2")]) == 2
    (tmp_path / "empty").mkdir()
    assert main(["convert", str(tmp_path / "empty"), str(tmp_path / "out2")]) == 2
    assert not (tmp_path / "out2").exists()


def test_bag_folder_converts(tmp_path):
    pytest.importorskip("rosbags.rosbag1", reason="the optional 'rosbags' package is not installed")
    from tests.helpers.bags import write_flight

    write_flight(tmp_path / "bags" / "flight_7", lidar=False)
    (path,) = convert(tmp_path / "bags", tmp_path / "out")
    rec = read_mcap(path)
    assert path.name == "flight_7.mcap" and rec.drone == "mavic2" and rec.meta["source_format"] == "rosbag1"
    assert rec.audio.num_samples == 30 * 4800 and len(rec.ground_truth) == 30
