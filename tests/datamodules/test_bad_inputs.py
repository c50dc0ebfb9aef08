"""Bad input, case by case: each row makes a bad recording from a simulated one, runs a command and checks
that it fails (or warns) with one line naming the file and what was expected, and that no good file changed.

A new case is one more row in ``CASES`` (a maker of the bad input, the command, the exit code and the words
the message must hold).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer as RawWriter

from datamodules.cli import main
from datamodules.formats import mcap_file, open_recording
from datamodules.formats.mcap_file import McapIndex, write_mcap
from datamodules.recording import ArrayAudio, RecordingError, Track
from tests.helpers.filesystem import deny_writes_under


def tree_hashes(root: Path) -> dict[str, str]:
    """sha256 of every file under ``root`` (hidden ones too), by relative path."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def first(simulated_dir: Path) -> Path:
    return sorted(simulated_dir.glob("*.mcap"))[0]


def in_memory(path: Path):
    """The recording at ``path`` with audio, LiDAR and track held in memory (so they can be altered)."""
    rec = open_recording(path)
    audio = rec.audio
    rec.audio = ArrayAudio(audio.read(0, audio.num_samples), audio.sample_rate, audio.t0, audio.mic_positions,
                           sample_format=audio.sample_format)
    from datamodules.recording import ArrayPointClouds

    rec.lidar = {s: ArrayPointClouds(c.timestamps, [c[i] for i in range(len(c))]) for s, c in rec.lidar.items()}
    rec.frames = None
    return rec


def rewrite(src: Path, dst: Path, audio_meta: dict[str, str], info: dict | None) -> None:
    """Copy an MCAP recording message for message with its metadata 'audio' and /audio/info message changed."""
    from mcap_ros2._dynamic import serialize_dynamic

    with open(src, "rb") as source, open(dst, "wb") as target:
        reader = make_reader(source)
        summary = reader.get_summary()
        writer = RawWriter(target)
        writer.start(profile="ros2", library="test")
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, {**record.metadata, **audio_meta} if record.name == "audio"
                                else record.metadata)
        schemas = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in summary.schemas.items()}
        channels = {cid: writer.register_channel(c.topic, c.message_encoding, schemas[c.schema_id], c.metadata)
                    for cid, c in summary.channels.items()}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            data = message.data
            if channel.topic == mcap_file.TOPIC_AUDIO_INFO:
                encode = serialize_dynamic(schema.name, schema.data.decode())[schema.name]
                data = encode(info)
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time, message.sequence)
        writer.finish()


# ------------------------------------------------------------------------------------------ bad inputs


def nan_ground_truth(good: Path, out: Path) -> Path:
    rec = in_memory(good)
    xyz = rec.ground_truth.xyz.copy()
    xyz[7] = np.nan
    rec.ground_truth = Track(rec.ground_truth.timestamps, xyz)
    return write_mcap(rec, out / "nan_gt.mcap")


def millimetre_ground_truth(good: Path, out: Path) -> Path:
    rec = in_memory(good)
    rec.ground_truth = Track(rec.ground_truth.timestamps, rec.ground_truth.xyz * 1000.0)
    return write_mcap(rec, out / "mm_gt.mcap")


def wrong_sample_rate(good: Path, out: Path) -> Path:
    """48 kHz data whose metadata and AudioInfo both say 44100 Hz."""
    target = out / "rate.mcap"
    rewrite(good, target, {"sample_rate": "44100.0"},
            {"channels": 4, "sample_rate": 44100, "sample_format": "S16LE", "bitrate": 0, "coding_format": "wave"})
    return target


def three_channels_as_four(good: Path, out: Path) -> Path:
    """Three-channel audio whose metadata and AudioInfo say four channels."""
    rec = in_memory(good)
    audio = rec.audio
    rec.audio = ArrayAudio(audio.samples[:3], audio.sample_rate, audio.t0, audio.mic_positions[:3],
                           sample_format=audio.sample_format)
    three = write_mcap(rec, out / "three.mcap")
    target = out / "channels.mcap"
    rewrite(three, target, {"channels": "4", "mic_positions_json": str(np.zeros((4, 3)).tolist())},
            {"channels": 4, "sample_rate": 48000, "sample_format": "S16LE", "bitrate": 0, "coding_format": "wave"})
    three.unlink()
    return target


def nan_audio(good: Path, out: Path, monkeypatch=None) -> Path:
    rec = in_memory(good)
    samples = rec.audio.samples.copy()
    samples[2, 48000 + 123] = np.nan  # 1.0026 s in
    rec.audio = ArrayAudio(samples, rec.audio.sample_rate, rec.audio.t0, rec.audio.mic_positions, "F32LE")
    check = mcap_file.check_finite_audio
    mcap_file.check_finite_audio = lambda *args: None  # the writer refuses NaN: bypass it to make the bad file
    try:
        return write_mcap(rec, out / "nan_audio.mcap", audio_format="F32LE")
    finally:
        mcap_file.check_finite_audio = check


def flipped_bits(good: Path, out: Path) -> Path:
    """Two bits flipped in the middle of a chunk that holds audio."""
    target = out / "flipped.mcap"
    shutil.copy(good, target)
    index = McapIndex(target)
    audio_id = index.topics[mcap_file.TOPIC_AUDIO].id
    chunk = next(c for c in index.summary.chunk_indexes if audio_id in c.message_index_offsets)
    data = bytearray(target.read_bytes())
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[middle] ^= 0x10
    data[middle + 1] ^= 0x01
    target.write_bytes(bytes(data))
    return target


def duplicate_in_source(good: Path, out: Path) -> Path:
    return out  # the folder itself: converting it into itself


def a_recording(good: Path, out: Path) -> Path:
    return good  # an existing file where a folder is expected


MakeBad = Callable[[Path, Path], Path]

#: (id, maker, command (BAD: the bad file, DIR: the folder of copies, OUT: a fresh folder), exit code, words)
CASES: list[tuple[str, MakeBad, list[str], int, list[str]]] = [
    ("nan_ground_truth_info", nan_ground_truth, ["info", "BAD"], 1,
     ["nan_gt.mcap", "/ground_truth", "NaN or infinite", "index 7", "expected finite"]),
    ("millimetres_info", millimetre_ground_truth, ["info", "BAD"], 1,
     ["mm_gt.mcap", "/ground_truth", "millimetres", "expected metres within 1000 m"]),
    ("millimetres_convert", millimetre_ground_truth, ["convert", "BAD", "OUT"], 2, ["mm_gt.mcap", "millimetres"]),
    ("sample_rate_info", wrong_sample_rate, ["info", "BAD"], 1,
     ["rate.mcap", "/audio", "48000 samples/s", "44100 Hz", "tolerance 1%"]),
    ("sample_rate_convert", wrong_sample_rate, ["convert", "BAD", "OUT"], 2, ["rate.mcap", "48000 samples/s"]),
    ("channels_info", three_channels_as_four, ["info", "BAD"], 1,
     ["channels.mcap", "3 channel(s) at 48000 Hz", "not the 4 channel(s) stated"]),
    ("nan_audio_info", nan_audio, ["info", "BAD"], 1,
     ["nan_audio.mcap", "/audio", "NaN or infinite audio sample", "channel 2", "expected finite samples"]),
    ("nan_audio_convert", nan_audio, ["convert", "BAD", "OUT"], 2,
     ["nan_audio.mcap", "t = 1692845358.003 s, 1.003 s into the audio"]),
    ("crc_convert", flipped_bits, ["convert", "BAD", "OUT"], 2,
     ["flipped.mcap", "corrupt chunk", " s, topic(s) ", "/audio"]),
    ("convert_into_itself", duplicate_in_source, ["convert", "DIR", "DIR", "--overwrite"], 2,
     ["destination is the source folder itself", "give a destination outside"]),
    ("convert_inside_itself", duplicate_in_source, ["convert", "DIR", "DIR/sub"], 2,
     ["lies inside the source folder"]),
    ("simulate_zero_seconds", duplicate_in_source, ["simulate", "--out", "OUT", "--seconds", "0"], 2,
     ["--seconds", "at least 0.2 s", "got 0"]),
    ("simulate_negative_seconds", duplicate_in_source, ["simulate", "--out", "OUT", "--seconds", "-3"], 2,
     ["--seconds", "got -3"]),
    ("simulate_zero_rate", duplicate_in_source, ["simulate", "--out", "OUT", "--sample-rate", "0"], 2,
     ["--sample-rate", "positive", "got 0"]),
    ("simulate_zero_sequences", duplicate_in_source, ["simulate", "--out", "OUT", "--sequences", "0"], 2,
     ["--sequences", "at least 1", "got 0"]),
    ("simulate_zero_workers", duplicate_in_source, ["simulate", "--out", "OUT", "--workers", "0"], 2,
     ["--workers", "at least 1", "got 0"]),
    ("audio_of_a_folder", duplicate_in_source, ["audio", "DIR", "--out", "OUT/a.wav"], 2,
     ["not a known recording layout but a folder of 3 recordings", "give one of them here", "--data.root"]),
    ("simulate_into_a_file", a_recording, ["simulate", "--out", "BAD", "--seconds", "1", "--sequences", "1"],
     2, [".mcap: is a file; the simulator's output folder (--out) must be a folder"]),
]


def message_lines(out: str, err: str) -> list[str]:
    """The lines that report a failure: ``aaute: error: ...`` on stderr, ``FAILED ...`` rows of ``info``."""
    return [line for line in (*err.splitlines(), *out.splitlines())
            if line.startswith(("aaute: error:", "FAILED "))]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_bad_input_gives_one_line_and_changes_nothing(case, simulated_dir, tmp_path, capsys):
    _, make, command, code, words = case
    data = tmp_path / "data"
    shutil.copytree(simulated_dir, data)
    bad = make(first(data), data)
    out = tmp_path / "out"
    before = tree_hashes(data)
    argv = [word.replace("BAD", str(bad)).replace("DIR", str(data)).replace("OUT", str(out)) for word in command]
    capsys.readouterr()
    assert main(argv) == code
    captured = capsys.readouterr()
    lines = message_lines(captured.out, captured.err)
    assert len(lines) == 1, (captured.out, captured.err)
    for word in words:
        assert word in lines[0], (word, lines[0])
    assert "Traceback" not in captured.err and "discover_recordings" not in lines[0]  # no Python on a command line
    assert tree_hashes(data) == before  # nothing of the input changed, nothing was added beside it
    assert not out.exists() or not any(out.rglob("*.mcap"))  # nothing written for a refused input


def test_info_reports_every_bad_file_and_still_describes_the_good_ones(simulated_dir, tmp_path, capsys):
    data = tmp_path / "data"
    shutil.copytree(simulated_dir, data)
    nan_ground_truth(first(simulated_dir), data)
    millimetre_ground_truth(first(simulated_dir), data)
    assert main(["info", str(data)]) == 1
    out = capsys.readouterr().out
    good = [p.name for p in sorted(simulated_dir.glob("*.mcap"))]
    assert all(any(line.startswith(name) for line in out.splitlines()) for name in good)
    failed = [line for line in out.splitlines() if line.startswith("FAILED ")]
    assert len(failed) == 2 and "nan_gt.mcap" in failed[1] + failed[0] and "mm_gt.mcap" in failed[0] + failed[1]


def test_a_plausible_range_override_accepts_far_tracks(simulated_dir, tmp_path, monkeypatch):
    bad = millimetre_ground_truth(first(simulated_dir), tmp_path)
    with pytest.raises(RecordingError, match="millimetres"):
        open_recording(bad)
    monkeypatch.setenv("AAUTE_PLAUSIBLE_RANGE_M", "1e6")
    assert open_recording(bad).ground_truth.xyz.max() > 1000


def test_ground_truth_at_a_normal_range_and_integer_audio_pass(simulated_dir):
    rec = open_recording(first(simulated_dir))  # the reader's checks accept good recordings
    assert np.isfinite(rec.ground_truth.xyz).all() and rec.audio.sample_format == "S16LE"


def test_duplicate_sequence_ids_name_the_ids_and_files(simulated_dir, tmp_path):
    from datamodules.mmaud import MMAUDDataModule

    data = tmp_path / "data"
    shutil.copytree(simulated_dir, data)
    shutil.copy(first(data), data / "copy.mcap")
    module = MMAUDDataModule(str(data), window_seconds=1.0, cache_dir=str(tmp_path / "cache"))
    with pytest.raises(RecordingError, match=r"sequence ids are not unique: 'sim11-0000-avata' in .*copy\.mcap, "
                                             r".*sim11_0000\.mcap"):
        module.setup("fit")


def test_stale_temporary_files_of_a_killed_write_are_removed_and_reported(simulated_dir, tmp_path, caplog):
    out = tmp_path / "out"
    out.mkdir()
    target = out / "sim11-0000-avata.mcap"
    stale = out / f".{target.name}.tmp-999999"
    stale.write_bytes(b"\0" * 4096)
    old = time.time() - 3600
    os.utime(stale, (old, old))
    assert main(["convert", str(first(simulated_dir)), str(target)]) == 0
    assert not stale.exists() and target.is_file()
    assert "removed" in caplog.text and stale.name in caplog.text and "interrupted write" in caplog.text


def test_a_temporary_file_being_written_is_left_alone(tmp_path):
    import fcntl

    from datamodules.atomic import remove_stale_temporaries

    target = tmp_path / "x.mcap"
    busy = tmp_path / f".{target.name}.tmp-999998"
    busy.write_bytes(b"\0")
    old = time.time() - 3600
    os.utime(busy, (old, old))
    with open(busy, "rb") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)  # a live writer holds it
        assert remove_stale_temporaries(target) == []
    assert remove_stale_temporaries(target) == [busy] and not busy.exists()


def test_debug_shows_the_traceback(simulated_dir, tmp_path, monkeypatch):
    bad = millimetre_ground_truth(first(simulated_dir), tmp_path)
    with pytest.raises(RecordingError, match="millimetres"):
        main(["convert", str(bad), str(tmp_path / "out"), "--debug"])
    monkeypatch.setenv("AAUTE_DEBUG", "1")
    with pytest.raises(RecordingError, match="millimetres"):
        main(["convert", str(bad), str(tmp_path / "out")])


def test_programming_errors_keep_their_traceback(monkeypatch, tmp_path):
    import datamodules.convert

    def broken(*args, **kwargs):
        raise KeyError("a bug")

    monkeypatch.setattr(datamodules.convert, "convert", broken)
    with pytest.raises(KeyError):
        main(["convert", str(tmp_path), str(tmp_path / "out")])


def test_written_chunks_carry_a_crc_to_validate(simulated_dir):
    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk

    index = McapIndex(first(simulated_dir))
    with open(first(simulated_dir), "rb") as stream:
        for chunk_index in index.summary.chunk_indexes:
            stream.seek(chunk_index.chunk_start_offset + 1 + 8)
            assert Chunk.read(ReadDataStream(stream)).uncompressed_crc != 0


def test_label_reports_nan_ground_truth_instead_of_a_nan_score(simulated_dir, tmp_path, capsys):
    bad = nan_ground_truth(first(simulated_dir), tmp_path)
    before = tree_hashes(tmp_path)
    assert main(["label", str(bad), "--evaluate"]) == 1
    out = capsys.readouterr().out
    assert "nan_gt.mcap /ground_truth: 1 labelled position(s) are NaN or infinite, first at index 7" in out
    assert "mean_m nan" not in out
    assert tree_hashes(tmp_path) == before


@pytest.mark.slow
def test_ctrl_c_stops_simulate_at_once_and_a_rerun_resumes(tmp_path):
    """SIGINT while two workers simulate: exit 130 without a traceback, no temporary file, finished files kept."""
    import signal
    import subprocess
    import sys

    out = tmp_path / "sim"
    command = [sys.executable, "-m", "datamodules.cli", "simulate", "--out", str(out), "--sequences", "6",
               "--seconds", "1", "--no-camera", "--workers", "2"]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    process = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 600
    while not list(out.glob("*.mcap")) and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=300)
    assert process.returncode == 130, err
    assert "Traceback" not in err and "run the same command again to resume" in err and "aaute: interrupted" in err
    assert not [p for p in out.iterdir() if ".tmp-" in p.name]
    finished = tree_hashes(out)
    assert 1 <= len(finished) < 6
    for name in finished:
        assert open_recording(out / name).audio is not None  # complete, readable files only
    assert subprocess.run(command, env=env, capture_output=True).returncode == 0
    again = tree_hashes(out)
    assert len(again) == 6 and all(again[name] == digest for name, digest in finished.items())


def test_convert_refuses_to_drop_lidar_topics_it_cannot_place(tmp_path, capsys, caplog):
    pytest.importorskip("rosbags")
    from tests.helpers.bags import write_flight

    flight = tmp_path / "flight"
    write_flight(flight, mid360_topic="/points_raw")  # a PointCloud2 topic whose name names no sensor
    before = tree_hashes(flight)
    out = tmp_path / "out"
    assert main(["convert", str(flight), str(out)]) == 2
    lines = message_lines(*capsys.readouterr())
    assert len(lines) == 1 and f"{flight}: LiDAR topic(s) /points_raw" in lines[0]
    assert "not mapped to a sensor and would be lost" in lines[0] and "--drop-unread-lidar" in lines[0]
    assert not out.exists() and tree_hashes(flight) == before
    assert main(["convert", str(flight), str(out), "--drop-unread-lidar"]) == 0
    written = next(out.glob("*.mcap"))
    assert "dropped LiDAR topic(s) /points_raw" in caplog.text
    rec = open_recording(written)
    assert rec.meta["dropped_lidar_topics"] == ["/points_raw"] and "mid360" not in rec.lidar
    assert main(["convert", str(written), str(tmp_path / "again")]) == 0  # the written file converts as it is


@pytest.mark.parametrize(("given", "words"), [
    (["--channels", "2"], ["4 channel(s) at 48000 Hz", "not the 2 channel(s) stated", "give the right channel count"]),
    (["--sample-rate", "44100"], ["48000 samples/s but the sample rate is 44100 Hz", "give the right sample rate"]),
])
def test_a_wrong_channel_count_for_a_bag_is_named_as_such(given, words, tmp_path, capsys):
    pytest.importorskip("rosbags")
    from tests.helpers.bags import write_flight

    flight = tmp_path / "flight"
    write_flight(flight, audio="plain", info=False, lidar=False, gt=False)  # 4 channels, S16LE, no AudioInfo
    assert main(["info", str(flight), *given]) == 1
    lines = message_lines(*capsys.readouterr())
    assert len(lines) == 1 and "mavic2.bag /audio/audio (parameters)" in lines[0], lines
    for word in words:
        assert word in lines[0], (word, lines[0])


def test_simulate_into_a_folder_it_cannot_write_says_so_before_simulating(tmp_path, monkeypatch, capsys):
    import datamodules.simulate.simulator as simulator

    out = tmp_path / "locked"
    out.mkdir()
    deny_writes_under(monkeypatch, out)
    simulated = []
    monkeypatch.setattr(simulator, "simulate_recording", lambda *args, **kwargs: simulated.append(args))
    assert main(["simulate", "--out", str(out), "--seconds", "1", "--sequences", "1"]) == 2
    err = capsys.readouterr().err
    assert err == (f"aaute: error: {out}: cannot write into the simulator's output folder (--out) (Permission "
                   f"denied) (--debug for the traceback)\n")
    assert simulated == [] and list(out.iterdir()) == []
