"""A folder of WAV files (per channel or per node) with positions and a ground-truth CSV, as one recording."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from scipy.io import wavfile

from datamodules.formats import detect_layout, discover_recordings, open_recording
from datamodules.formats.mcap_file import read_mcap
from datamodules.recording import RecordingError

FS = 16000
POSITIONS = [[1.5, 1.5, 0.2], [-1.5, 1.5, 0.7], [-1.5, -1.5, 1.2], [1.5, -1.5, 1.7]]


def write_folder(folder, *, per_node: bool = False, positions: bool = True, rates=(FS,) * 4, lengths=(FS,) * 4):
    """Four channels of noise as ch1..ch4.wav (or two stereo node files), positions, ground truth, t0."""
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    codes = [(rng.uniform(-0.5, 0.5, n) * 32768).astype(np.int16) for n in lengths]
    if per_node:
        for k in range(2):
            wavfile.write(folder / f"node{k + 1}.wav", FS, np.stack(codes[2 * k:2 * k + 2], axis=1))
    else:
        for k in range(4):  # ch10 would sort after ch2: names are ordered naturally
            wavfile.write(folder / f"ch{k + 1}.wav", rates[k], codes[k])
    if positions:
        (folder / "mic_positions.csv").write_text("x,y,z\n" + "\n".join(",".join(map(str, p)) for p in POSITIONS))
    (folder / "ground_truth.csv").write_text("t,x,y,z\n" + "\n".join(f"{100 + i / 10},{i},2,3" for i in range(10)))
    (folder / "aaute_layout.yaml").write_text("t0: 100.0\ndrone: mavic3\n")
    return np.stack([c[:min(lengths)] for c in codes]).astype(np.float32) / 32768


@pytest.mark.parametrize("per_node", [False, True])
def test_wav_folder_reads_and_round_trips_through_convert(tmp_path, per_node, capsys):
    from datamodules.cli import main

    expected = write_folder(tmp_path / "flight", per_node=per_node)
    assert detect_layout(tmp_path / "flight") == "wav_folder"
    assert discover_recordings(tmp_path) == [tmp_path / "flight"]
    rec = open_recording(tmp_path / "flight")
    assert rec.drone == "mavic3" and rec.audio.t0 == 100.0 and rec.audio.sample_rate == FS
    assert np.array_equal(rec.audio.read(0, FS), expected)
    assert np.array_equal(rec.audio.mic_positions, POSITIONS) and rec.meta["mic_positions_known"] is True
    assert rec.ground_truth.xyz[3].tolist() == [3, 2, 3]
    assert main(["convert", str(tmp_path / "flight"), str(tmp_path / "out.mcap")]) == 0
    back = read_mcap(tmp_path / "out.mcap")
    assert np.array_equal(back.audio.read(0, FS), expected) and np.array_equal(back.audio.mic_positions, POSITIONS)
    assert np.array_equal(back.ground_truth.timestamps, rec.ground_truth.timestamps)
    assert back.meta["source_format"] == "wav_folder"
    assert rec.meta["audio_alignment_uncertainty_s"] is None  # WAVs hold no stamps: the alignment is not known
    capsys.readouterr()
    assert main(["info", str(tmp_path / "flight")]) == 0
    assert f"{2 if per_node else 4} own-clocks ±?" in capsys.readouterr().out


def test_without_positions_and_of_unequal_length(tmp_path, caplog):
    expected = write_folder(tmp_path / "f", positions=False, lengths=(FS, FS, FS - 800, FS))
    with caplog.at_level(logging.WARNING):
        rec = open_recording(tmp_path / "f")
    assert rec.meta["mic_positions_known"] is False and rec.audio.num_samples == FS - 800
    assert np.array_equal(rec.audio.read(0, FS - 800), expected)
    assert "ch1.wav is 0.050 s longer than the shortest file" in caplog.text


def test_files_at_different_rates_are_refused(tmp_path):
    write_folder(tmp_path / "f", rates=(FS, FS, 8000, FS))
    with pytest.raises(RecordingError, match=r"different sample rates \(ch1.wav 16000 Hz, ch2.wav 16000 Hz, "
                                             r"ch3.wav 8000 Hz"):
        open_recording(tmp_path / "f")


def test_bad_positions_and_ground_truth_name_the_file(tmp_path):
    write_folder(tmp_path / "f")
    (tmp_path / "f" / "mic_positions.csv").write_text("1,2,3\n4,5,6\n")
    with pytest.raises(RecordingError, match=r"mic_positions.csv: 2 microphone position\(s\) for 4 audio channel"):
        open_recording(tmp_path / "f")
    (tmp_path / "f" / "mic_positions.csv").unlink()
    (tmp_path / "f" / "ground_truth.csv").write_text("time,x,y,z\n1,2,3,4\n")
    with pytest.raises(RecordingError, match=r"ground_truth.csv: ground truth needs columns t, x, y, z"):
        open_recording(tmp_path / "f")
