"""Real-time tracking from audio alone, the engine of ``aaute track``: blocks -> mel front end -> net -> smoother.

The audio arrives in blocks of one hop (0.1 s) from an :class:`~datamodules.streams.AudioSource` (a
recording of any layout the project reads, played as fast as possible or at real time; a WAV file; raw
PCM from a pipe). After each block, the window of ``window_seconds`` ending at the block's last sample
goes through the model's mel recipe (:class:`~datamodules.features.IncrementalMel`, each STFT frame of
the stream computed once), the net gives a position, and :class:`~zoo.smoothing.OnlineSmoother`
(causal at ``lag`` 0, fixed-lag otherwise) turns it into rows ``timestamp, x, y, z, std_x, std_y, std_z``
followed by the net's own position ``raw_x, raw_y, raw_z``, that the writers flush one line at a time.
``batch`` > 1 runs the net on several ready windows at once (faster replays, later lines).

Windows end exactly where the DataModule's do: a position at ``t0 + k * hop`` uses the samples
``[k * block - window, k * block)``, so the positions equal ``aaute predict`` on the recording's label
times followed by :func:`~zoo.smoothing.smooth_online` (tested).

Bad input: a block holding NaN or infinite samples is skipped and reported, and no position is made
from a window containing it (the recording readers refuse such audio themselves); a stream that stalls,
ends inside a block or is interrupted ends the run cleanly after the smoother has emitted what it holds;
audio shorter than one window is an error. The sources refuse bad bytes themselves
(:mod:`datamodules.streams`). The command (its arguments, the source they name, the output files) is
:mod:`zoo.cli.track`.
"""

from __future__ import annotations

import io
import json
import logging
import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch
from torch import nn

from datamodules.errors import AauteError, ConfigError
from datamodules.features import MEL_RECIPES, IncrementalMel, MelRecipe, mel_recipe
from datamodules.streams import AudioSource
from zoo.smoothing import SMOOTHED_COLUMNS, OnlineRow, OnlineSmoother

log = logging.getLogger(__name__)

HOP_SECONDS = 0.1  #: one position per 0.1 s, the 10 Hz of MMAUD's ground truth and the DataModule's labels
#: a row: the smoothed position and its std, then the net's position (what ``aaute smooth`` reads back)
TRACK_ROW_COLUMNS = (*SMOOTHED_COLUMNS, "raw_x", "raw_y", "raw_z")


class TrackingError(AauteError, ValueError):
    """Audio or a model that cannot be tracked as asked (the message names the source and what was expected)."""


# ============================================================================================ model


@dataclass
class TrackingModel:
    """A net ready for streaming: the net, its mel recipe, the window it was trained on and where it came from."""

    net: nn.Module
    name: str
    recipe: MelRecipe
    window_seconds: float
    source: str
    sample_rate: float | None = None  #: the audio rate it was trained at (Hz), where known


def _data_settings(path: Path) -> dict[str, Any]:
    """The DataModule hyperparameters a Lightning checkpoint stored (empty for other files)."""
    from zoo.weights.files import read_file

    try:
        stored = read_file(path)
    except AauteError:
        return {}
    settings = stored.get("datamodule_hyper_parameters") if isinstance(stored, dict) else None
    state = stored.get("MMAUDDataModule") if isinstance(stored, dict) else None  # its state_dict()
    return {**(settings if isinstance(settings, dict) else {}), **(state if isinstance(state, dict) else {})}


def load_net(ckpt_path: str | Path | None = None, weights: str | Path | None = None,
             offline: bool | None = None) -> tuple[nn.Module, str, str, dict[str, Any]]:
    """The net (eval mode), its model name, where it came from and the data settings stored with it, from a
    project checkpoint (``ckpt_path``) or named / file weights (``weights``); exactly one of the two.

    Raises:
        ConfigError: neither or both given.
    """
    from zoo.weights import build_net, load_task, resolve_weights

    if (ckpt_path is None) == (weights is None):
        raise ConfigError("aaute track needs exactly one of --ckpt_path FILE, --weights NAME_OR_PATH and "
                          "--config FILE")
    if ckpt_path is not None:
        path = Path(ckpt_path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such checkpoint")
        task = load_task(path)
        return task.net.eval(), str(task.hparams.net), str(path), _data_settings(path)
    contents, entry = resolve_weights(None, weights, offline)
    net = build_net(contents, None, None, entry)
    return net.eval(), net.model_name, str(contents.path), {
        "inputs": dict(contents.inputs or (entry.inputs if entry else {})),
        "audio_sample_rates": contents.metadata.get("audio_sample_rates")  # a checkpoint's DataModule
        or contents.metadata.get("provenance", {}).get("audio_sample_rates")}  # an exported file's


def load_tracking_model(ckpt_path: str | Path | None = None, weights: str | Path | None = None,
                        recipe: str | None = None, window_seconds: float | None = None,
                        offline: bool | None = None) -> TrackingModel:
    """The net of a project checkpoint (``ckpt_path``) or of named / file weights (``weights``), in eval mode.

    The mel recipe and window come from ``recipe`` / ``window_seconds`` if given, else from the
    checkpoint's data settings, else from the net's declared inputs and the DataModule's 2 s window.

    Raises:
        TrackingError: neither or both sources given, or a model whose inputs are not one mel map (phase
            models stream through :mod:`zoo.deploy.live_phase`; image recipes are not streamed), naming the
            model and the recipes supported.
    """
    net, name, source, data = load_net(ckpt_path, weights, offline)
    inputs = dict(getattr(net, "inputs", {}))
    supported = ", ".join(sorted(MEL_RECIPES))
    if set(inputs) != {"audio_mel"}:
        raise TrackingError(f"model {name!r} reads {inputs}; aaute track streams models of one mel input "
                            f"(audio_mel recipes {supported}) or of one phase input, not image recipes")
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
    # the rate of its training audio, else the one its data was read at, else its recipe's mel filters
    rates = data.get("audio_sample_rates") or []
    read_at = (data.get("reader_options") or {}).get("sample_rate")
    rate = rates[0] if len(rates) == 1 else read_at or mel.mel_sample_rate
    return TrackingModel(net, name, mel, seconds, source, float(rate) if rate else None)


# ============================================================================================ writers


class CsvWriter:
    """Rows as CSV lines, flushed one by one; a file is written to its temporary sibling and renamed at the end."""

    def __init__(self, stream: IO[str]):
        self.stream = stream
        stream.write(",".join(TRACK_ROW_COLUMNS) + "\n")
        stream.flush()

    def write(self, row: OnlineRow) -> None:
        values = (*row.mean, *row.std, *row.raw)
        self.stream.write(f"{row.timestamp:.6f}," + ",".join(f"{v:.6f}" for v in values) + "\n")
        self.stream.flush()


class McapTrackWriter:
    """Rows as JSON messages on one MCAP topic (schema ``aaute/TrackPoint``), each written out at once."""

    SCHEMA = {"type": "object", "title": "aaute/TrackPoint",
              "properties": {name: {"type": "number"} for name in TRACK_ROW_COLUMNS}}

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

        values = dict(zip(TRACK_ROW_COLUMNS, (row.timestamp, *map(float, (*row.mean, *row.std, *row.raw))),
                          strict=True))
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
    frame_kind: str = "STFT"  #: what the front end's frames are (STFT for mel recipes, GCC-PHAT for phase ones)
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
                f"({busy:.1f}x counting compute only, {cpu:.1f}x in CPU time); {self.frame_kind} frames computed "
                f"{share:.0%} of those used; "
                f"{self.threads} torch thread(s); ended by {self.ended}")


def _silence_stdout() -> None:
    """Point stdout at /dev/null after its reader closed it, so that exiting does not fail on a flush."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, io.UnsupportedOperation):
        pass
    finally:
        os.close(devnull)


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

    frame_kind = "STFT"  #: the front end's frames, as the end-of-run report names them

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
        self.front = self.front_end()
        self.smoother = OnlineSmoother(preset, lag=lag)
        self.bad_until = -1  #: windows ending at or before this absolute sample contain a non-finite block

    def front_end(self) -> Any:
        """The streaming front end (``push``, ``features``, ``end``, ``computed``, ``used``): the mel recipe's."""
        return IncrementalMel(self.model.recipe, self.source.sample_rate, self.source.channels, self.window)

    def _finish_rows(self) -> list[Any]:
        """The rows still held back when the stream ends (the smoother's, with the future seen so far)."""
        return self.smoother.flush()

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
        report = TrackingReport(threads=torch.get_num_threads(), frame_kind=self.frame_kind)
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
                self._emit(self._finish_rows(), report)
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
