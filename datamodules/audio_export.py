"""A recording's microphone audio as a WAV file or raw interleaved PCM (``aaute audio``).

For listening, for other tools, and to feed ``aaute track --audio -`` the byte stream a sound card
gives. The audio is read one second at a time, so an hour-long recording never sits in memory. WAV
files are written atomically with the standard library's ``wave`` module (integer PCM: ``s16le``
or ``s32le``); raw PCM goes to a binary stream in any of ``s16le``, ``s32le``, ``f32le``. Integer
samples are the float samples times full scale, rounded and clipped, so audio stored as S16LE
round-trips exactly through ``s16le``.
"""

from __future__ import annotations

import wave
from pathlib import Path
from typing import BinaryIO

import numpy as np

from datamodules.atomic import atomic_write
from datamodules.errors import ConfigError
from datamodules.formats.ros_messages import SAMPLE_FORMATS, full_scale
from datamodules.recording import AudioStream

#: raw PCM sample formats as command lines spell them (``s16le``, ...) -> numpy dtypes of one sample
PCM_FORMATS = {name.lower(): np.dtype(dtype) for name, dtype in SAMPLE_FORMATS.items()}
WAV_FORMATS = ("s16le", "s32le")
CHUNK_SECONDS = 1.0


def encode(samples: np.ndarray, fmt: str) -> bytes:
    """Float samples (channels x n, full scale 1) -> interleaved little-endian bytes of ``fmt``."""
    dtype = PCM_FORMATS[fmt]
    frames = samples.T.astype(np.float64)
    if dtype.kind != "f":
        scale = full_scale(dtype)
        frames = np.clip(np.rint(frames * scale), -scale, scale - 1)
    return np.ascontiguousarray(frames, dtype=dtype).tobytes()


def _chunks(audio: AudioStream, fmt: str):
    step = max(1, int(round(CHUNK_SECONDS * audio.sample_rate)))
    for start in range(0, audio.num_samples, step):
        yield encode(audio.read(start, min(start + step, audio.num_samples)), fmt)


def _check_format(fmt: str, allowed: tuple[str, ...], what: str) -> None:
    if fmt not in allowed:
        raise ConfigError(f"{what}: sample format {fmt!r} is not supported; expected one of {', '.join(allowed)}")


def write_pcm(audio: AudioStream, stream: BinaryIO, fmt: str = "s16le") -> int:
    """Write the audio as raw interleaved PCM to ``stream``; returns the bytes written.

    A reader that closes the pipe early (``aaute track`` interrupted) ends the writing quietly.
    """
    _check_format(fmt, tuple(PCM_FORMATS), "raw PCM")
    written = 0
    try:
        for data in _chunks(audio, fmt):
            stream.write(data)
            written += len(data)
        stream.flush()
    except BrokenPipeError:
        pass
    return written


def write_wav(audio: AudioStream, path: str | Path, fmt: str = "s16le", overwrite: bool = False) -> Path:
    """Write the audio as a WAV file (integer PCM), atomically; an existing file is kept unless ``overwrite``."""
    path = Path(path)
    _check_format(fmt, WAV_FORMATS, str(path))
    rate = audio.sample_rate
    if rate != round(rate):
        raise ConfigError(f"{path}: WAV needs a whole-number sample rate, the recording has {rate} Hz")
    with atomic_write(path, overwrite=overwrite) as tmp, wave.open(str(tmp), "wb") as out:
        out.setnchannels(audio.num_channels)
        out.setsampwidth(PCM_FORMATS[fmt].itemsize)
        out.setframerate(int(round(rate)))
        for data in _chunks(audio, fmt):
            out.writeframesraw(data)
    return path
