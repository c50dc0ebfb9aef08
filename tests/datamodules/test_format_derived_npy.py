"""The derived per-sample npy layout (AAUTE / AV-FDTI / TAME): rebuilt recordings, list files, bad input."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from datamodules.cli import main
from datamodules.formats import derived_npy, discover_recordings, open_recording
from datamodules.formats.mcap_file import read_mcap, write_mcap
from datamodules.recording import RecordingError
from tests.helpers.layouts import CHUNK, make_derived


@pytest.fixture()
def derived(tmp_path) -> tuple[Path, dict]:
    root = tmp_path / "Data-M"
    truth = make_derived(root, {"0": 30, "3": 25})
    annotation = root / "annotation" / "annotation_train_all"
    annotation.mkdir(parents=True)
    (annotation / "trainval.txt").write_text("\n".join(f"0/{i}.npy" for i in range(8, 30)) + "\n")
    return root, truth


def test_sequence_rebuilt_as_one_continuous_recording(derived):
    root, truth = derived
    rec = open_recording(root / "audio_npy" / "0", sample_rate=46080)
    audio = rec.audio
    assert rec.sequence_id == "0" and rec.meta["source_format"] == "derived_npy"
    assert audio.sample_rate == 46080 and audio.num_channels == 4 and audio.num_samples == 30 * CHUNK
    assert audio.sample_format == "S16LE" and rec.meta["sample_rate_assumed"] is False
    expected = truth["0"]["audio"].T / 32768.0
    assert np.array_equal(audio.read(0, audio.num_samples), expected.astype(np.float32))
    # a range across three chunk files
    assert np.array_equal(audio.read(CHUNK - 7, 3 * CHUNK + 5), expected[:, CHUNK - 7:3 * CHUNK + 5].astype(np.float32))
    assert np.array_equal(audio.mic_positions, np.zeros((4, 3))) and rec.meta["mic_positions_known"] is False


def test_labels_are_stamped_at_the_end_of_their_chunk(derived):
    root, truth = derived
    rec = open_recording(root / "audio_npy" / "0", sample_rate=46080, t0=100.0)
    duration = CHUNK / 46080
    assert rec.meta["chunk_duration_s"] == duration and rec.audio.t0 == 100.0
    gt, pseudo = rec.ground_truth, rec.pseudo_labels
    assert np.allclose(gt.timestamps, 100.0 + (np.arange(30) + 1) * duration)
    assert np.allclose(gt.xyz, truth["0"]["gt"]) and np.allclose(pseudo.xyz, truth["0"]["pseudo"])
    assert gt.valid.all() and pseudo.valid.all()
    # the causal window ending at label idx ends with exactly chunk idx's audio
    window = rec.audio.window(float(gt.timestamps[9]), duration)
    assert np.array_equal(window, (truth["0"]["audio"][9 * CHUNK:10 * CHUNK].T / 32768.0).astype(np.float32))
    assert np.array_equal(rec.frames.timestamps, gt.timestamps) and rec.frames[0].format == "png"
    assert np.array_equal(gt.quality["image_visible"], np.arange(30) % 2)
    # the default rate (48 kHz) gives a shorter chunk duration
    default = open_recording(root / "audio_npy" / "0")
    assert default.audio.sample_rate == 48000 and default.meta["sample_rate_assumed"] is True
    assert default.ground_truth.timestamps[0] == pytest.approx(CHUNK / 48000)


def test_first_index_sets_t0(tmp_path):
    make_derived(tmp_path / "root", {"mavic3": 5}, first=1)
    rec = open_recording(tmp_path / "root" / "audio_npy" / "mavic3")
    assert rec.drone == "mavic3" and rec.meta["first_index"] == 1
    assert rec.audio.t0 == pytest.approx(CHUNK / 48000) and rec.ground_truth.timestamps[0] == pytest.approx(
        2 * CHUNK / 48000)


def test_drone_from_class_folder_label_files_or_sidecar(derived, tmp_path):
    root, _ = derived
    assert open_recording(root / "audio_npy" / "0").drone == "mavic2"  # Data-M class folder 0
    assert open_recording(root / "audio_npy" / "3").drone == "avata"
    make_derived(tmp_path / "other", {"flight_a": 4})
    rec = open_recording(tmp_path / "other" / "audio_npy" / "flight_a")
    assert rec.drone == "m300" and "label/" in rec.meta["drone_source"]  # label/ holds class 4
    (tmp_path / "other" / "aaute_layout.yaml").write_text("sample_rate: 46080\ndrone: {flight_a: phantom4}\n")
    rec = open_recording(tmp_path / "other" / "audio_npy" / "flight_a")
    assert rec.drone == "phantom4" and rec.audio.sample_rate == 46080


def test_avfdti_names(tmp_path):
    root = tmp_path / "fdti"
    make_derived(root, {"m300s1": 6})
    (root / "audio_npy").rename(root / "np_data_align")
    (root / "gt").rename(root / "label_xyz")
    for path in (root / "label" / "m300s1").glob("*.npy"):  # AV-FDTI's label/ holds the gt position
        np.save(path, np.load(root / "label_xyz" / "m300s1" / path.name))
    rec = open_recording(root / "np_data_align" / "m300s1")
    assert rec.drone == "m300" and rec.meta["folders"]["ground_truth"] == "label"
    assert np.allclose(rec.ground_truth.xyz[2], np.load(root / "label_xyz" / "m300s1" / "2.npy"))


def test_missing_labels_are_invalid_with_a_warning(derived, caplog):
    root, _ = derived
    (root / "gt" / "3" / "4.npy").unlink()
    (root / "gt" / "3" / "5.npy").unlink()
    with caplog.at_level(logging.WARNING, logger="datamodules.formats.derived_npy"):
        rec = open_recording(root / "audio_npy" / "3")
    assert rec.ground_truth.valid.sum() == 23 and not rec.ground_truth.valid[[4, 5]].any()
    assert any("2 of 25 chunks have no (finite) ground truth" in r.getMessage() for r in caplog.records)


def test_discover_root_and_list_file(derived):
    root, _ = derived
    assert discover_recordings(root) == [root / "audio_npy" / "0", root / "audio_npy" / "3"]
    listing = root / "annotation" / "annotation_train_all" / "trainval.txt"
    assert discover_recordings(listing) == [root / "audio_npy" / "0"]
    assert derived_npy.read_sample_list(listing) == {"0": list(range(8, 30))}
    with pytest.raises(RecordingError, match="2 sequences"):
        open_recording(root)


def test_list_file_naming_missing_samples(derived):
    root, _ = derived
    listing = root / "annotation" / "bad.txt"
    listing.write_text("0/3.npy\n0/31.npy\n7/1.npy\n")
    with pytest.raises(RecordingError, match=r"bad\.txt: 2 listed sample\(s\) have no audio file.*0/31\.npy, 7/1\.npy"):
        discover_recordings(listing)
    listing.write_text("justaname\n")
    with pytest.raises(RecordingError, match=r"bad\.txt:1: expected a '<seq>/<idx>\.npy' line"):
        discover_recordings(listing)


def test_mismatched_chunk_lengths(derived):
    root, _ = derived
    np.save(root / "audio_npy" / "0" / "12.npy", np.zeros((CHUNK - 10, 4), np.int16))
    with pytest.raises(RecordingError, match=r"audio_npy/0: audio chunks differ.*first odd one 12\.npy"):
        open_recording(root / "audio_npy" / "0")


def test_missing_chunk_is_an_error_or_silence_on_request(derived, caplog):
    root, truth = derived
    (root / "audio_npy" / "0" / "10.npy").unlink()
    with pytest.raises(RecordingError, match=r"1 audio chunk\(s\) missing.*10\.npy"):
        open_recording(root / "audio_npy" / "0")
    with caplog.at_level(logging.WARNING, logger="datamodules.formats.derived_npy"):
        rec = open_recording(root / "audio_npy" / "0", missing_audio="zeros")
    assert rec.meta["audio_missing_chunks"] == 1
    assert any("1 missing audio chunk(s) filled with zeros" in r.getMessage() for r in caplog.records)
    block = rec.audio.read(9 * CHUNK, 12 * CHUNK)
    assert not block[:, CHUNK:2 * CHUNK].any() and block[:, :CHUNK].any() and block[:, 2 * CHUNK:].any()


def test_nan_audio_and_bad_names(tmp_path):
    root = tmp_path / "floats"
    make_derived(root, {"x": 4}, images=False)
    for path in (root / "audio_npy" / "x").glob("*.npy"):
        np.save(path, (np.load(path) / 32768.0).astype(np.float32))
    rec = open_recording(root / "audio_npy" / "x")
    assert rec.audio.sample_format == "F32LE" and rec.audio.read(0, 4 * CHUNK).any()
    bad = np.zeros((CHUNK, 4), np.float32)
    bad[7, 2] = np.nan
    np.save(root / "audio_npy" / "x" / "2.npy", bad)
    with pytest.raises(RecordingError, match=r"x/2\.npy: audio chunk holds NaN"):
        open_recording(root / "audio_npy" / "x").audio.read(0, 4 * CHUNK)
    np.save(root / "audio_npy" / "x" / "notes.npy", np.zeros(1))
    with pytest.raises(RecordingError, match=r"must be named <idx>\.npy.*notes\.npy"):
        open_recording(root / "audio_npy" / "x")


def test_audio_is_read_lazily(derived, monkeypatch):
    root, _ = derived
    rec = open_recording(root / "audio_npy" / "0")
    reads = []
    original = np.fromfile
    monkeypatch.setattr(np, "fromfile", lambda path, *a, **k: reads.append(Path(path).name) or original(path, *a, **k))
    rec.audio.read(5 * CHUNK + 3, 6 * CHUNK + 3)
    assert reads == ["5.npy", "6.npy"]


def test_converts_to_mcap_and_info_lists_every_sequence(derived, tmp_path, capsys):
    root, truth = derived
    rec = open_recording(root / "audio_npy" / "3", sample_rate=46080)
    back = read_mcap(write_mcap(rec, tmp_path / "seq3.mcap"))
    assert back.meta == rec.meta and back.drone == "avata"
    assert np.array_equal(back.audio.read(0, back.audio.num_samples), rec.audio.read(0, rec.audio.num_samples))
    assert back.audio.sample_rate == 46080
    assert np.array_equal(back.ground_truth.timestamps, rec.ground_truth.timestamps)
    assert np.array_equal(back.ground_truth.quality["image_visible"], rec.ground_truth.quality["image_visible"])
    assert np.array_equal(back.pseudo_labels.xyz, rec.pseudo_labels.xyz)
    assert main(["info", str(root), "--sample-rate", "46080"]) == 0
    table = capsys.readouterr().out.splitlines()
    assert len(table) == 4 and "derived_npy" in table[2] and "4ch 46080Hz" in table[3]
