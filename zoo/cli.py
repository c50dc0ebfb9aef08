"""The ``aaute`` command.

Data and reporting subcommands (``simulate``, ``info``, ...) are plain argparse commands; the
training subcommands (``fit``, ``validate``, ``test``, ``predict``) are LightningCLI's, configured by
YAML files in ``configs/`` (``aaute fit --config configs/model/student.yaml --data.root DATA``).
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

log = logging.getLogger("aaute")


def _cmd_simulate(args: argparse.Namespace) -> int:
    from datamodules.simulate.acoustics import AudioConfig
    from datamodules.simulate.simulator import SimulationConfig, simulate_dataset

    config = SimulationConfig(
        duration=args.seconds,
        drone=args.drone,
        scene=args.scene,
        light=args.light,
        camera=not args.no_camera,
        audio=AudioConfig(sample_rate=args.sample_rate, microphones=args.microphones, ground=args.ground),
    )
    paths = simulate_dataset(args.out, args.sequences, config, seed=args.seed, workers=args.workers)
    log.info("%d recordings in %s", len(paths), args.out)
    return _cmd_info(argparse.Namespace(paths=paths))


def _cmd_info(args: argparse.Namespace) -> int:
    from datamodules.inspect import describe, format_table

    rows = [describe(Path(p)) for p in args.paths]
    sys.stdout.write(format_table(rows) + "\n")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="aaute", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

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
    sim.add_argument("--no-camera", action="store_true")
    sim.add_argument("--workers", type=int, default=1, help="parallel processes")
    sim.set_defaults(func=_cmd_simulate)

    info = sub.add_parser("info", help="what recordings hold")
    info.add_argument("paths", nargs="+", type=Path)
    info.set_defaults(func=_cmd_info)
    return parser


LIGHTNING_COMMANDS = ("fit", "validate", "test", "predict")


def lightning_main(argv: Sequence[str] | None) -> None:
    """``aaute fit|validate|test|predict``: LightningCLI over TrajectoryTask and the MMAUD DataModule."""
    from lightning.pytorch.cli import LightningCLI

    from datamodules.mmaud import MMAUDDataModule
    from zoo.task import TrajectoryTask

    LightningCLI(
        TrajectoryTask,
        MMAUDDataModule,
        subclass_mode_model=True,
        subclass_mode_data=True,
        args=None if argv is None else list(argv),  # None: LightningCLI reads sys.argv itself
        save_config_kwargs={"overwrite": True},
        parser_kwargs={"prog": "aaute"},
    )


def main(argv: Sequence[str] | None = None) -> int:
    given = argv
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in LIGHTNING_COMMANDS:
        lightning_main(given)
        return 0
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except (ValueError, FileExistsError, FileNotFoundError) as error:
        log.error("%s", error)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
