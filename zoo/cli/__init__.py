"""The ``aaute`` command as the zoo composes it: one module per command group.

- :mod:`~zoo.cli.command`: the parser (the data subcommands of :mod:`datamodules.cli`, then the zoo's) and
  :func:`main`;
- :mod:`~zoo.cli.lightning`: ``fit|validate|test|predict`` (:func:`lightning_cli`), with
  :mod:`~zoo.cli.checkpoint_args` checking their ``--ckpt_path`` and ``--weights``;
- :mod:`~zoo.cli.smooth`, :mod:`~zoo.cli.track`: ``aaute smooth`` and ``aaute track``;
- :mod:`~zoo.cli.weights`: ``weights list|register``, ``import-checkpoint`` and ``export``.
"""

from zoo.cli.command import main
from zoo.cli.lightning import lightning_cli

__all__ = ["lightning_cli", "main"]
