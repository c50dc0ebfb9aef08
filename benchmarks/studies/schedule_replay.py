"""What a memory budget costs a suite in time, estimated from a finished run without running it again.

The train-and-test stage of ``--suite`` is replayed with the launcher's own choices
(:func:`benchmarks.scheduling.simulate_schedule`), each job taking its ``wall_time_s`` and expecting its
``peak_rss_mb`` from ``--results`` (a finished run of that suite): in the suite's order without a budget (the
launcher before it had one), then with ``--memory-gb`` (default: the suite's ``launcher.memory_gb``) twice, in
the suite's order with the suite's hints (a fresh clone's first run) and longest first with the measured peaks
(a run after this one). It prints the stage's length and the highest sum of expected peaks of the jobs running
together, and the start times of the last replay. Wall times are measured inside the jobs' processes, so the
lengths leave out the few seconds each process takes to start; their differences are the budget's cost.

    python -m benchmarks.studies.schedule_replay --suite configs/benchmark/quick.yaml \\
        --results demo_out/benchmark/results.csv
"""

from __future__ import annotations

import argparse
from pathlib import Path

from benchmarks.results import latest, read_results
from benchmarks.scheduling import DEFAULT_JOB_GB, expected_peaks, longest_first, simulate_schedule
from benchmarks.suite import expand_jobs, load_suite


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", type=Path, required=True, help="the suite YAML")
    parser.add_argument("--results", type=Path, required=True, help="results.csv of a finished run of that suite")
    parser.add_argument("--memory-gb", type=float, help="the budget (default: the suite's launcher.memory_gb)")
    parser.add_argument("--parallel", type=int, help="jobs at once (default: the suite's launcher.parallel)")
    args = parser.parse_args(argv)
    suite = load_suite(args.suite)
    budget = args.memory_gb if args.memory_gb is not None else suite.launcher["memory_gb"]
    if budget is None:
        parser.error(f"{args.suite} has no launcher.memory_gb: give --memory-gb")
    parallel = args.parallel or int(suite.launcher["parallel"])
    frame = latest(read_results(args.results))
    rows = frame[(frame["suite"] == suite.name) & (frame["status"] == "ok")].set_index("job_id")
    jobs = [job for job in expand_jobs(suite) if job.kind != "profile"]
    missing = [job.job_id for job in jobs if job.job_id not in rows.index]
    jobs = [job for job in jobs if job.job_id in rows.index]
    durations = {job.job_id: float(rows.loc[job.job_id, "wall_time_s"]) for job in jobs}
    peaks = expected_peaks(jobs, args.results, suite.launcher["job_memory_gb"] or DEFAULT_JOB_GB)
    hints = expected_peaks(jobs, Path("/nonexistent/results.csv"), suite.launcher["job_memory_gb"] or DEFAULT_JOB_GB)
    order = [job.job_id for job in jobs]
    longest = [job.job_id for job in longest_first(jobs, args.results)]
    print(f"{len(jobs)} jobs of suite {suite.name}, {parallel} at once"
          + (f" (not in the results, left out: {', '.join(missing)})" if missing else ""))
    free = simulate_schedule(order, durations, peaks, parallel, None)
    print(f"suite order, no budget: {free[0]:.0f} s, highest summed expected peak {free[1]:.2f} GB (measured)")
    for name, start_order, expected in (("suite order, hints", order, hints),
                                        ("longest first, measured", longest, peaks)):
        length, highest, starts = simulate_schedule(start_order, durations, expected, parallel, budget)
        print(f"{name}, budget {budget:g} GB: {length:.0f} s ({length - free[0]:+.0f} s, "
              f"{100 * (length / free[0] - 1):+.0f} %), highest summed expected peak {highest:.2f} GB")
    for job_id, start in sorted(starts.items(), key=lambda item: item[1]):
        print(f"  {start:7.0f} s  {job_id:36s} {durations[job_id]:6.0f} s  {peaks[job_id].gb:.2f} GB measured")


if __name__ == "__main__":
    main()
