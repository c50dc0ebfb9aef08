"""Live and recorded multichannel audio as a stream of blocks: the sources ``aaute track`` reads.

An :class:`AudioSource` delivers blocks of one hop (channels x samples, float32 at full scale 1), in
order, until the stream ends: :class:`RecordingSource` plays the audio of a recording of any layout
the project reads (as fast as possible or at real time), :class:`WavSource` a WAV file and
:class:`PcmSource` raw interleaved PCM from a pipe, a socket or stdin (the byte stream
:mod:`datamodules.audio_export` writes). Each source also says where its microphones are: the
recording's own positions, a text file of one ``x y z`` row per channel, or the simulator's default
array, and whether they are known (``mic_positions_known``: a default array or a recording that says
its positions are unknown is not; the phase models refuse such a source).

Bad input: a PCM byte count that is not a whole number of frames of ``channels`` x the sample size is
refused at the end of the stream (wrong ``--channels`` or ``--format``); float samples far beyond full
scale are refused (wrong ``--format``); a stream that stalls (``stall_timeout``) or ends inside a block
ends cleanly, and the source records the stall and the samples of the dropped partial block.
"""

from __future__ import annotations

import io
import math
import os
import select
import time
from abc import ABC, abstractmethod
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from datamodules.audio_export import PCM_FORMATS
from datamodules.errors import ConfigError
from datamodules.formats.positions import read_mic_positions
from datamodules.formats.ros_messages import full_scale
from datamodules.recording import RecordingError

FLOAT_FULL_SCALE_LIMIT = 1e3  #: float samples are in [-1, 1]; values this large mean the bytes are not float32


class StreamError(RecordingError):
    """Audio that cannot be streamed as asked (the message names the source and what was expected)."""


class AudioSource(ABC):
    """A stream of multichannel audio read in blocks.

    Attributes:
        name: what to call the source in messages (a path or ``stdin``).
        sample_rate: Hz.
        channels: microphones.
        t0: time of sample 0 (s); positions are stamped ``t0 + stop / sample_rate``.
        mic_positions: channels x 3 (m), and ``mic_source`` says where they came from.
        mic_positions_known: whether they were measured (a file, or a recording that knows them) rather than
            a default standing in for unknown positions.
        nodes_share_clock: whether the audio nodes sample on one clock (a recording on separate clocks says
            not), and ``alignment_uncertainty_s`` how well their stamps align them (None: unknown).
        leftover: samples of a last, incomplete block (dropped), set when the stream ends.
        stalled: whether the stream ended by stalling rather than by its end.
    """

    name: str
    sample_rate: float
    channels: int
    t0: float = 0.0
    mic_positions: np.ndarray
    mic_source: str = ""
    mic_positions_known: bool = True
    nodes_share_clock: bool = True
    alignment_uncertainty_s: float | None = None
    leftover: int = 0
    stalled: bool = False

    @abstractmethod
    def blocks(self, size: int) -> Iterator[np.ndarray]:
        """Blocks of ``size`` samples (float32, channels x size), in order, until the stream ends."""


class RecordingSource(AudioSource):
    """The audio of a recording (MCAP or any layout :func:`datamodules.formats.open_recording` reads).

    Args:
        path: the recording.
        realtime: deliver each block when its last sample would arrive from a live array.
        reader_options: options of the non-MCAP readers (sample rate of the derived layout, ...).
        mic_positions: a positions file used when the recording says its own are unknown.
    """

    def __init__(self, path: str | Path, realtime: bool = False, reader_options: dict[str, Any] | None = None,
                 mic_positions: str | Path | None = None):
        from datamodules.formats import open_recording

        self.name = str(path)
        recording = open_recording(path, **(reader_options or {}))
        if recording.audio is None:
            raise StreamError(f"{path}: the recording holds no audio to track from")
        self.audio = recording.audio
        self.sample_rate = float(self.audio.sample_rate)
        self.channels = self.audio.num_channels
        self.t0 = float(self.audio.t0)
        self.mic_positions = np.asarray(self.audio.mic_positions, dtype=np.float64)
        self.mic_source = "the recording"
        self.mic_positions_known = bool(recording.meta.get("mic_positions_known", True))
        self.nodes_share_clock = recording.meta.get("nodes_share_clock", True) is not False
        self.alignment_uncertainty_s = recording.meta.get("audio_alignment_uncertainty_s")
        if not self.mic_positions_known and mic_positions is not None:
            self.mic_positions = read_mic_positions(mic_positions, self.channels)
            self.mic_source, self.mic_positions_known = str(mic_positions), True
        self.realtime = realtime

    def blocks(self, size: int) -> Iterator[np.ndarray]:
        start_wall = time.perf_counter()
        total = self.audio.num_samples
        for start in range(0, total - size + 1, size):
            if self.realtime:
                delay = start_wall + (start + size) / self.sample_rate - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
            yield self.audio.read(start, start + size)
        self.leftover = total % size


def default_mic_positions(channels: int, path: str | Path | None, source: str) -> tuple[np.ndarray, str]:
    """Positions from ``path``, else the simulator's default array of that many channels; and where they came from."""
    if path is not None:
        return read_mic_positions(path, channels), str(path)
    from datamodules.simulate.acoustics import AudioConfig
    from datamodules.simulate.microphones import mic_geometry

    name = AudioConfig().microphones
    positions = mic_geometry(name)
    if positions.shape[0] != channels:
        raise StreamError(f"{source}: {channels} channels, but the simulator's default array {name!r} has "
                          f"{positions.shape[0]} microphones; give --mic-positions FILE")
    return positions, f"the simulator's default array {name!r}"


class WavSource(AudioSource):
    """A WAV file (integer PCM scaled by full scale, or float), memory-mapped and read block by block."""

    def __init__(self, path: str | Path, mic_positions: str | Path | None = None, t0: float = 0.0):
        from scipy.io import wavfile

        self.name = str(path)
        try:
            rate, data = wavfile.read(path, mmap=True)
        except (ValueError, OSError) as error:
            if isinstance(error, FileNotFoundError):
                raise
            raise StreamError(f"{path}: not a readable WAV file ({error})") from None
        self.data = data if data.ndim == 2 else data[:, None]
        self.sample_rate = float(rate)
        self.channels = int(self.data.shape[1])
        kind = self.data.dtype
        self.scale = full_scale(kind)
        if kind.kind not in "fi":
            raise StreamError(f"{path}: {kind} WAV samples; expected signed integer or float PCM")
        self.t0 = float(t0)
        self.mic_positions, self.mic_source = default_mic_positions(self.channels, mic_positions, self.name)
        self.mic_positions_known = mic_positions is not None

    def blocks(self, size: int) -> Iterator[np.ndarray]:
        total = self.data.shape[0]
        for start in range(0, total - size + 1, size):
            block = np.asarray(self.data[start:start + size], dtype=np.float64) / self.scale
            yield np.ascontiguousarray(block.T, dtype=np.float32)
        self.leftover = total % size


class PcmSource(AudioSource):
    """Raw interleaved PCM from a binary stream (stdin, a pipe, a socket file).

    Args:
        stream: binary file object.
        channels, sample_rate, sample_format: as given (``s16le``, ``s32le`` or ``f32le``).
        stall_timeout: seconds without data after which the stream counts as ended (pipes and sockets).
    """

    def __init__(self, stream: IO[bytes], channels: int, sample_rate: float, sample_format: str,
                 mic_positions: str | Path | None = None, t0: float = 0.0, stall_timeout: float = 5.0,
                 name: str = "stdin"):
        if sample_format not in PCM_FORMATS:
            raise ConfigError(f"--format must be one of {', '.join(PCM_FORMATS)}, got {sample_format!r}")
        if channels < 1 or not (math.isfinite(sample_rate) and sample_rate > 0):
            raise ConfigError(f"{name}: raw PCM needs --channels >= 1 and a positive --rate, got {channels} and "
                              f"{sample_rate:g}")
        self.name, self.stream, self.channels, self.sample_rate = name, stream, int(channels), float(sample_rate)
        self.format = sample_format
        self.dtype = PCM_FORMATS[sample_format]
        self.scale = full_scale(self.dtype)
        self.frame_bytes = self.channels * self.dtype.itemsize
        self.t0 = float(t0)
        self.stall_timeout = float(stall_timeout)
        self.mic_positions, self.mic_source = default_mic_positions(self.channels, mic_positions, name)
        self.mic_positions_known = mic_positions is not None
        self.bytes_read = 0
        try:
            self._fd: int | None = stream.fileno()
        except (AttributeError, OSError, io.UnsupportedOperation):
            self._fd = None

    def _read(self, count: int) -> bytes:
        """Up to ``count`` bytes: fewer only at the end of the stream or after a stall."""
        parts, got = [], 0
        while got < count:
            if self._fd is not None:
                ready, _, _ = select.select([self._fd], [], [], self.stall_timeout)
                if not ready:
                    self.stalled = True
                    break
                part = os.read(self._fd, count - got)
            else:
                part = self.stream.read(count - got)
            if not part:
                break
            parts.append(part)
            got += len(part)
        return b"".join(parts)

    def blocks(self, size: int) -> Iterator[np.ndarray]:
        want = size * self.frame_bytes
        while True:
            data = self._read(want)
            self.bytes_read += len(data)
            if len(data) < want:
                self._end(len(data))
                return
            values = np.frombuffer(data, dtype=self.dtype).reshape(size, self.channels)
            if self.dtype.kind == "f":
                finite = values[np.isfinite(values)]
                if finite.size and float(np.abs(finite).max()) > FLOAT_FULL_SCALE_LIMIT:
                    raise StreamError(
                        f"{self.name}: samples of magnitude {float(np.abs(finite).max()):.3g} in what should be "
                        f"float32 audio in [-1, 1]; is the stream really {self.format} (--format)?")
            yield np.ascontiguousarray((values.astype(np.float64) / self.scale).T, dtype=np.float32)

    def _end(self, partial_bytes: int) -> None:
        """Check the byte count at the end of the stream (not at a stall) and record the dropped partial block."""
        if self.bytes_read % self.frame_bytes and not self.stalled:
            raise StreamError(
                f"{self.name}: {self.bytes_read} bytes is not a whole number of {self.channels}-channel "
                f"{self.format} frames ({self.frame_bytes} bytes each); check --channels and --format")
        self.leftover = partial_bytes // self.frame_bytes

