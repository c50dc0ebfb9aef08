"""Measuring and reporting: profiler, benchmark runner, leaderboard; one-off studies in ``benchmarks.studies``."""
