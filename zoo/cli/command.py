"""The ``aaute`` command: the data subcommands, the zoo's own, and LightningCLI's ``fit|validate|test|predict``.

The parser is composed, in this order, of :mod:`datamodules.cli`'s subcommands (``simulate``, ``info``,
``convert``, ``label``, ``audio``), the zoo's (``smooth``, ``track``, ``weights``, ``import-checkpoint``,
``export``) and those a caller adds (the benchmarks', :mod:`benchmarks.cli`). Every run goes through
:func:`datamodules.cli.run_guarded`, the one error policy of the command.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from datamodules.cli import AddCommands, run_guarded, run_parsed
from datamodules.cli import build_parser as data_parser
from zoo.cli import smooth, track, weights
from zoo.cli.lightning import LIGHTNING_COMMANDS, lightning_main


def add_commands(sub: argparse._SubParsersAction) -> None:
    """The zoo's subcommands: ``smooth``, ``track``, ``weights list|register``, ``import-checkpoint``, ``export``."""
    smooth.add_command(sub)
    track.add_command(sub)
    weights.add_commands(sub)


def build_parser(extra: AddCommands | None = None) -> argparse.ArgumentParser:
    """The ``aaute`` parser: the data and zoo subcommands, plus those ``extra`` adds (the benchmarks' own)."""

    def zoo_and_extra(sub: argparse._SubParsersAction) -> None:
        add_commands(sub)
        if extra is not None:
            extra(sub)

    return data_parser(zoo_and_extra)


def _run(argv: list[str], extra: AddCommands | None, from_sys_argv: bool) -> int:
    if argv and argv[0] in LIGHTNING_COMMANDS:
        lightning_main(None if from_sys_argv else argv)
        return 0
    return run_parsed(build_parser(extra), argv)


def main(argv: Sequence[str] | None = None, extra: AddCommands | None = None) -> int:
    """Run one ``aaute`` subcommand; ``extra`` adds subcommands (see :mod:`benchmarks.cli`).

    Project errors (:data:`datamodules.cli.USER_ERRORS`) print one line and return 2; Ctrl-C prints one
    line and returns 130. With ``--debug`` (anywhere on the command line) or ``AAUTE_DEBUG=1`` both raise
    with their traceback.
    """
    return run_guarded(argv, lambda words, from_sys_argv: _run(words, extra, from_sys_argv))
