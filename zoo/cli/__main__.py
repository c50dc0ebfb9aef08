"""``python -m zoo.cli``: the ``aaute`` command without the benchmarks' subcommands."""

from zoo.cli.command import main

raise SystemExit(main())
