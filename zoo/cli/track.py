"""``aaute track``: its parser, the audio source it names, its writers, and the run with its report on stderr.

The tracking itself (model, writers, :class:`~zoo.deploy.tracking.Tracker`) is :mod:`zoo.deploy.tracking`
and the audio sources are :mod:`datamodules.streams`; both import torch or numpy, so they are imported
when the command runs, not when the parser is built.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Any

from datamodules.cli import check_output
from datamodules.errors import ConfigError

if TYPE_CHECKING:
    from datamodules.streams import AudioSource

log = logging.getLogger(__name__)


def open_source(audio: str, *, channels: int | None = None, rate: float | None = None, sample_format: str = "s16le",
                mic_positions: str | Path | None = None, t0: float = 0.0, stall_timeout: float = 5.0,
                realtime: bool = False, separate_clocks: bool = False) -> AudioSource:
    """The source ``audio`` names: ``-`` (raw PCM on stdin), a ``.wav`` file, or a recording.

    Args:
        audio: ``-``, a WAV file or a recording of any layout the project reads.
        channels, rate, sample_format: raw PCM on stdin only (``channels`` and ``rate`` are required there).
        mic_positions: a text file of one ``x y z`` row per channel (PCM, WAV, and recordings whose own
            positions are unknown).
        t0: time of the first sample of PCM and WAV audio (s).
        stall_timeout: seconds without data after which stdin counts as ended.
        realtime: recordings: deliver blocks at real-time pace.
        separate_clocks: the channels come from audio nodes that do not share a clock (e.g. one WAV per node
            joined), whatever the source says.

    Raises:
        ConfigError: raw PCM without ``channels`` or ``rate``.
        FileNotFoundError: ``audio`` does not exist.
    """
    from datamodules.streams import PcmSource, RecordingSource, WavSource

    source: AudioSource
    if audio == "-":
        missing = [flag for flag, value in (("--channels", channels), ("--rate", rate)) if value is None]
        if missing:
            raise ConfigError(f"raw PCM on stdin needs {' and '.join(missing)} (and --format, default s16le)")
        source = PcmSource(sys.stdin.buffer, channels, rate, sample_format, mic_positions, t0, stall_timeout)
    else:
        path = Path(audio)
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such audio file or recording")
        if path.suffix.lower() == ".wav":
            source = WavSource(path, mic_positions, t0)
        else:
            source = RecordingSource(path, realtime=realtime, mic_positions=mic_positions)
            if mic_positions is not None and source.mic_source == "the recording":
                log.info("%s: the recording's own microphone positions are used (--mic-positions ignored)", path)
    if separate_clocks:
        source.nodes_share_clock = False
    return source


RATE_TOLERANCE = 0.01  #: audio more than 1 % off the model's rate is refused


def check_rate(source_name: str, rate: float, model_name: str, expected: float | None) -> None:
    """Refuse audio whose sample rate is more than :data:`RATE_TOLERANCE` off the model's (where known).

    Raises:
        ConfigError: naming the source, its rate and the expected one.
    """
    if expected and abs(rate / expected - 1.0) > RATE_TOLERANCE:
        raise ConfigError(f"{source_name}: audio at {rate:g} Hz, but model {model_name!r} was trained on "
                          f"{expected:g} Hz audio (within {RATE_TOLERANCE:.0%}); resample it to {expected:g} Hz first")


def run_track(args: argparse.Namespace) -> int:
    """``aaute track``: track, write the rows, print the report to stderr."""
    import torch

    from datamodules.atomic import atomic_write
    from zoo.deploy.live_phase import PhaseCsvWriter, PhaseMcapWriter, PhaseTracker, is_phase_model, load_phase_model
    from zoo.deploy.tracking import CsvWriter, McapTrackWriter, Tracker, load_tracking_model

    torch.set_num_threads(max(1, int(args.threads)))
    phase = is_phase_model(args.config, args.ckpt_path, args.weights)

    def source() -> AudioSource:
        return open_source(args.audio, channels=args.channels, rate=args.rate, sample_format=args.format,
                           mic_positions=args.mic_positions, t0=args.t0, stall_timeout=args.stall_timeout,
                           realtime=args.realtime, separate_clocks=args.separate_clocks)

    if phase:  # the array first: a phase model is built for it and refuses unknown positions
        audio = source()
        model: Any = load_phase_model(args.config, args.ckpt_path, args.weights, source=audio)
    else:
        model = load_tracking_model(args.ckpt_path, args.weights, args.recipe, args.window_seconds)
        audio = source()
        check_rate(audio.name, audio.sample_rate, model.name, model.sample_rate)
    log.info("tracking %s (%d channels, %g Hz; microphones from %s) with %s from %s: recipe %s, %g s "
             "windows, lag %g s", audio.name, audio.channels, audio.sample_rate, audio.mic_source, model.name,
             model.source, model.recipe.name, model.window_seconds, args.lag)
    csv_writer, mcap_class = (PhaseCsvWriter, PhaseMcapWriter) if phase else (CsvWriter, McapTrackWriter)
    source_path = Path(args.audio) if args.audio != "-" else Path(os.devnull)
    for out in (args.out, args.mcap_out):
        if out is not None:
            check_output(source_path, Path(out), args.overwrite)
    with ExitStack() as stack:
        writers: list[Any] = []
        if args.out is None and args.mcap_out is None or args.stdout:
            writers.append(csv_writer(sys.stdout))
        if args.out is not None:
            tmp = stack.enter_context(atomic_write(args.out))
            writers.append(csv_writer(stack.enter_context(open(tmp, "w"))))
        mcap_writer = None
        if args.mcap_out is not None:
            tmp = stack.enter_context(atomic_write(args.mcap_out))
            mcap_writer = mcap_class(stack.enter_context(open(tmp, "wb")), args.topic)
            writers.append(mcap_writer)
        tracker = PhaseTracker if phase else Tracker
        preset = args.preset if phase or args.preset else "robust"  # a phase model falls back to its config's
        extra = {"clock_seconds": args.clock_seconds, "clock_follow": not args.clock_once} if phase else {}
        report = tracker(model, audio, writers, lag=args.lag, preset=preset, batch=args.batch, **extra).run()
        if mcap_writer is not None:
            mcap_writer.finish()
    sys.stderr.write(f"aaute track: {report.summary()}\n")
    return 0


def add_command(sub: argparse._SubParsersAction) -> None:
    """Register ``aaute track`` on an argparse subparsers object."""
    track = sub.add_parser(
        "track", help="real-time positions with uncertainty every 0.1 s from audio alone",
        description="Track a drone from microphone audio: a recording (MCAP or any layout aaute reads), a WAV "
                    "file, or raw PCM on stdin ('-'). After each 0.1 s block the window ending there goes through "
                    "the model's mel recipe and net, then the causal (or fixed-lag) robust smoother; each row "
                    "'timestamp,x,y,z,std_x,std_y,std_z,raw_x,raw_y,raw_z' (smoothed, its std, the net's own) is "
                    "written and flushed at once. Phase models (--config "
                    "configs/model/srp_phat.yaml, or phase_student weights) stream the GCC-PHAT recipe, need the "
                    "microphone positions, and add detection_score,detected,state. Statistics "
                    "(latency, "
                    "speed against real time, threads) go to stderr at the end.")
    track.add_argument("--audio", required=True, help="'-' (raw PCM on stdin), a .wav file, or a recording")
    model = track.add_mutually_exclusive_group(required=True)
    model.add_argument("--ckpt_path", help="a project checkpoint (.ckpt of aaute fit)")
    model.add_argument("--weights", help="registered weights (aaute weights list) or a weights file")
    model.add_argument("--config", help="a phase model's config (non-learned: configs/model/srp_phat.yaml); its "
                                        "net settings, phase recipe, bird's-eye bounds and live_smoother")
    track.add_argument("--recipe", help="mel recipe (default: the checkpoint's data settings, else the net's own)")
    track.add_argument("--window-seconds", type=float, help="audio seconds per window (default: the checkpoint's, "
                                                            "else 2)")
    track.add_argument("--lag", type=float, default=0.0, help="seconds of future each smoothed position may use "
                                                              "(0: causal, the default)")
    track.add_argument("--preset", choices=["robust", "srp_phat"],
                       help="online smoother preset (default: a phase config's live_smoother, else robust)")
    track.add_argument("--realtime", action="store_true", help="recordings: deliver blocks at real-time pace")
    track.add_argument("--clock-seconds", type=float, default=30.0, metavar="S",
                       help="phase models, recordings whose audio nodes do not share a clock: seconds of the "
                            "stream's start from which their offsets are estimated, then corrected, and again "
                            "from every further S s, drift followed; rows before the first estimate are "
                            "'uncorrected', never detections (default 30; 0: not corrected, rows as they come)")
    track.add_argument("--clock-once", action="store_true",
                       help="phase models, nodes on separate clocks: estimate the clocks from the first "
                            "--clock-seconds only, not again as the stream goes on")
    track.add_argument("--separate-clocks", action="store_true",
                       help="phase models: the channels come from audio nodes on separate clocks (e.g. one WAV per "
                            "node joined, or PCM from several devices): calibrate them as --clock-seconds says")
    pcm = track.add_argument_group("raw PCM on stdin and WAV files")
    pcm.add_argument("--channels", type=int, help="interleaved channels of the PCM stream")
    pcm.add_argument("--rate", type=float, help="sample rate of the PCM stream (Hz)")
    pcm.add_argument("--format", choices=["s16le", "s32le", "f32le"], default="s16le", help="PCM sample format")
    pcm.add_argument("--mic-positions", type=Path,
                     help="text file of one 'x y z' row (m) per channel, also for recordings whose positions are "
                          "unknown (mel models default to the simulator's array; phase models need real positions)")
    pcm.add_argument("--t0", type=float, default=0.0, help="time of the first sample (s; default 0)")
    pcm.add_argument("--stall-timeout", type=float, default=5.0,
                     help="seconds without data after which the stream counts as ended (default 5)")
    out = track.add_argument_group("output (default: CSV on stdout)")
    out.add_argument("--out", type=Path, help="CSV file (written beside it, renamed into place at the end)")
    out.add_argument("--mcap-out", type=Path, help="MCAP file of JSON track points")
    out.add_argument("--topic", default="/track/position", help="topic of --mcap-out (default /track/position)")
    out.add_argument("--stdout", action="store_true", help="also write CSV to stdout when writing files")
    out.add_argument("--overwrite", action="store_true", help="replace existing output files")
    track.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    track.add_argument("--batch", type=int, default=1,
                       help="windows per net call (default 1: each line as soon as its block is in); more speed up "
                            "a replay and delay each line by up to that many blocks")
    track.set_defaults(func=run_track)
