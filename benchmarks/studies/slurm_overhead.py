"""Scheduling overhead of the Slurm launcher against the local one, on the same tiny jobs.

Run ``python -m benchmarks.studies.slurm_overhead`` on a machine with a Slurm cluster (for a one-node one:
``scripts/local_slurm.sh up``). A suite of ``--jobs`` constant-position jobs (each a few seconds: start
Python, import torch and Lightning, read three 4 s simulated flights, score them) runs four times, twice with the
local launcher and twice with the Slurm launcher (one job array), all ``--parallel`` jobs at once, in the order
local, Slurm, Slurm, local (so a change in the machine's load over the run weighs on both alike). Per
launcher, the seconds a job costs outside its own work are stage time x parallel / jobs - the mean wall time
of a job inside its process (process start, imports, submission, scheduling, collecting the result); the
Slurm launcher's overhead per job is its figure minus the local launcher's.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[2]


def write_suite(folder: Path, jobs: int, parallel: int, data: Path) -> Path:
    """A suite of ``jobs`` constant-position jobs (seeds x ground-truth target) on simulated flights."""
    suite = {
        "name": "slurm_overhead", "out": str(folder / "out"),
        "data": {"description": "three 4 s simulated flights", "kind": "simulated",
                 "config": str(REPO / "configs/data/sim.yaml"), "root": str(data),
                 "simulate": {"sequences": 3, "seconds": 4, "seed": 11}, "label": {"workers": 1},
                 "init_args": {"window_seconds": 1.0, "cache_dir": str(data.parent / "cache")}},
        "protocols": {"by_sequence": {"train": ["sim11-0000-avata"], "val": ["sim11-0001-m300"],
                                       "test": ["sim11-0002-mavic2"]}},
        "lights": ["ideal"], "seeds": list(range(jobs)), "smoothing": False, "constant": ["gt"],
        "models": [{"model": "student", "config": str(REPO / "configs/model/student.yaml")}],
        "profile": False,
        "launcher": {"kind": "local", "parallel": parallel, "threads_per_job": 1, "timeout_min": 30},
    }
    path = folder / "suite.yaml"
    path.write_text(yaml.safe_dump(suite))
    return path


def measure(jobs: int, parallel: int, work: Path, repeats: int = 2) -> list[dict[str, float | str]]:
    """Both launchers on the same suite (``repeats`` 2: local, slurm, slurm, local); one table row each."""
    from benchmarks.results import read_results
    from benchmarks.runner import run_suite
    from benchmarks.suite import load_suite

    data = work / "data"
    runs: dict[str, list[tuple[float, float]]] = {"local": [], "slurm": []}
    order = ("local", "slurm", "slurm", "local")[: 2 * repeats] if repeats <= 2 else ("local", "slurm") * repeats
    for index, launcher in enumerate(order):
        folder = work / f"{launcher}{index}"
        folder.mkdir(parents=True, exist_ok=True)
        suite = load_suite(write_suite(folder, jobs, parallel, data))
        summary = run_suite(suite, launcher=launcher, only=["constant"])
        if summary.failed:
            raise SystemExit(f"{launcher}: {len(summary.failed)} job(s) failed; see {suite.results_path}")
        wall = float(read_results(suite.results_path)["wall_time_s"].mean())
        runs[launcher].append((summary.stages["train_test"], wall))
    rows: list[dict[str, float | str]] = []
    for launcher, pairs in runs.items():
        stage = sum(p[0] for p in pairs) / len(pairs)
        wall = sum(p[1] for p in pairs) / len(pairs)
        rows.append({"launcher": launcher, "jobs": jobs, "stage_s": stage, "job_wall_s": wall,
                     "outside_s": stage * parallel / jobs - wall})
    for row in rows:
        row["overhead_per_job_s"] = float(row["outside_s"]) - float(rows[0]["outside_s"])
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=20, help="jobs in the suite")
    parser.add_argument("--parallel", type=int, default=2, help="jobs at once, both launchers")
    parser.add_argument("--repeats", type=int, default=2, help="runs per launcher (2: local, slurm, slurm, local)")
    parser.add_argument("--work", type=Path, help="working folder (default: a temporary one)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        rows = measure(args.jobs, args.parallel, args.work or Path(tmp), args.repeats)
    print(f"{args.jobs} constant-position jobs, {args.parallel} at once, 1 thread per job")
    print(f"| launcher | jobs | stage, mean of {args.repeats} (s) | job wall, mean (s) | outside the job, per job (s) "
          "| overhead vs local, per job (s) |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        print(f"| {row['launcher']} | {row['jobs']} | {row['stage_s']:.1f} | {row['job_wall_s']:.1f} "
              f"| {row['outside_s']:.1f} | {row['overhead_per_job_s']:+.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
