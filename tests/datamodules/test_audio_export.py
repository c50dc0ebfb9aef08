"""``aaute audio``: a recording's audio as WAV or raw PCM, exact for S16LE audio, never half-written."""

from __future__ import annotations

import io
import wave

import numpy as np
import pytest

from datamodules.audio_export import encode, write_pcm, write_wav
from datamodules.cli import main
from datamodules.errors import ConfigError
from datamodules.formats import open_recording


@pytest.fixture(scope="module")
def recording(simulated_dir):
    return sorted(simulated_dir.glob("*.mcap"))[0]


def test_raw_pcm_holds_the_recordings_samples_exactly(recording):
    audio = open_recording(recording).audio
    stream = io.BytesIO()
    written = write_pcm(audio, stream, "s16le")
    frames = np.frombuffer(stream.getvalue(), dtype="<i2").reshape(-1, audio.num_channels)
    assert written == frames.nbytes and frames.shape[0] == audio.num_samples
    np.testing.assert_array_equal(frames.T / 32768.0, audio.read(0, audio.num_samples))
    floats = io.BytesIO()
    write_pcm(audio, floats, "f32le")
    np.testing.assert_array_equal(np.frombuffer(floats.getvalue(), dtype="<f4").reshape(-1, 4).T,
                                  audio.read(0, audio.num_samples))


def test_wav_round_trips_and_an_existing_file_is_kept(recording, tmp_path):
    audio = open_recording(recording).audio
    path = write_wav(audio, tmp_path / "a.wav")
    with wave.open(str(path)) as wav:
        assert (wav.getnchannels(), wav.getframerate(), wav.getsampwidth()) == (4, round(audio.sample_rate), 2)
        data = np.frombuffer(wav.readframes(wav.getnframes()), dtype="<i2").reshape(-1, 4)
    np.testing.assert_array_equal(data.T / 32768.0, audio.read(0, audio.num_samples))
    before = path.read_bytes()
    with pytest.raises(FileExistsError):
        write_wav(audio, path)
    assert path.read_bytes() == before
    with pytest.raises(ConfigError, match="f32le.*expected one of s16le, s32le"):
        write_wav(audio, tmp_path / "b.wav", "f32le")
    assert not (tmp_path / "b.wav").exists()


def test_integer_encoding_rounds_and_clips_at_full_scale():
    samples = np.array([[0.5, -1.0, 1.0, 2.0, 1 / 32768 * 0.6]])
    assert np.frombuffer(encode(samples, "s16le"), dtype="<i2").tolist() == [16384, -32768, 32767, 32767, 1]


def test_cli_writes_pcm_to_stdout_and_a_wav_file(recording, tmp_path, capsysbinary, caplog):
    caplog.set_level("INFO")
    assert main(["audio", str(recording), "--out", "-"]) == 0
    out = capsysbinary.readouterr()
    audio = open_recording(recording).audio
    assert len(out.out) == audio.num_samples * audio.num_channels * 2
    assert "aaute track --audio - --channels 4 --rate 48000 --format s16le --t0" in caplog.text
    assert main(["audio", str(recording), "--out", str(tmp_path / "x.wav")]) == 0
    assert main(["audio", str(recording), "--out", str(tmp_path / "x.wav")]) == 2  # exists: one line, kept
    assert b"already exists" in capsysbinary.readouterr().err
