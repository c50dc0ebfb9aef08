"""Microphone positions as configuration: the positions file, its checks, and phase recipes refusing a recording
read without them."""

from __future__ import annotations

import numpy as np
import pytest

from datamodules.formats import discover_recordings, open_recording
from datamodules.formats.mcap_file import write_mcap
from datamodules.formats.positions import parse_mic_positions, read_mic_positions
from datamodules.recording import RecordingError

POSITIONS = [[1.5, 1.5, 0.2], [-1.5, 1.5, 0.7], [-1.5, -1.5, 1.2], [1.5, -1.5, 1.7]]


@pytest.mark.parametrize(("name", "text"), [
    ("mics.csv", "# rig frame, metres\nx,y,z\n" + "\n".join(",".join(map(str, p)) for p in POSITIONS) + "\n"),
    ("mics.txt", "\n".join(" ".join(map(str, p)) for p in POSITIONS)),
    ("mics.yaml", "mic_positions:\n" + "".join(f"  - {p}\n" for p in POSITIONS)),
    ("list.yml", "".join(f"- {p}\n" for p in POSITIONS)),
])
def test_positions_file_forms(tmp_path, name, text):
    (tmp_path / name).write_text(text)
    assert np.array_equal(read_mic_positions(tmp_path / name), POSITIONS)
    assert read_mic_positions(tmp_path / name, 4).shape == (4, 3)


@pytest.mark.parametrize(("value", "channels", "match"), [
    (POSITIONS, 3, r"4 microphone position\(s\) for 3 audio channel"),
    ([[0, 0]], None, r"list of \[x, y, z\].*shape \(1, 2\)"),
    ([[0, 0, float("nan")]], None, "NaN or infinite"),
    ([[150.0, 0, 0], [0, 0, 0]], None, "150 m from the rig's origin"),
    ([[1, 0, 0], [1, 0, 0]], None, "microphones 0 and 1 are at the same point"),
    ("four", None, "list of"),
])
def test_bad_positions(value, channels, match):
    with pytest.raises(RecordingError, match=match):
        parse_mic_positions(value, channels, "mapping")


def test_bad_positions_file_names_line(tmp_path):
    (tmp_path / "m.csv").write_text("x,y,z\n1,2,3\n4,five,6\n")
    with pytest.raises(RecordingError, match=r"m.csv: line 3 is not three numbers"):
        read_mic_positions(tmp_path / "m.csv")


def test_phase_recipe_refuses_unknown_positions_and_warns_of_separate_clocks(simulated_dir, tmp_path, caplog):
    from datamodules.mmaud import MMAUDDataModule

    recording = open_recording(discover_recordings(simulated_dir)[0])
    recording.meta.update(mic_positions_known=False, nodes_share_clock=False, audio_alignment_uncertainty_s=2e-4)
    recording.lidar, recording.frames = {}, None  # audio and ground truth are all the windows need
    write_mcap(recording, tmp_path / "data" / "blind.mcap")
    module = MMAUDDataModule(str(tmp_path / "data"), inputs={"audio_phase": "gcc_phat"},
                             cache_dir=str(tmp_path / "cache"), clock_calibration="off")  # off: it warns
    with pytest.raises(RecordingError, match=r"blind.mcap: phase features \('gcc_phat'\) needs the microphone "
                                             rf"positions, but recording '{recording.sequence_id}' was read "
                                             r"without them"):
        module.setup("fit")
    assert "uses time differences between audio nodes on separate clocks (alignment uncertainty 0.20 ms" in caplog.text
