"""The canonical MCAP recording format: round trip, lazy window reads, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from mcap.writer import Writer as RawWriter

from datamodules.formats import open_recording
from datamodules.formats.mcap_file import McapIndex, write_mcap
from datamodules.recording import ArrayPointClouds, RecordingError, Track
from tests.helpers.layouts import RECORDING_T0, make_recording
from tests.helpers.recording_checks import assert_same_recording


@pytest.mark.parametrize("sample_format", ["S16LE", "F32LE"])
def test_round_trip_is_identical(tmp_path, sample_format):
    recording = make_recording(sample_format=sample_format)
    path = write_mcap(recording, tmp_path / "rec.mcap")
    assert_same_recording(recording, open_recording(path))
    # written again from what was read: the same bytes
    again = write_mcap(open_recording(path), tmp_path / "again.mcap")
    assert again.read_bytes() == path.read_bytes()


def test_window_read_touches_only_its_chunks(tmp_path, monkeypatch):
    recording = make_recording(seconds=60.0)
    path = write_mcap(recording, tmp_path / "long.mcap", chunk_size=256 * 1024)
    read = open_recording(path)
    index: McapIndex = read.audio._index
    assert len(index.summary.chunk_indexes) > 30
    opened = []
    original = McapIndex._chunk_messages

    def counting(self, chunk_id):
        opened.append(chunk_id)
        return original(self, chunk_id)

    monkeypatch.setattr(McapIndex, "_chunk_messages", counting)
    t_end = RECORDING_T0 + 31.0
    window = read.audio.window(t_end, 2.0)
    assert np.array_equal(window, recording.audio.window(t_end, 2.0))
    assert len(set(opened)) <= 4


def test_refuses_to_overwrite_and_a_failed_write_keeps_the_old_file(tmp_path):
    path = write_mcap(make_recording(), tmp_path / "rec.mcap")
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="already exists"):
        write_mcap(make_recording(seed=1), path)

    class Broken(ArrayPointClouds):
        def __getitem__(self, index):
            if index == 5:
                raise OSError("sensor stream broke")
            return super().__getitem__(index)

    broken = make_recording(seed=2)
    broken.lidar["mid360"] = Broken(broken.lidar["mid360"].timestamps, broken.lidar["mid360"].clouds)
    with pytest.raises(OSError, match="sensor stream broke"):
        write_mcap(broken, path, overwrite=True)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.mcap"]


def test_bad_files_raise_errors_naming_them(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file at all" * 10)
    with pytest.raises(RecordingError, match="junk.mcap: not an MCAP file"):
        open_recording(junk)

    good = write_mcap(make_recording(), tmp_path / "good.mcap")
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(RecordingError, match="truncated.mcap"):
        open_recording(truncated)

    foreign = tmp_path / "foreign.mcap"
    with open(foreign, "wb") as stream:
        writer = RawWriter(stream)
        writer.start()
        writer.finish()
    with pytest.raises(RecordingError, match="metadata 'mmaud' missing"):
        open_recording(foreign)

    with pytest.raises(RecordingError, match="no such file"):
        open_recording(tmp_path / "missing.mcap")
    with pytest.raises(RecordingError, match="not a known recording layout"):
        open_recording(tmp_path)


def _copy_with_metadata(src, dst, edit) -> None:
    """Copy an MCAP file record by record, editing its metadata on the way."""
    from mcap.reader import make_reader

    with open(src, "rb") as source, open(dst, "wb") as target:
        reader = make_reader(source)
        writer = RawWriter(target)
        writer.start(profile="ros2")
        summary = reader.get_summary()
        for schema in summary.schemas.values():
            writer.register_schema(schema.name, schema.encoding, schema.data)
        for channel in summary.channels.values():
            writer.register_channel(channel.topic, channel.message_encoding, channel.schema_id)
        for meta in reader.iter_metadata():
            writer.add_metadata(meta.name, edit(meta.name, dict(meta.metadata)))
        for _, channel, message in reader.iter_messages():
            writer.add_message(channel.id, message.log_time, message.data, message.publish_time)
        writer.finish()


def test_inconsistent_audio_description_is_rejected(tmp_path):
    recording = make_recording()
    good = write_mcap(recording, tmp_path / "good.mcap")

    def two_channels(name, meta):
        if name == "audio":
            meta["channels"] = "2"
            meta["mic_positions_json"] = "[[0, 0, 0], [1, 0, 0]]"
        return meta

    _copy_with_metadata(good, tmp_path / "bad.mcap", two_channels)
    with pytest.raises(RecordingError, match="bad.mcap: /audio/info says 4 ch"):
        open_recording(tmp_path / "bad.mcap")

    recording.audio.mic_positions = recording.audio.mic_positions[:2]  # 4 channels, 2 positions
    with pytest.raises(RecordingError, match="4 channels but 2 mic positions"):
        write_mcap(recording, tmp_path / "never.mcap")
    assert not (tmp_path / "never.mcap").exists()


def test_duplicate_timestamps_are_refused_on_write(tmp_path):
    recording = make_recording()
    recording.ground_truth.timestamps[3] = recording.ground_truth.timestamps[2]
    with pytest.raises(RecordingError, match="/ground_truth: timestamps must increase"):
        write_mcap(recording, tmp_path / "dup.mcap")
    assert not any(tmp_path.iterdir())


def test_replace_track_adds_pseudo_labels_and_keeps_the_rest(tmp_path):
    from datamodules.formats.mcap_file import replace_track

    recording = make_recording()
    recording.pseudo_labels = None
    path = write_mcap(recording, tmp_path / "rec.mcap")
    labels = Track(recording.ground_truth.timestamps, recording.ground_truth.xyz + 0.5,
                   valid=np.arange(len(recording.ground_truth)) % 4 != 0,
                   quality={"support": np.arange(len(recording.ground_truth), dtype=float)})
    replace_track(path, "/pseudo_label", labels)
    recording.pseudo_labels = labels
    assert_same_recording(recording, open_recording(path))
    replace_track(path, "/pseudo_label", None)
    again = open_recording(path)
    assert again.pseudo_labels is None and len(again.lidar["mid360"]) == len(recording.lidar["mid360"])
