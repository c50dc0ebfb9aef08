"""The ``aaute`` command: the zoo's and the datamodules' subcommands plus ``profile``, ``benchmark``, ``leaderboard``.

This module sits at the top of the import graph (benchmarks -> zoo -> datamodules), so the
subcommands below it never import upward.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from zoo import cli as zoo_cli

log = logging.getLogger("aaute")


def _cmd_benchmark(args: argparse.Namespace) -> int:
    from benchmarks.runner import run_suite
    from benchmarks.suite import load_suite

    suite = load_suite(args.suite, {"data.root": args.data_root, "out": args.out,
                                    "launcher.memory_gb": args.memory_gb})  # checked like the suite's own
    if args.parallel is not None:
        suite.raw.setdefault("launcher", {})["parallel"] = args.parallel
    summary = run_suite(suite, rerun=args.rerun, launcher=args.launcher, only=args.only or None)
    stages = ", ".join(f"{name} {seconds:.0f} s" for name, seconds in summary.stages.items())
    log.info("suite %s: %d jobs run, %d failed, %d already finished, %.0f s (%s); results in %s", suite.name,
             len(summary.done), len(summary.failed), len(summary.skipped), summary.seconds, stages, summary.results)
    for job_id in summary.failed:
        log.error("job %s failed (its row in %s names the error and the log)", job_id, summary.results)
    return 1 if summary.failed or summary.busy else 0


#: subcommands whose modules are imported only when that subcommand runs (the profiler imports torch)
LAZY_COMMANDS = {
    "profile": ("benchmarks.profiler", "parameters, GMACs/FLOPs, latency and throughput of zoo models"),
    "leaderboard": ("benchmarks.leaderboard",
                    "render results.csv as tables (Markdown, CSV, LaTeX, HTML) and plots"),
}


def _run_lazy(module_name: str) -> Callable[[argparse.Namespace], int]:
    def run(args: argparse.Namespace) -> int:
        return importlib.import_module(module_name).run(args)

    return run


def add_commands(sub: argparse._SubParsersAction, command: str | None = None) -> None:
    """The benchmarks' subcommands; ``command``: the one that will run (only its module is imported)."""
    bench = sub.add_parser("benchmark", help="run a benchmark suite (models x protocols x seeds) into results.csv")
    bench.add_argument("--suite", required=True, type=Path, help="suite YAML, e.g. configs/benchmark/quick.yaml")
    bench.add_argument("--data.root", dest="data_root", help="the data root (overrides the suite's)")
    bench.add_argument("--out", help="output folder (overrides the suite's)")
    bench.add_argument("--launcher", choices=["local", "slurm", "debug"], help="overrides the suite's launcher")
    bench.add_argument("--parallel", type=int, help="jobs at once (overrides the suite's)")
    bench.add_argument("--memory-gb", type=float, help="summed expected peak memory of the jobs running at once "
                       "(overrides the suite's launcher.memory_gb)")
    bench.add_argument("--only", nargs="+", help="run only these job ids or models")
    bench.add_argument("--rerun", action="store_true", help="run finished jobs again")
    bench.set_defaults(func=_cmd_benchmark)

    for name, (module_name, help_text) in LAZY_COMMANDS.items():
        parser = sub.add_parser(name, help=help_text)
        if command in (None, name):
            importlib.import_module(module_name).add_arguments(parser)
        parser.set_defaults(func=_run_lazy(module_name))


def main(argv: Sequence[str] | None = None) -> int:
    words = list(sys.argv[1:] if argv is None else argv)
    command = next((word for word in words if word in LAZY_COMMANDS), None)
    return zoo_cli.main(argv, extra=lambda sub: add_commands(sub, command))


if __name__ == "__main__":
    raise SystemExit(main())
