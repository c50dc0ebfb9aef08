"""The data subcommands of ``aaute`` (``simulate``, ``info``, ``convert``, ``label``, ``audio``) and its error policy.

Each command is a parser (``_add_<command>``) and a handler (``_cmd_<command>``); heavy modules are
imported by the handlers only, so that building the parser stays fast. The error policy lives here, at
the bottom of the import graph, so that every ``aaute`` (this module's own :func:`main`, the zoo's
:func:`zoo.cli.main` and the console script :func:`benchmarks.cli.main`) reports bad input alike: the
project's errors (:data:`USER_ERRORS`) as one line and exit code 2, Ctrl-C as one line and exit code 130,
both with their traceback under ``--debug`` (anywhere on the line) or ``AAUTE_DEBUG=1``.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from datamodules.errors import AauteError, ConfigError

if TYPE_CHECKING:
    from datamodules.simulate.clocks import ClockConfig

log = logging.getLogger("aaute")

#: errors printed as one line and exit code 2 (the traceback only with ``--debug`` or ``AAUTE_DEBUG=1``): the
#: project's own error classes (bad input, bad settings) and a file that is missing or in the way.
#: Anything else is a programming error and shows its traceback.
USER_ERRORS = (AauteError, FileNotFoundError, FileExistsError, IsADirectoryError, NotADirectoryError,
               PermissionError)

#: adds subcommands to the ``aaute`` parser (the zoo's, the benchmarks')
AddCommands = Callable[[argparse._SubParsersAction], None]


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


# ============================================================================================ simulate


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
        clocks=_clock_config(args),
    )
    paths = simulate_dataset(args.out, args.sequences, config, seed=args.seed, workers=args.workers)
    log.info("%d recordings in %s", len(paths), args.out)
    return _cmd_info(argparse.Namespace(paths=paths))


def _clock_config(args: argparse.Namespace) -> ClockConfig | None:
    """The nodes' clocks from the --clock-* and --stamp-jitter-ms options (None: one shared clock)."""
    from datamodules.simulate.clocks import ClockConfig

    clocks = ClockConfig(offset_ms=args.clock_offset_ms, offset_range_ms=args.clock_offset_range_ms,
                         drift_ppm=args.clock_drift_ppm, drift_range_ppm=args.clock_drift_range_ppm,
                         stamp_jitter_ms=args.stamp_jitter_ms)
    try:
        clocks.check()
    except ValueError as error:
        raise ConfigError(str(error)) from None
    return clocks if clocks.active() else None


def _add_simulate(sub: argparse._SubParsersAction) -> None:
    from datamodules.recording import DRONE_TYPES  # the data model imports numpy: when the parser is built

    sim = sub.add_parser("simulate", help="simulate MMAUD-like recordings (MCAP)")
    sim.add_argument("--out", required=True, type=Path, help="output directory")
    sim.add_argument("--sequences", type=int, default=5)
    sim.add_argument("--seconds", type=float, default=60.0, help="duration of each recording")
    sim.add_argument("--seed", type=int, default=0)
    sim.add_argument("--drone", choices=DRONE_TYPES, help="one drone type for all (default: cycle through the five)")
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
    clocks = sim.add_argument_group("node clocks (default: one shared, exact clock; truth in meta clocks_truth)")
    clocks.add_argument("--clock-offset-ms", type=float, nargs="+", metavar="MS",
                        help="fixed offset per node; one value X: node n is n*X ms off")
    clocks.add_argument("--clock-offset-range-ms", type=float, default=0.0, metavar="MS",
                        help="plus a random offset in [-MS, MS] per node, drawn per recording")
    clocks.add_argument("--clock-drift-ppm", type=float, nargs="+", metavar="PPM",
                        help="fixed drift per node; one value X: node n drifts n*X ppm")
    clocks.add_argument("--clock-drift-range-ppm", type=float, default=0.0, metavar="PPM",
                        help="plus a random drift in [-PPM, PPM] per node, drawn per recording")
    clocks.add_argument("--stamp-jitter-ms", type=float, default=0.0, metavar="MS",
                        help="mean receive latency of each node's 0.1 s messages (nodes aligned by receive times)")
    sim.set_defaults(func=_cmd_simulate)


# ============================================================================================ info


def _cmd_info(args: argparse.Namespace) -> int:
    from datamodules.describe import describe, format_table
    from datamodules.formats import discover_all

    options = _reader_options(args)
    paths = discover_all(args.paths)
    rows, failed = [], []
    for path in paths:  # a bad recording is reported after the table; the others are still described
        try:
            rows.append(describe(path, **options))
        except AauteError as error:
            failed.append((path, error))
    sys.stdout.write(format_table(rows) + "\n")
    if getattr(args, "clocks", False):
        from datamodules.describe import clock_line

        for path in paths:
            if all(path != bad for bad, _ in failed) and (line := clock_line(path, **options)) is not None:
                sys.stdout.write(f"{path.name}: {line}\n")
    for path, error in failed:
        message = " ".join(str(error).split())
        sys.stdout.write(f"FAILED {path}: {message}\n" if str(path) not in message else f"FAILED {message}\n")
    if failed:
        log.error("%d of %d recording(s) could not be read", len(failed), len(paths))
    return 1 if failed else 0


def _add_info(sub: argparse._SubParsersAction) -> None:
    info = sub.add_parser("info", help="what recordings hold (files or folders of any layout)")
    info.add_argument("paths", nargs="+", type=Path)
    info.add_argument("--clocks", action="store_true",
                      help="for recordings whose audio nodes do not share a clock, estimate the offsets between "
                           "them from the audio (with their uncertainty; reads all of it, seconds per minute)")
    _add_reader_options(info)
    info.set_defaults(func=_cmd_info)


# ============================================================================================ convert


def _cmd_convert(args: argparse.Namespace) -> int:
    from datamodules.convert import convert

    written = convert(args.src, args.dst, overwrite=args.overwrite, audio_format=args.audio_format,
                      drop_unread_lidar=args.drop_unread_lidar, **_reader_options(args))
    log.info("%d MCAP recording(s) written to %s", len(written), args.dst)
    return 0


def _add_convert(sub: argparse._SubParsersAction) -> None:
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


# ============================================================================================ label


def _cmd_label(args: argparse.Namespace) -> int:
    from datamodules.describe import format_table
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


def _add_label(sub: argparse._SubParsersAction) -> None:
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


# ============================================================================================ audio


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


def _add_audio(sub: argparse._SubParsersAction) -> None:
    audio = sub.add_parser("audio", help="a recording's microphone audio as a WAV file or raw PCM on stdout")
    audio.add_argument("recording", type=Path, help="a recording of any layout")
    audio.add_argument("--out", required=True, type=Path, help="a .wav file, or - for raw interleaved PCM on stdout")
    audio.add_argument("--format", choices=["s16le", "s32le", "f32le"], default="s16le",
                       help="sample format (default s16le; WAV: s16le or s32le)")
    audio.add_argument("--overwrite", action="store_true", help="replace an existing WAV file")
    _add_reader_options(audio)
    audio.set_defaults(func=_cmd_audio)


# ============================================================================================ the command


def add_commands(sub: argparse._SubParsersAction) -> None:
    """The data subcommands: ``simulate``, ``info``, ``convert``, ``label`` and ``audio``."""
    for add in (_add_simulate, _add_info, _add_convert, _add_label, _add_audio):
        add(sub)


def build_parser(extra: AddCommands | None = None) -> argparse.ArgumentParser:
    """The ``aaute`` parser: the data subcommands plus those ``extra`` adds (the zoo's, the benchmarks')."""
    parser = argparse.ArgumentParser(prog="aaute", description="The ``aaute`` command.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--debug", action="store_true",
                        help="show the traceback of errors (also AAUTE_DEBUG=1); accepted anywhere on the line")
    sub = parser.add_subparsers(dest="command", required=True)
    add_commands(sub)
    if extra is not None:
        extra(sub)
    return parser


def run_parsed(parser: argparse.ArgumentParser, argv: Sequence[str]) -> int:
    """Parse ``argv``, set up logging and run the chosen subcommand's handler; its exit code."""
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    func: Callable[[argparse.Namespace], int] = args.func
    return func(args)


def debug_requested(argv: Sequence[str]) -> bool:
    """Whether tracebacks were asked for: ``--debug`` anywhere on the command line or ``AAUTE_DEBUG=1``."""
    return "--debug" in argv or os.environ.get("AAUTE_DEBUG", "").strip().lower() in ("1", "true", "yes")


#: the project's own packages: their warnings are always shown
PROJECT_MODULES = r"(zoo|datamodules|benchmarks)(\.|$)"


def quiet_third_party_deprecations() -> None:
    """Hide deprecation warnings raised inside libraries (``torch.jit.script is deprecated``, ...).

    The user of the command cannot act on them; the project's own warnings, and everything under
    ``--debug`` or an explicit ``PYTHONWARNINGS``, stay visible.
    """
    if os.environ.get("PYTHONWARNINGS"):
        return
    for category in (DeprecationWarning, PendingDeprecationWarning, FutureWarning):
        warnings.filterwarnings("ignore", category=category, module=rf"(?!{PROJECT_MODULES})")


def report_error(error: BaseException) -> None:
    """Print a project error as one line on stderr (its message names the file and what was expected)."""
    message = " ".join(str(error).split()) or type(error).__name__
    sys.stderr.write(f"aaute: error: {message} (--debug for the traceback)\n")


def run_guarded(argv: Sequence[str] | None, run: Callable[[list[str], bool], int]) -> int:
    """Run ``run(words, from_sys_argv)`` under the error policy (see the module docstring); its exit code.

    ``argv`` None reads ``sys.argv``; ``--debug`` is taken out of the words (and out of ``sys.argv``,
    which LightningCLI reads itself when it is given no list).
    """
    from_sys_argv = argv is None
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = debug_requested(argv)
    if not debug:
        quiet_third_party_deprecations()
    argv = [word for word in argv if word != "--debug"]
    if from_sys_argv:
        sys.argv[1:] = argv
    try:
        return run(argv, from_sys_argv)
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


def main(argv: Sequence[str] | None = None) -> int:
    """Run one data subcommand (``argv`` None: ``sys.argv``) under the error policy; its exit code."""
    return run_guarded(argv, lambda words, _: run_parsed(build_parser(), words))


if __name__ == "__main__":
    raise SystemExit(main())
