"""Real-time tracking from audio alone (``aaute track``): audio blocks -> mel front end -> net -> causal smoother.

The audio arrives in blocks of one hop (0.1 s) from an :class:`AudioSource` (a recording of any layout the
project reads, played as fast as possible or at real time; a WAV file; raw PCM from a pipe). After each
block, the window of ``window_seconds`` ending at the block's last sample goes through the model's mel
recipe, the net gives a position, and :class:`~zoo.robust_smoothing.OnlineSmoother` (causal at ``lag`` 0,
fixed-lag otherwise) turns it into rows ``timestamp, x, y, z, std_x, std_y, std_z`` that the writers flush
one line at a time. ``batch`` > 1 runs the net on several ready windows at once (faster replays, later lines).

Front end. :class:`IncrementalMel` keeps the last window of samples and a store of power-mel frames keyed
by their first sample, so every STFT frame of the stream is computed once, whichever windows share it.
Each window's spectrogram is assembled from the store (plus its two zero-padded edge frames, which belong
to that window alone) and finished by :func:`datamodules.features.mel_map`, the offline recipe's own
normalisation and resizing, so the map equals :func:`datamodules.features.mel_features` on the same
samples (to float rounding, tested to 1e-5). How much is shared depends on the grid: frames of a window
starting at sample ``s`` start at ``s + j * hop - n_fft / 2``, so windows 0.1 s apart share frames only
when the hop divides the block. At 48 kHz with hop 1024 (the student's recipe) a 4800-sample block moves
the grid by 704 samples: a window shares frames only with the window 1.6 s (16 blocks, 75 hops) before
it, and each update computes 77 of its 94 frames. Where the hop divides the block (hop 1024 or 512 at
51.2 kHz) an update computes ``block / hop`` interior frames and its two edge frames.

Windows end exactly where the DataModule's do: a position at ``t0 + k * hop`` uses the samples
``[k * block - window, k * block)``, so the positions equal ``aaute predict`` on the recording's label
times followed by :func:`~zoo.robust_smoothing.smooth_online` (tested).

Bad input: a PCM byte count that is not a whole number of frames of ``channels`` x the sample size is
refused at the end of the stream (wrong ``--channels`` or ``--format``); float samples far beyond full
scale are refused (wrong ``--format``); a block holding NaN or infinite samples is skipped and reported,
and no position is made from a window containing it (the recording readers refuse such audio themselves);
a stream that stalls (``stall_timeout``), ends inside a block or is interrupted ends the run cleanly after
the smoother has emitted what it holds; audio shorter than one window is an error.
"""

from __future__ import annotations

import io
import json
import logging
import math
import os
import select
import sys
import time
from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch
from torch import nn

from datamodules.audio_export import PCM_FORMATS
from datamodules.errors import AauteError, ConfigError
from datamodules.features import MEL_RECIPES, MelRecipe, frame_power_mel, mel_frame_layout, mel_map, mel_recipe
from datamodules.formats.ros_messages import full_scale
from zoo.smoothing import SMOOTHED_COLUMNS, OnlineRow, OnlineSmoother

log = logging.getLogger(__name__)

HOP_SECONDS = 0.1  #: one position per 0.1 s, the 10 Hz of MMAUD's ground truth and the DataModule's labels
FLOAT_FULL_SCALE_LIMIT = 1e3  #: float samples are in [-1, 1]; values this large mean the bytes are not float32


class TrackingError(AauteError, ValueError):
    """Audio or a model that cannot be tracked as asked (the message names the source and what was expected)."""


# ============================================================================================ sources


class AudioSource(ABC):
    """A stream of multichannel audio read in blocks.

    Attributes:
        name: what to call the source in messages (a path or ``stdin``).
        sample_rate: Hz.
        channels: microphones.
        t0: time of sample 0 (s); positions are stamped ``t0 + stop / sample_rate``.
        mic_positions: channels x 3 (m), and ``mic_source`` says where they came from.
        leftover: samples of a last, incomplete block (dropped), set when the stream ends.
        stalled: whether the stream ended by stalling rather than by its end.
    """

    name: str
    sample_rate: float
    channels: int
    t0: float = 0.0
    mic_positions: np.ndarray
    mic_source: str = ""
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
    """

    def __init__(self, path: str | Path, realtime: bool = False, reader_options: dict[str, Any] | None = None):
        from datamodules.formats import open_recording

        self.name = str(path)
        recording = open_recording(path, **(reader_options or {}))
        if recording.audio is None:
            raise TrackingError(f"{path}: the recording holds no audio to track from")
        self.audio = recording.audio
        self.sample_rate = float(self.audio.sample_rate)
        self.channels = self.audio.num_channels
        self.t0 = float(self.audio.t0)
        self.mic_positions = np.asarray(self.audio.mic_positions, dtype=np.float64)
        self.mic_source = "the recording"
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


def read_mic_positions(path: str | Path, channels: int) -> np.ndarray:
    """Microphone positions from a text file: one ``x y z`` row (m) per channel, spaces or commas.

    Raises:
        TrackingError: the file does not hold ``channels`` rows of three numbers.
    """
    try:
        positions = np.loadtxt(path, delimiter=None if "," not in Path(path).read_text() else ",", ndmin=2)
    except ValueError as error:
        raise TrackingError(f"{path}: expected one 'x y z' row of numbers (m) per microphone ({error})") from None
    if positions.shape != (channels, 3):
        raise TrackingError(f"{path}: expected {channels} rows of x y z (one per channel), got an array of shape "
                            f"{positions.shape}")
    return positions


def default_mic_positions(channels: int, path: str | Path | None, source: str) -> tuple[np.ndarray, str]:
    """Positions from ``path``, else the simulator's default array of that many channels; and where they came from."""
    if path is not None:
        return read_mic_positions(path, channels), str(path)
    from datamodules.simulate.acoustics import AudioConfig
    from datamodules.simulate.microphones import mic_geometry

    name = AudioConfig().microphones
    positions = mic_geometry(name)
    if positions.shape[0] != channels:
        raise TrackingError(f"{source}: {channels} channels, but the simulator's default array {name!r} has "
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
            raise TrackingError(f"{path}: not a readable WAV file ({error})") from None
        self.data = data if data.ndim == 2 else data[:, None]
        self.sample_rate = float(rate)
        self.channels = int(self.data.shape[1])
        kind = self.data.dtype
        self.scale = full_scale(kind)
        if kind.kind not in "fi":
            raise TrackingError(f"{path}: {kind} WAV samples; expected signed integer or float PCM")
        self.t0 = float(t0)
        self.mic_positions, self.mic_source = default_mic_positions(self.channels, mic_positions, self.name)

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
                    raise TrackingError(
                        f"{self.name}: samples of magnitude {float(np.abs(finite).max()):.3g} in what should be "
                        f"float32 audio in [-1, 1]; is the stream really {self.format} (--format)?")
            yield np.ascontiguousarray((values.astype(np.float64) / self.scale).T, dtype=np.float32)

    def _end(self, partial_bytes: int) -> None:
        """Check the byte count at the end of the stream (not at a stall) and record the dropped partial block."""
        if self.bytes_read % self.frame_bytes and not self.stalled:
            raise TrackingError(
                f"{self.name}: {self.bytes_read} bytes is not a whole number of {self.channels}-channel "
                f"{self.format} frames ({self.frame_bytes} bytes each); check --channels and --format")
        self.leftover = partial_bytes // self.frame_bytes


# ============================================================================================ front end


class IncrementalMel:
    """Mel maps of consecutive windows of one stream, each STFT frame computed once (see the module docstring).

    Args:
        recipe: a mel recipe of :mod:`datamodules.features`.
        sample_rate: Hz.
        channels: microphones.
        window_samples: samples per window.
    """

    def __init__(self, recipe: MelRecipe, sample_rate: float, channels: int, window_samples: int):
        self.recipe, self.sample_rate, self.channels = recipe, float(sample_rate), int(channels)
        self.window = int(window_samples)
        self.frames, self.n_fft, self.hop = mel_frame_layout(recipe, sample_rate, self.window)
        self.half = self.n_fft // 2
        if self.window < self.n_fft:
            raise TrackingError(f"recipe {recipe.name!r}: a {self.window}-sample window is shorter than one "
                                f"{self.n_fft}-sample frame")
        offsets = np.arange(self.frames) * self.hop - self.half  #: first sample of each frame, window-relative
        self.inner = (offsets >= 0) & (offsets + self.n_fft <= self.window)
        self.offsets = offsets
        self._buffer = np.zeros((self.channels, 2 * (self.window + self.n_fft)), dtype=np.float32)
        self._filled = 0  #: valid samples in the buffer
        self.end = 0  #: samples received so far (absolute index of the next one)
        #: first sample of a frame -> (C x n_mels x frames power mel computed with it, its column there)
        self._store: dict[int, tuple[torch.Tensor, int]] = {}
        self.computed = 0  #: frames computed (for the report)
        self.used = 0  #: frames used by the windows made

    def push(self, block: np.ndarray) -> None:
        """Append a block (channels x n) to the stream."""
        n = block.shape[1]
        keep = self.window + self.n_fft
        if self._filled + n > self._buffer.shape[1]:
            retained = min(self._filled, keep)
            self._buffer[:, :retained] = self._buffer[:, self._filled - retained:self._filled]
            self._filled = retained
            if n > self._buffer.shape[1] - retained:
                self._buffer = np.concatenate([self._buffer[:, :retained], np.zeros((self.channels, n + keep),
                                                                                   np.float32)], axis=1)
        self._buffer[:, self._filled:self._filled + n] = block
        self._filled += n
        self.end += n

    def _samples(self, start: int, stop: int) -> np.ndarray:
        """Absolute samples ``start:stop`` from the buffer."""
        first = self.end - self._filled
        if start < first or stop > self.end:
            raise IndexError(f"samples {start}:{stop} are not buffered ({first}:{self.end})")
        return self._buffer[:, start - first:stop - first]

    def features(self, stop: int | None = None) -> torch.Tensor:
        """The recipe's map (C x H x W) of the window ending just before absolute sample ``stop`` (default: now)."""
        stop = self.end if stop is None else int(stop)
        start = stop - self.window
        starts = start + self.offsets
        missing = [j for j in np.flatnonzero(self.inner) if int(starts[j]) not in self._store]
        for run in _runs(missing):
            first, last = int(starts[run[0]]), int(starts[run[-1]])
            segment = torch.from_numpy(self._samples(first, last + self.n_fft))
            frames = segment.unfold(-1, self.n_fft, self.hop)  # C x len(run) x n_fft
            block = frame_power_mel(frames, self.recipe, self.sample_rate)  # C x n_mels x len(run)
            for column, j in enumerate(run):
                self._store[int(starts[j])] = (block, column)
            self.computed += len(run)
        edges = np.flatnonzero(~self.inner)
        window = self._samples(start, stop)
        padded = np.zeros((self.channels, len(edges), self.n_fft), dtype=np.float32)
        for i, j in enumerate(edges):
            lo, hi = int(self.offsets[j]), int(self.offsets[j]) + self.n_fft
            padded[:, i, max(0, -lo):self.n_fft - max(0, hi - self.window)] = window[:, max(lo, 0):min(hi, self.window)]
        edge_block = frame_power_mel(torch.from_numpy(padded), self.recipe, self.sample_rate)
        edge_column = {int(j): i for i, j in enumerate(edges)}
        self.computed += len(edges)
        # consecutive frames that were computed together are copied as one slice
        pieces: list[list[Any]] = []  # [block, first column, last column]
        for j in range(self.frames):
            block, column = (edge_block, edge_column[j]) if j in edge_column else self._store[int(starts[j])]
            if pieces and pieces[-1][0] is block and pieces[-1][2] == column - 1:
                pieces[-1][2] = column
            else:
                pieces.append([block, column, column])
        spectrogram = torch.cat([block[:, :, a:b + 1] for block, a, b in pieces], dim=-1)
        self.used += self.frames
        for key in [k for k in self._store if k < start + self.hop - self.half]:
            del self._store[key]  # later windows start later: frames before this one's second are done
        return mel_map(spectrogram, self.recipe)


def _silence_stdout() -> None:
    """Point stdout at /dev/null after its reader closed it, so that exiting does not fail on a flush."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, io.UnsupportedOperation):
        pass
    finally:
        os.close(devnull)


def _runs(indices: Sequence[int]) -> list[list[int]]:
    """Consecutive runs of sorted integers: [1, 2, 3, 7, 8] -> [[1, 2, 3], [7, 8]]."""
    runs: list[list[int]] = []
    for index in indices:
        if runs and index == runs[-1][-1] + 1:
            runs[-1].append(int(index))
        else:
            runs.append([int(index)])
    return runs


# ============================================================================================ model


@dataclass
class TrackingModel:
    """A net ready for streaming: the net, its mel recipe, the window it was trained on and where it came from."""

    net: nn.Module
    name: str
    recipe: MelRecipe
    window_seconds: float
    source: str


def _data_settings(path: Path) -> dict[str, Any]:
    """The DataModule hyperparameters a Lightning checkpoint stored (empty for other files)."""
    from zoo.checkpoints import read_file

    try:
        stored = read_file(path)
    except AauteError:
        return {}
    settings = stored.get("datamodule_hyper_parameters") if isinstance(stored, dict) else None
    return dict(settings) if isinstance(settings, dict) else {}


def load_tracking_model(ckpt_path: str | Path | None = None, weights: str | Path | None = None,
                        recipe: str | None = None, window_seconds: float | None = None,
                        offline: bool | None = None) -> TrackingModel:
    """The net of a project checkpoint (``ckpt_path``) or of named / file weights (``weights``), in eval mode.

    The mel recipe and window come from ``recipe`` / ``window_seconds`` if given, else from the
    checkpoint's data settings, else from the net's declared inputs and the DataModule's 2 s window.

    Raises:
        TrackingError: neither or both sources given, or a model whose inputs are not one mel map (phase
            and image recipes are not streamed), naming the model and the recipes supported.
    """
    from zoo.weights import build_net, load_task, resolve_weights

    if (ckpt_path is None) == (weights is None):
        raise ConfigError("aaute track needs exactly one of --ckpt_path FILE and --weights NAME_OR_PATH")
    data: dict[str, Any] = {}
    if ckpt_path is not None:
        path = Path(ckpt_path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such checkpoint")
        task = load_task(path)
        net, name, source = task.net, str(task.hparams.net), str(path)
        data = _data_settings(path)
    else:
        contents, entry = resolve_weights(None, weights, offline)
        net = build_net(contents, None, None, entry)
        name, source = net.model_name, str(contents.path)
        data = {"inputs": dict(contents.inputs or (entry.inputs if entry else {}))}
    inputs = dict(getattr(net, "inputs", {}))
    supported = ", ".join(sorted(MEL_RECIPES))
    if set(inputs) != {"audio_mel"}:
        raise TrackingError(f"model {name!r} reads {inputs}; aaute track streams models of one mel input "
                            f"(audio_mel recipes {supported}), not phase or image recipes")
    chosen = recipe or (data.get("inputs") or {}).get("audio_mel") or inputs["audio_mel"]
    try:
        mel = mel_recipe(chosen)
    except ValueError as error:
        raise TrackingError(f"model {name!r}: {error}") from None
    if mel.output_shape != mel_recipe(inputs["audio_mel"]).output_shape:
        raise TrackingError(f"model {name!r} reads {inputs['audio_mel']!r} maps of shape "
                            f"{mel_recipe(inputs['audio_mel']).output_shape}; recipe {chosen!r} makes "
                            f"{mel.output_shape}")
    if data.get("faithful_window_order"):
        log.warning("%s was trained on the original newest-first chunk order; aaute track uses the continuous "
                    "causal window", source)
    seconds = float(window_seconds if window_seconds is not None else data.get("window_seconds", 2.0))
    return TrackingModel(net.eval(), name, mel, seconds, source)


# ============================================================================================ writers


class CsvWriter:
    """Rows as CSV lines, flushed one by one; a file is written to its temporary sibling and renamed at the end."""

    def __init__(self, stream: IO[str]):
        self.stream = stream
        stream.write(",".join(SMOOTHED_COLUMNS) + "\n")
        stream.flush()

    def write(self, row: OnlineRow) -> None:
        values = (*row.mean, *row.std)
        self.stream.write(f"{row.timestamp:.6f}," + ",".join(f"{v:.6f}" for v in values) + "\n")
        self.stream.flush()


class McapTrackWriter:
    """Rows as JSON messages on one MCAP topic (schema ``aaute/TrackPoint``), each written out at once."""

    SCHEMA = {"type": "object", "title": "aaute/TrackPoint",
              "properties": {name: {"type": "number"} for name in SMOOTHED_COLUMNS}}

    def __init__(self, stream: IO[bytes], topic: str):
        from mcap.writer import Writer

        self.stream = stream
        self.writer = Writer(stream, use_chunking=False)
        self.writer.start(profile="", library="aaute track")
        schema = self.writer.register_schema("aaute/TrackPoint", "jsonschema", json.dumps(self.SCHEMA).encode())
        self.channel = self.writer.register_channel(topic, "json", schema)
        self.sequence = 0

    def write(self, row: OnlineRow) -> None:
        from datamodules.recording import seconds_to_ns

        values = dict(zip(SMOOTHED_COLUMNS, (row.timestamp, *map(float, row.mean), *map(float, row.std)), strict=True))
        stamp = int(seconds_to_ns(row.timestamp))
        self.writer.add_message(self.channel, stamp, json.dumps(values).encode(), stamp, self.sequence)
        self.sequence += 1
        self.stream.flush()

    def finish(self) -> None:
        self.writer.finish()


# ============================================================================================ tracker


@dataclass
class TrackingReport:
    """What a run did: updates, skipped windows, latencies (s), audio and wall seconds, threads."""

    updates: int = 0
    rows: int = 0
    skipped_windows: int = 0
    latencies: list[float] = field(default_factory=list)
    compute_seconds: float = 0.0  #: wall seconds from block arrivals to their lines
    busy_until: float = 0.0  #: when the last line was written (perf_counter), so overlapping batches count once
    cpu_seconds: float = 0.0  #: CPU seconds of this process over the run (reading, features, net, smoother, writing)
    audio_seconds: float = 0.0
    wall_seconds: float = 0.0
    threads: int = 1
    frames_computed: int = 0
    frames_used: int = 0
    ended: str = "end of stream"

    def summary(self) -> str:
        lat = np.array(self.latencies) * 1e3
        median, p95 = (float(np.median(lat)), float(np.percentile(lat, 95))) if lat.size else (math.nan, math.nan)
        wall = self.audio_seconds / self.wall_seconds if self.wall_seconds > 0 else math.nan
        busy = self.audio_seconds / self.compute_seconds if self.compute_seconds > 0 else math.nan
        cpu = self.audio_seconds / self.cpu_seconds if self.cpu_seconds > 0 else math.nan
        share = self.frames_computed / self.frames_used if self.frames_used else math.nan
        return (f"{self.updates} updates, {self.rows} rows, {self.skipped_windows} windows skipped; latency per "
                f"update median {median:.2f} ms, p95 {p95:.2f} ms (block arrival to line written); "
                f"{self.audio_seconds:.1f} s of audio in {self.wall_seconds:.2f} s: {wall:.1f}x real time "
                f"({busy:.1f}x counting compute only, {cpu:.1f}x in CPU time); STFT frames computed {share:.0%} of "
                f"those used; "
                f"{self.threads} torch thread(s); ended by {self.ended}")


class Tracker:
    """Streams a source through a model and the online smoother to writers (see the module docstring).

    Args:
        model: the net and its recipe (:func:`load_tracking_model`).
        source: the audio.
        writers: objects with ``write(row)``.
        lag: seconds of future each smoothed position may use (0: causal).
        preset: the robust smoother's preset.
        hop_seconds: seconds between positions.
        batch: windows per net call. 1 (the default) gives each block its line as soon as it is computed;
            more raise the throughput of a replay (one matrix product instead of several) and delay the
            earlier windows of each batch by the later ones' blocks.
    """

    def __init__(self, model: TrackingModel, source: AudioSource, writers: Sequence[Any], lag: float = 0.0,
                 preset: str = "robust", hop_seconds: float = HOP_SECONDS, batch: int = 1):
        self.model, self.source, self.writers = model, source, list(writers)
        channels = getattr(model.net, "in_channels", source.channels)
        if channels != source.channels:
            raise TrackingError(f"{source.name}: {source.channels} audio channels, but model {model.name!r} "
                                f"takes {channels} microphones")
        block = hop_seconds * source.sample_rate
        if abs(block - round(block)) > 1e-6:
            raise TrackingError(f"{source.name}: a {hop_seconds:g} s hop is {block:g} samples at "
                                f"{source.sample_rate:g} Hz; expected a whole number")
        self.block = int(round(block))
        if batch < 1:
            raise ConfigError(f"--batch must be at least 1, got {batch}")
        self.batch = int(batch)
        self.window = int(round(model.window_seconds * source.sample_rate))
        self.front = IncrementalMel(model.recipe, source.sample_rate, source.channels, self.window)
        self.smoother = OnlineSmoother(preset, lag=lag)
        self.bad_until = -1  #: windows ending at or before this absolute sample contain a non-finite block

    def _timestamp(self, stop: int) -> float:
        return self.source.t0 + stop / self.source.sample_rate

    def _emit(self, rows: list[OnlineRow], report: TrackingReport) -> None:
        for row in rows:
            for writer in self.writers:
                writer.write(row)
        report.rows += len(rows)

    def _positions(self, pending: list[tuple[int, torch.Tensor, float]], report: TrackingReport) -> None:
        """Run the net on the pending windows (one batch), smooth and write their rows in time order.

        Raises:
            BrokenPipeError: stdout was closed by its reader.
        """
        if not pending:
            return
        with torch.inference_mode():
            batch = torch.stack([features for _, features, _ in pending])
            positions = self.model.net({"audio_mel": batch})["position"].double().numpy()
        report.updates += len(pending)
        for (stop, _, arrival), position in zip(pending, positions, strict=True):
            if not np.isfinite(position).all():
                log.warning("%s: model %s gave a non-finite position at %.3f s: skipped", self.source.name,
                            self.model.name, self._timestamp(stop))
                report.skipped_windows += 1
                continue
            self._emit(self.smoother.update(self._timestamp(stop), position), report)
            done = time.perf_counter()
            report.latencies.append(done - arrival)
            report.compute_seconds += done - max(arrival, report.busy_until)
            report.busy_until = done
        pending.clear()

    def run(self) -> TrackingReport:
        """Track until the source ends (or stalls, or is interrupted); returns the report."""
        report = TrackingReport(threads=torch.get_num_threads())
        wall_start, cpu_start = time.perf_counter(), time.process_time()
        blocks = self.source.blocks(self.block)
        pending: list[tuple[int, torch.Tensor, float]] = []  #: windows waiting for the net: stop, map, arrival
        try:
            while True:
                try:
                    block = next(blocks)
                except StopIteration:
                    break
                arrival = time.perf_counter()
                stop = self.front.end + block.shape[1]
                if not np.isfinite(block).all():
                    t = self._timestamp(stop - block.shape[1])
                    log.warning("%s: the block at %.3f-%.3f s holds %d NaN or infinite samples: skipped; no "
                                "position from windows that contain it (until %.3f s)", self.source.name, t,
                                self._timestamp(stop), int((~np.isfinite(block)).sum()),
                                self._timestamp(stop + self.window))
                    self.bad_until = stop + self.window - 1  # every window ending before stop + window holds it
                self.front.push(block)
                if stop < self.window:
                    continue
                if stop <= self.bad_until:
                    report.skipped_windows += 1
                    continue
                pending.append((stop, self.front.features(), arrival))
                if len(pending) >= self.batch:
                    self._positions(pending, report)
            self._positions(pending, report)
        except KeyboardInterrupt:  # the usual way to stop a live stream: end cleanly with what is known
            report.ended = "an interrupt"
        except BrokenPipeError:  # the reader of stdout went away: nobody left to track for
            report.ended = "the output being closed"
            _silence_stdout()
        if report.ended != "the output being closed":
            try:
                self._emit(self.smoother.flush(), report)
            except BrokenPipeError:
                report.ended = "the output being closed"
                _silence_stdout()
        report.wall_seconds = time.perf_counter() - wall_start
        report.cpu_seconds = time.process_time() - cpu_start
        report.audio_seconds = self.front.end / self.source.sample_rate
        report.frames_computed, report.frames_used = self.front.computed, self.front.used
        if self.source.stalled:
            report.ended = f"a stall of {getattr(self.source, 'stall_timeout', 0):g} s"
        if self.source.leftover:
            log.warning("%s: the stream ended %.3f s into a block; those %d samples are dropped (a position needs "
                        "a whole %g s block)", self.source.name, self.source.leftover / self.source.sample_rate,
                        self.source.leftover, self.block / self.source.sample_rate)
        if report.updates == 0 and report.skipped_windows == 0:
            raise TrackingError(f"{self.source.name}: {report.audio_seconds:.2f} s of audio, fewer than the "
                                f"{self.window / self.source.sample_rate:g} s window model {self.model.name!r} needs "
                                f"for one position; nothing to track")
        return report


# ============================================================================================ command


def open_source(audio: str, args: Any) -> AudioSource:
    """The source ``audio`` names: ``-`` (raw PCM on stdin), a ``.wav`` file, or a recording."""
    if audio == "-":
        missing = [flag for flag, value in (("--channels", args.channels), ("--rate", args.rate)) if value is None]
        if missing:
            raise ConfigError(f"raw PCM on stdin needs {' and '.join(missing)} (and --format, default s16le)")
        return PcmSource(sys.stdin.buffer, args.channels, args.rate, args.format, args.mic_positions, args.t0,
                         args.stall_timeout)
    path = Path(audio)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such audio file or recording")
    if path.suffix.lower() == ".wav":
        return WavSource(path, args.mic_positions, args.t0)
    if args.mic_positions is not None:
        log.info("%s: the recording's own microphone positions are used (--mic-positions ignored)", path)
    return RecordingSource(path, realtime=args.realtime)


def run_track(args: Any) -> int:
    """``aaute track`` (its arguments: ``zoo.cli``): track, write the rows, print the report to stderr."""
    from datamodules.atomic import atomic_write
    from zoo.cli import check_output

    torch.set_num_threads(max(1, int(args.threads)))
    model = load_tracking_model(args.ckpt_path, args.weights, args.recipe, args.window_seconds)
    source = open_source(args.audio, args)
    log.info("tracking %s (%d channels, %g Hz; microphones from %s) with %s from %s: recipe %s, %g s windows, "
             "lag %g s", source.name, source.channels, source.sample_rate, source.mic_source, model.name,
             model.source, model.recipe.name, model.window_seconds, args.lag)
    source_path = Path(args.audio) if args.audio != "-" else Path(os.devnull)
    for out in (args.out, args.mcap_out):
        if out is not None:
            check_output(source_path, Path(out), args.overwrite)
    with ExitStack() as stack:
        writers: list[Any] = []
        if args.out is None and args.mcap_out is None or args.stdout:
            writers.append(CsvWriter(sys.stdout))
        if args.out is not None:
            tmp = stack.enter_context(atomic_write(args.out))
            writers.append(CsvWriter(stack.enter_context(open(tmp, "w"))))
        mcap_writer = None
        if args.mcap_out is not None:
            tmp = stack.enter_context(atomic_write(args.mcap_out))
            mcap_writer = McapTrackWriter(stack.enter_context(open(tmp, "wb")), args.topic)
            writers.append(mcap_writer)
        report = Tracker(model, source, writers, lag=args.lag, preset=args.preset, batch=args.batch).run()
        if mcap_writer is not None:
            mcap_writer.finish()
    sys.stderr.write(f"aaute track: {report.summary()}\n")
    return 0
