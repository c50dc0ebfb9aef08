"""Scheduling overhead of the Slurm launcher against the local one, on the same tiny jobs.

Run ``python -m benchmarks.studies.slurm_overhead`` on a machine with a Slurm cluster (for a one-node one:
``scripts/local_slurm.sh up``). A suite of ``--jobs`` constant-position jobs (each a few seconds: start
Python, import torch and Lightning, read three 4 s simulated flights, score them) runs twice, with the
local launcher and with the Slurm launcher (one job array), both ``--parallel`` jobs at once; the table
gives each launcher's stage time, the mean wall time of a job inside its process, and the overhead per
job: (Slurm stage time - local stage time) x parallel / jobs, the seconds of scheduling each job costs.
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


def measure(jobs: int, parallel: int, work: Path) -> list[dict[str, float | str]]:
    """Both launchers on the same suite (in separate output folders); one table row each."""
    from benchmarks.results import read_results
    from benchmarks.runner import run_suite
    from benchmarks.suite import load_suite

    data = work / "data"
    rows = []
    for launcher in ("local", "slurm"):
        folder = work / launcher
        folder.mkdir(parents=True, exist_ok=True)
        suite = load_suite(write_suite(folder, jobs, parallel, data))
        summary = run_suite(suite, launcher=launcher, only=["constant"])
        if summary.failed:
            raise SystemExit(f"{launcher}: {len(summary.failed)} job(s) failed; see {suite.results_path}")
        results = read_results(suite.results_path)
        rows.append({"launcher": launcher, "jobs": len(summary.done), "stage_s": summary.stages["train_test"],
                     "job_wall_s": float(results["wall_time_s"].mean())})
    local, slurm = rows
    overhead = (slurm["stage_s"] - local["stage_s"]) * parallel / jobs
    for row in rows:
        row["overhead_per_job_s"] = overhead if row is slurm else 0.0
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=20, help="jobs in the suite")
    parser.add_argument("--parallel", type=int, default=2, help="jobs at once, both launchers")
    parser.add_argument("--work", type=Path, help="working folder (default: a temporary one)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        rows = measure(args.jobs, args.parallel, args.work or Path(tmp))
    print(f"{args.jobs} constant-position jobs, {args.parallel} at once, 1 thread per job")
    print("| launcher | jobs | stage (s) | job wall, mean (s) | scheduling overhead per job (s) |")
    print("|---|---|---|---|---|")
    for row in rows:
        print(f"| {row['launcher']} | {row['jobs']} | {row['stage_s']:.1f} | {row['job_wall_s']:.1f} "
              f"| {row['overhead_per_job_s']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
