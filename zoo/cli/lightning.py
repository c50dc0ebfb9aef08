"""``aaute fit|validate|test|predict``: LightningCLI over :class:`~zoo.task.TrajectoryTask` and the MMAUD DataModule.

The training subcommands are LightningCLI's, configured by YAML files in ``configs/``
(``aaute fit --config configs/model/student.yaml --data.root DATA``). Here they get ``--weights`` and
``--use_checkpoint_model`` (checked by :mod:`zoo.cli.checkpoint_args`), keep this run's output and
smoothing settings over a checkpoint's, and report a class's own project error instead of
jsonargparse's summary of every attempt. Lightning is imported only when one of them runs.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from datamodules.errors import AauteError

if TYPE_CHECKING:
    from lightning.pytorch.cli import LightningCLI

LIGHTNING_COMMANDS = ("fit", "validate", "test", "predict")
#: TrajectoryTask arguments that belong to a run, not to a checkpoint (kept from the command line)
RUN_SETTINGS = ("predictions_dir", "predictions_topic", "smooth", "smoother")


def lightning_cli(argv: Sequence[str] | None, run: bool = True, instantiate: bool = True,
                  exit_on_error: bool = True) -> LightningCLI:
    """LightningCLI over TrajectoryTask and the MMAUD DataModule, as ``aaute fit|validate|test|predict`` builds it.

    ``argv`` None reads ``sys.argv``. With ``run=False`` the argument list has no subcommand and the
    caller drives ``cli.trainer`` (the benchmark runner does); with ``instantiate=False`` the
    arguments are only parsed and checked (``cli.config``), nothing is built. With
    ``exit_on_error=False`` a bad argument raises ``argparse.ArgumentError`` instead of exiting.
    """
    from lightning.pytorch.cli import LightningCLI

    from datamodules.mmaud import MMAUDDataModule
    from zoo.cli import checkpoint_args
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
                checkpoint_args.load_pending(self.model, self.pending_weights)

        def _parse_ckpt_path(self) -> None:
            # Lightning merges a checkpoint's hyperparameters over the command line; where this run writes
            # its outputs and how it smooths them are this run's settings, not the trained model's
            subcommand = self.config.get("subcommand")
            init_args = self.config[subcommand].get("model", {}).get("init_args") if subcommand else None
            given = {key: init_args.get(key) for key in RUN_SETTINGS} if init_args is not None else {}
            if subcommand:  # a checkpoint of another net is refused, not silently swapped in
                self.pending_weights = checkpoint_args.check_run(subcommand, self.config[subcommand])
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
