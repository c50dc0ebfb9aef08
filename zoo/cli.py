"""The ``aaute`` command.

Data and reporting subcommands (``simulate``, ``info``, ...) are plain argparse commands; the
training subcommands (``fit``, ``validate``, ``test``, ``predict``) are LightningCLI's, configured by
YAML files in ``configs/`` (``aaute fit --config configs/model/student.yaml --data.root DATA``).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from datamodules.errors import AauteError, ConfigError

log = logging.getLogger("aaute")

#: errors printed as one line and exit code 2 (the traceback only with ``--debug`` or ``AAUTE_DEBUG=1``): the
#: project's own error classes (bad input, bad settings) and a file that is missing or in the way.
#: Anything else is a programming error and shows its traceback.
USER_ERRORS = (AauteError, FileNotFoundError, FileExistsError, IsADirectoryError, NotADirectoryError,
               PermissionError)


def _cmd_simulate(args: argparse.Namespace) -> int:
    from datamodules.simulate.acoustics import AudioConfig
    from datamodules.simulate.ambient import AmbientConfig
    from datamodules.simulate.simulator import SimulationConfig, simulate_dataset

    ranges: dict[str, tuple[float, float]] = {}  # only those given: the rest keep AmbientConfig's defaults
    for flag, field, given in (("--ambient-dba", "level_dba", args.ambient_dba), ("--wind", "wind_speed", args.wind)):
        if given is not None:
            lo, hi = given
            if not 0 <= lo <= hi:
                raise ConfigError(f"{flag} needs 0 <= LOW <= HIGH, got {lo:g} {hi:g}")
            ranges[field] = (lo, hi)
    ambient = AmbientConfig(hvac=not args.no_hvac, **ranges)
    config = SimulationConfig(
        duration=args.seconds,
        drone=args.drone,
        scene=args.scene,
        light=args.light,
        camera=not args.no_camera,
        audio=AudioConfig(sample_rate=args.sample_rate, microphones=args.microphones, ground=args.ground,
                          ambient=ambient),
    )
    paths = simulate_dataset(args.out, args.sequences, config, seed=args.seed, workers=args.workers)
    log.info("%d recordings in %s", len(paths), args.out)
    return _cmd_info(argparse.Namespace(paths=paths))


def _reader_options(args: argparse.Namespace) -> dict:
    """Options for reading non-MCAP layouts that were given on the command line."""
    names = ("sample_rate", "mapping", "channels", "sample_format")
    return {name: getattr(args, name) for name in names if getattr(args, name, None) is not None}


def _add_reader_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("reading real MMAUD layouts (derived npy, ROS 1 bags)")
    group.add_argument("--sample-rate", type=float,
                       help="audio sample rate of the derived npy layout, or of bags without an AudioInfo topic "
                            "(46080 in the AAUTE code, 48000 elsewhere; default 48000)")
    group.add_argument("--mapping", type=Path, help="YAML topic mapping for ROS 1 bags (audio, mid360, avia, ...)")
    group.add_argument("--channels", type=int, help="audio channels of bags without AudioInfo (default 4)")
    group.add_argument("--sample-format", choices=["S16LE", "S32LE", "F32LE"],
                       help="audio sample format of bags without AudioInfo (default S16LE)")


def _cmd_info(args: argparse.Namespace) -> int:
    from datamodules.formats import discover_all
    from datamodules.inspect import describe, format_table

    options = _reader_options(args)
    paths = discover_all(args.paths)
    rows, failed = [], []
    for path in paths:  # a bad recording is reported after the table; the others are still described
        try:
            rows.append(describe(path, **options))
        except AauteError as error:
            failed.append((path, error))
    sys.stdout.write(format_table(rows) + "\n")
    for path, error in failed:
        message = " ".join(str(error).split())
        sys.stdout.write(f"FAILED {path}: {message}\n" if str(path) not in message else f"FAILED {message}\n")
    if failed:
        log.error("%d of %d recording(s) could not be read", len(failed), len(paths))
    return 1 if failed else 0


def _cmd_convert(args: argparse.Namespace) -> int:
    from datamodules.convert import convert

    written = convert(args.src, args.dst, overwrite=args.overwrite, audio_format=args.audio_format,
                      drop_unread_lidar=args.drop_unread_lidar, **_reader_options(args))
    log.info("%d MCAP recording(s) written to %s", len(written), args.dst)
    return 0


def _cmd_label(args: argparse.Namespace) -> int:
    from datamodules.inspect import format_table
    from datamodules.label import label_paths
    from datamodules.teacher import TeacherConfig
    from datamodules.teacher.evaluate import pool_scores

    overrides = {}
    for item in args.param:
        name, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"--param expects NAME=VALUE, got {item!r}")
        overrides[name.strip()] = value.strip()
    config = TeacherConfig.from_overrides(overrides)
    paths = [*args.paths, *args.data]
    if not paths:
        raise ConfigError("aaute label: give recordings or folders to label (PATH... or --data ROOT)")
    outcomes = label_paths(paths, config, workers=args.workers, write=not args.no_write,
                           evaluate=args.evaluate, skip_existing=args.skip_existing, max_range_m=args.max_range,
                           reader_options=_reader_options(args))
    rows = [o.as_row() for o in outcomes]
    columns = list(dict.fromkeys(k for row in rows for k in row))
    sys.stdout.write(format_table([{k: row.get(k, "") for k in columns} for row in rows]) + "\n")
    scores = [o.score for o in outcomes if o.score is not None]
    if args.evaluate:
        if scores:
            pooled = pool_scores(scores).as_row()
            sys.stdout.write("all recordings: " + ", ".join(
                f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in pooled.items()
                if k != "sequence") + "\n")
        else:
            log.warning("no recording holds ground truth: nothing to evaluate")
    failed = [o for o in outcomes if o.error]
    if failed:
        log.error("%d of %d recording(s) failed", len(failed), len(outcomes))
    return 1 if failed else 0


def check_output(src: Path, dst: Path, overwrite: bool) -> None:
    """The one overwrite policy of commands that write a file: never over an input, over others only if asked.

    Raises:
        ConfigError: ``dst`` is the input ``src``.
        FileExistsError: ``dst`` exists and ``overwrite`` is False.
    """
    if dst.exists() and src.exists() and dst.resolve() == src.resolve():
        raise ConfigError(f"{dst}: the output is the input {src}; write the result to another file")
    if dst.exists() and not overwrite:
        raise FileExistsError(f"{dst} already exists; refusing to overwrite it (use --overwrite)")


def _cmd_audio(args: argparse.Namespace) -> int:
    from datamodules.audio_export import write_pcm, write_wav
    from datamodules.formats import open_recording

    audio = open_recording(args.recording, **_reader_options(args)).audio
    if audio is None:
        raise ConfigError(f"{args.recording}: the recording holds no microphone audio")
    shape = (f"{audio.num_channels} channels, {audio.sample_rate:g} Hz, {args.format}, "
             f"{audio.duration:.1f} s from t0 = {audio.t0!r}")
    if str(args.out) == "-":
        log.info("%s: raw PCM to stdout (%s); read it with: aaute track --audio - --channels %d --rate %g "
                 "--format %s --t0 %r", args.recording, shape, audio.num_channels, audio.sample_rate, args.format,
                 audio.t0)
        write_pcm(audio, sys.stdout.buffer, args.format)
        return 0
    check_output(args.recording, args.out, args.overwrite)
    write_wav(audio, args.out, args.format, overwrite=args.overwrite)
    log.info("%s -> %s (%s)", args.recording, args.out, shape)
    return 0


def _cmd_smooth(args: argparse.Namespace) -> int:
    from dataclasses import replace

    import numpy as np

    from zoo.smoothing import (
        ROBUST_PRESETS,
        fit_robust_hyperparameters,
        make_smoother,
        read_track_csv,
        smooth_online,
        write_smoothed_csv,
    )

    check_output(args.src, args.dst, args.overwrite)
    robust = args.preset in ROBUST_PRESETS
    if args.lag is not None and not robust:
        raise ConfigError(f"--lag needs a robust preset ({', '.join(ROBUST_PRESETS)}), not {args.preset!r}")
    options: dict = {"fit": args.fit}
    if not robust:
        options["backend"] = args.backend
    if args.horizon is not None:
        options["horizon"] = args.horizon
    timestamps, xyz = read_track_csv(args.src)
    if args.lag is not None:
        preset = ROBUST_PRESETS[args.preset]
        if args.fit:  # learned offline on this track's positions, then run online
            fitted = fit_robust_hyperparameters([(timestamps, xyz)], preset).hyperparameters
            preset = replace(fitted, std_scale=preset.std_scale)
        track = smooth_online(timestamps, xyz, preset, lag=args.lag)
    else:
        track = make_smoother(args.preset, **options).smooth(timestamps, xyz)
    write_smoothed_csv(args.dst, track)
    log.info("smoothed %d points of %s (%s) -> %s", len(track), args.src, track.backend, args.dst)
    if track.weights is not None:
        hp = track.hyperparameters
        mode = f"lag {args.lag:g} s" if args.lag is not None else "offline"
        sys.stdout.write(f"{args.preset} smoother ({mode}): "
                         f"degrees of freedom {hp.dof:.3g}{' (fitted)' if args.fit else ''}, "
                         f"{np.mean(track.weights < 0.5):.1%} of {len(track)} frames down-weighted "
                         f"(weight < 0.5), median weight {np.median(track.weights):.2f}\n")
    beyond = int(track.beyond_horizon.sum())
    if beyond:
        log.info("%d of %d points lie beyond the %g s horizon", beyond, len(track), track.horizon)
    return 0


def _cmd_track(args: argparse.Namespace) -> int:
    from zoo.tracking import run_track

    return run_track(args)


def _add_track_command(sub: argparse._SubParsersAction) -> None:
    """Register ``aaute track`` on an argparse subparsers object."""
    track = sub.add_parser(
        "track", help="real-time positions with uncertainty every 0.1 s from audio alone",
        description="Track a drone from microphone audio: a recording (MCAP or any layout aaute reads), a WAV "
                    "file, or raw PCM on stdin ('-'). After each 0.1 s block the window ending there goes through "
                    "the model's mel recipe and net, then the causal (or fixed-lag) robust smoother; each row "
                    "'timestamp,x,y,z,std_x,std_y,std_z' is written and flushed at once. Statistics (latency, "
                    "speed against real time, threads) go to stderr at the end.")
    track.add_argument("--audio", required=True, help="'-' (raw PCM on stdin), a .wav file, or a recording")
    model = track.add_mutually_exclusive_group(required=True)
    model.add_argument("--ckpt_path", help="a project checkpoint (.ckpt of aaute fit)")
    model.add_argument("--weights", help="registered weights (aaute weights list) or a weights file")
    track.add_argument("--recipe", help="mel recipe (default: the checkpoint's data settings, else the net's own)")
    track.add_argument("--window-seconds", type=float, help="audio seconds per window (default: the checkpoint's, "
                                                            "else 2)")
    track.add_argument("--lag", type=float, default=0.0, help="seconds of future each smoothed position may use "
                                                              "(0: causal, the default)")
    track.add_argument("--preset", choices=["robust"], default="robust", help="robust smoother preset")
    track.add_argument("--realtime", action="store_true", help="recordings: deliver blocks at real-time pace")
    pcm = track.add_argument_group("raw PCM on stdin and WAV files")
    pcm.add_argument("--channels", type=int, help="interleaved channels of the PCM stream")
    pcm.add_argument("--rate", type=float, help="sample rate of the PCM stream (Hz)")
    pcm.add_argument("--format", choices=["s16le", "s32le", "f32le"], default="s16le", help="PCM sample format")
    pcm.add_argument("--mic-positions", type=Path,
                     help="text file of one 'x y z' row (m) per channel (default: the simulator's array)")
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
    track.set_defaults(func=_cmd_track)


def add_commands(sub: argparse._SubParsersAction) -> None:
    """The zoo's and the datamodules' argparse subcommands (simulate, info, convert, label, smooth, track)."""
    sim = sub.add_parser("simulate", help="simulate MMAUD-like recordings (MCAP)")
    sim.add_argument("--out", required=True, type=Path, help="output directory")
    sim.add_argument("--sequences", type=int, default=5)
    sim.add_argument("--seconds", type=float, default=60.0, help="duration of each recording")
    sim.add_argument("--seed", type=int, default=0)
    sim.add_argument("--drone", choices=["avata", "m300", "mavic2", "mavic3", "phantom4"],
                     help="one drone type for all (default: cycle through the five)")
    sim.add_argument("--scene", choices=["rooftop", "carpark"], default="rooftop")
    sim.add_argument("--light", choices=["ideal", "dark"], default="ideal")
    sim.add_argument("--sample-rate", type=float, default=48000.0, help="48000 (default) or 46080")
    sim.add_argument("--microphones", default="distributed4", help="distributed4 | respeaker4 | respeaker6")
    sim.add_argument("--ground", default="concrete", help="concrete | asphalt | grass | none")
    sim.add_argument("--ambient-dba", type=float, nargs=2, metavar=("LOW", "HIGH"),
                     help="range of the diffuse ambient level, dB(A), drawn per recording (default 45 62)")
    sim.add_argument("--wind", type=float, nargs=2, metavar=("LOW", "HIGH"),
                     help="range of the wind speed, m/s, drawn per recording (default 0 4; 0 0: no wind)")
    sim.add_argument("--no-hvac", action="store_true", help="no rooftop HVAC unit")
    sim.add_argument("--no-camera", action="store_true")
    sim.add_argument("--workers", type=int, default=1, help="parallel processes")
    sim.set_defaults(func=_cmd_simulate)

    info = sub.add_parser("info", help="what recordings hold (files or folders of any layout)")
    info.add_argument("paths", nargs="+", type=Path)
    _add_reader_options(info)
    info.set_defaults(func=_cmd_info)

    conv = sub.add_parser("convert", help="convert recordings of any layout (UG2, derived npy, ROS 1 bags) to MCAP")
    conv.add_argument("src", type=Path, help="a recording, or a folder / list file holding several")
    conv.add_argument("dst", type=Path, help="an .mcap file (one recording) or a folder (one MCAP per sequence)")
    conv.add_argument("--overwrite", action="store_true", help="replace existing MCAP files")
    conv.add_argument("--drop-unread-lidar", action="store_true",
                      help="convert bags even if some LiDAR topics cannot be placed on a sensor (they are dropped)")
    conv.add_argument("--audio-format", choices=["S16LE", "S32LE", "F32LE"],
                      help="sample format of the written audio (default: the source's own)")
    _add_reader_options(conv)
    conv.set_defaults(func=_cmd_convert)

    lab = sub.add_parser("label", help="LiDAR pseudo-labels (the teacher) for recordings of any layout")
    lab.add_argument("paths", nargs="*", type=Path, help="recordings, or folders holding them")
    lab.add_argument("--data", action="append", type=Path, default=[], help="a dataset root (same as a path)")
    lab.add_argument("--workers", type=int, default=1, help="recordings labelled in parallel processes")
    lab.add_argument("--evaluate", action="store_true",
                     help="report the teacher's error and coverage against ground truth where it exists")
    lab.add_argument("--max-range", type=float, help="evaluate only ground truth within this distance (m) of a LiDAR")
    lab.add_argument("--no-write", action="store_true", help="do not store the tracks (with --evaluate: a dry run)")
    lab.add_argument("--skip-existing", action="store_true", help="leave recordings that carry pseudo-labels alone")
    lab.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                     help="teacher parameter (a TeacherConfig field), repeatable, e.g. --param max_gap_s=2")
    _add_reader_options(lab)
    lab.set_defaults(func=_cmd_label)

    audio = sub.add_parser("audio", help="a recording's microphone audio as a WAV file or raw PCM on stdout")
    audio.add_argument("recording", type=Path, help="a recording of any layout")
    audio.add_argument("--out", required=True, type=Path, help="a .wav file, or - for raw interleaved PCM on stdout")
    audio.add_argument("--format", choices=["s16le", "s32le", "f32le"], default="s16le",
                       help="sample format (default s16le; WAV: s16le or s32le)")
    audio.add_argument("--overwrite", action="store_true", help="replace an existing WAV file")
    _add_reader_options(audio)
    audio.set_defaults(func=_cmd_audio)

    smooth = sub.add_parser("smooth", help="smooth a track CSV (timestamp,x,y,z) and add per-axis std")
    smooth.add_argument("src", type=Path)
    smooth.add_argument("dst", type=Path)
    smooth.add_argument("--preset", choices=["robust", "paper", "tuned"], default="robust",
                        help="robust: Student-t state-space smoother learned on real MMAUD predictions (default); "
                             "paper: the paper's RBF GP, lengthscale 300 x 10 ms, noise 2, outputscale 1; tuned: "
                             "Matern-5/2 GP learned on real MMAUD predictions")
    smooth.add_argument("--lag", type=float, help="robust only: causal (0) or fixed-lag (seconds) smoothing, "
                                                  "each output using data up to its time plus the lag")
    smooth.add_argument("--backend", default="auto", help="GP presets: auto | exact | statespace | local")
    smooth.add_argument("--fit", action="store_true", help="fit the hyperparameters to this track first")
    smooth.add_argument("--horizon", type=float, help="flag query times farther than this (s) from any data")
    smooth.add_argument("--overwrite", action="store_true", help="replace an existing DST (never SRC itself)")
    smooth.set_defaults(func=_cmd_smooth)

    _add_track_command(sub)
    from zoo import weights_cli

    weights_cli.add_commands(sub)  # weights list|register, import-checkpoint, export


def build_parser(extra: Callable[[argparse._SubParsersAction], None] | None = None) -> argparse.ArgumentParser:
    """The ``aaute`` parser: the zoo's subcommands plus those ``extra`` adds (the benchmarks' own)."""
    parser = argparse.ArgumentParser(prog="aaute", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--debug", action="store_true",
                        help="show the traceback of errors (also AAUTE_DEBUG=1); accepted anywhere on the line")
    sub = parser.add_subparsers(dest="command", required=True)
    add_commands(sub)
    if extra is not None:
        extra(sub)
    return parser


LIGHTNING_COMMANDS = ("fit", "validate", "test", "predict")
#: TrajectoryTask arguments that belong to a run, not to a checkpoint (kept from the command line)
RUN_SETTINGS = ("predictions_dir", "predictions_topic", "smooth", "smoother")


def lightning_cli(argv: Sequence[str] | None, run: bool = True, instantiate: bool = True,
                  exit_on_error: bool = True):
    """LightningCLI over TrajectoryTask and the MMAUD DataModule, as ``aaute fit|validate|test|predict`` builds it.

    ``argv`` None reads ``sys.argv``. With ``run=False`` the argument list has no subcommand and the
    caller drives ``cli.trainer`` (the benchmark runner does); with ``instantiate=False`` the
    arguments are only parsed and checked (``cli.config``), nothing is built. With
    ``exit_on_error=False`` a bad argument raises ``argparse.ArgumentError`` instead of exiting.
    """
    from lightning.pytorch.cli import LightningCLI

    from datamodules.mmaud import MMAUDDataModule
    from zoo import checkpoint_guard
    from zoo.task import TrajectoryTask

    class _CLI(LightningCLI):
        pending_weights = None

        def add_arguments_to_parser(self, parser) -> None:
            parser.add_argument("--weights", type=str | None, default=None,
                                help="registered weights (aaute weights list) or a weights file, instead of ckpt_path")
            parser.add_argument("--use_checkpoint_model", type=bool, default=False,
                                help="run the model of --ckpt_path / --weights even if another one is configured")

        def instantiate_classes(self) -> None:
            if instantiate:
                try:
                    super().instantiate_classes()
                except ValueError as error:  # jsonargparse keeps only the text of the class's own error
                    _raise_project_error(self.config, error)
                    raise
                checkpoint_guard.load_pending(self.model, self.pending_weights)

        def _parse_ckpt_path(self) -> None:
            # Lightning merges a checkpoint's hyperparameters over the command line; where this run writes
            # its outputs and how it smooths them are this run's settings, not the trained model's
            subcommand = self.config.get("subcommand")
            init_args = self.config[subcommand].get("model", {}).get("init_args") if subcommand else None
            given = {key: init_args.get(key) for key in RUN_SETTINGS} if init_args is not None else {}
            if subcommand:  # a checkpoint of another net is refused, not silently swapped in
                self.pending_weights = checkpoint_guard.check_run(subcommand, self.config[subcommand])
            super()._parse_ckpt_path()
            for key, value in given.items():
                self.config[subcommand]["model"]["init_args"][key] = value

    return _CLI(
        TrajectoryTask,
        MMAUDDataModule,
        subclass_mode_model=True,
        subclass_mode_data=True,
        args=None if argv is None else list(argv),  # None: LightningCLI reads sys.argv itself
        run=run,
        save_config_kwargs={"overwrite": True},
        parser_kwargs={"prog": "aaute", "exit_on_error": exit_on_error},
    )


def _raise_project_error(config, error: ValueError) -> None:
    """Build the model and data classes of ``config`` again, so that their own project error surfaces.

    jsonargparse reports a failing ``__init__`` as a ValueError holding the text of every attempt; the
    project error (an unknown net, an alpha outside [0, 1], ...) is raised here by type instead.
    """
    import importlib

    subcommand = config.get("subcommand")
    section = config[subcommand] if subcommand else config
    for key in ("model", "data"):
        entry = section.get(key)
        if not entry or not getattr(entry, "class_path", None):
            continue
        module_name, _, class_name = entry.class_path.rpartition(".")
        cls = getattr(importlib.import_module(module_name), class_name)
        init_args = entry.init_args.as_dict() if entry.get("init_args") is not None else {}
        try:
            cls(**init_args)
        except AauteError as project_error:
            raise project_error from error


def lightning_main(argv: Sequence[str] | None) -> None:
    """``aaute fit|validate|test|predict``."""
    lightning_cli(argv)


def debug_requested(argv: Sequence[str]) -> bool:
    """Whether tracebacks were asked for: ``--debug`` anywhere on the command line or ``AAUTE_DEBUG=1``."""
    return "--debug" in argv or os.environ.get("AAUTE_DEBUG", "").strip().lower() in ("1", "true", "yes")


def report_error(error: BaseException) -> None:
    """Print a project error as one line on stderr (its message names the file and what was expected)."""
    message = " ".join(str(error).split()) or type(error).__name__
    sys.stderr.write(f"aaute: error: {message} (--debug for the traceback)\n")


def _run(argv: list[str], extra: Callable[[argparse._SubParsersAction], None] | None, from_sys_argv: bool) -> int:
    if argv and argv[0] in LIGHTNING_COMMANDS:
        lightning_main(None if from_sys_argv else argv)
        return 0
    args = build_parser(extra).parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    func: Callable[[argparse.Namespace], int] = args.func
    return func(args)


def main(argv: Sequence[str] | None = None,
         extra: Callable[[argparse._SubParsersAction], None] | None = None) -> int:
    """Run one ``aaute`` subcommand; ``extra`` adds subcommands (see :mod:`benchmarks.cli`).

    Project errors (:data:`USER_ERRORS`) print one line and return 2; Ctrl-C prints one line and returns
    130. With ``--debug`` (anywhere on the command line) or ``AAUTE_DEBUG=1`` both raise with their traceback.
    """
    from_sys_argv = argv is None
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = debug_requested(argv)
    argv = [word for word in argv if word != "--debug"]
    if from_sys_argv:
        sys.argv[1:] = argv  # LightningCLI reads sys.argv itself when it is given no list
    try:
        return _run(argv, extra, from_sys_argv)
    except USER_ERRORS as error:
        if debug:
            raise
        report_error(error)
        return 2
    except KeyboardInterrupt:
        if debug:
            raise
        sys.stderr.write("aaute: interrupted; files already written are complete, nothing half-written is left\n")
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
