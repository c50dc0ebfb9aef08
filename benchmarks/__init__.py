"""Measuring and reporting: profiler, benchmark runner, leaderboard and speed benchmarks."""
