"""One-off studies: each answers one question with a printed table; they are not part of the benchmark product.

Each runs as ``python -m benchmarks.studies.<study> [options]`` (``--help`` lists the options). No study imports
another (what two of them share is in :mod:`benchmarks.studies.common`), and the product (suite, runner, jobs,
results, leaderboard, plots, profiler, cli) imports no study.

One line per study: its command (after ``python -m benchmarks.studies.``), the question it answers, and the README
section that quotes its numbers (or only its command):

- ``phase_bench --data DIR``: srp_phat's error, detections and speed on flights? "Train and test a model", 1st table
- ``phase_headroom --train DIR --test DIR``: what could re-scoring srp_phat's candidates add? same, headroom table
- ``audio_probe --data DIR``: how much position do the band levels carry? "Train and test a model", command only
- ``student_check --data DIR``: does the student learn (alpha 1, alpha 0, constant)? same section, command only
- ``smoothing_bench [--accuracy]``: the smoothers' error, coverage, speed? "Train and test a model", commands only
- ``teacher_bench [--quick]``: the LiDAR teacher's error, coverage, speed, memory? "Pseudo-labels from LiDAR", command
- ``tracking_bench --seconds 60 [--config configs/model/srp_phat.yaml]``: how fast is ``aaute track``, end to end
  and per stage (mel or live phase)? "Real-time tracking"
- ``live_phase_accuracy --data DIR``: live srp_phat's raw and smoothed error and the std's coverage?
  "Real-time tracking", phase table
- ``live_phase_calibration --data DIR``: the ``srp_phat`` online smoother preset from development flights?
  "Real-time tracking", command only
- ``clock_sensitivity [--identifiability]``: what clock error between nodes costs srp_phat? "Train and test a
  model", clock table
- ``clock_calibration --condition NAME SHARED_DIR CLOCKS_DIR``: how close the self-calibrated node clocks come,
  and srp_phat's E with them? same section, self-calibration table
- ``clock_stretches --data CLOCKS_DIR [--seconds 10 30]``: how close the clocks estimated from one stretch of S
  seconds come (as ``aaute track`` estimates them)? same section, self-calibration paragraph
- ``live_clock_calibration --condition NAME SHARED_DIR CLOCKS_DIR``: the live self-calibration's offsets, E and
  cost? same section, live self-calibration table
- ``datamodule_bench --data DIR``: the DataModule's feature, cache and epoch speed and memory? not in the README
- ``recording_bench``: the recording pipeline's speed and size? ``make bench``; "Tests, lint, benchmarks", command only
"""
