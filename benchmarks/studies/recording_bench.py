"""Speed and size of the recording pipeline: simulate, write, and read windows back.

Run ``python -m benchmarks.studies.recording_bench`` (``make bench``). It measures, on one core
(single-threaded numerical libraries):

1. the time to simulate one minute of all sensors (target: under one minute), per stage;
2. the size on disk of a ten-minute recording at default settings (target: under 300 MB),
   per topic;
3. the time to read a 2 s audio window from that ten-minute recording (target: under 50 ms),
   cold (including opening the file) and for random windows of an open recording.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import logging  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402


class _StageTimes(logging.Handler):
    """Collects the simulator's per-stage timing messages."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.stages: dict[str, float] = {}

    def emit(self, record: logging.LogRecord) -> None:
        if getattr(record, "stage", None):
            self.stages[record.stage] = record.seconds


def _simulate(seconds: float, seed: int):
    from datamodules.simulate.simulator import SimulationConfig, simulate_recording

    handler = _StageTimes()
    logger = logging.getLogger("datamodules.simulate.simulator")
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    start_wall, start_cpu = time.perf_counter(), time.process_time()
    recording = simulate_recording(SimulationConfig(duration=seconds), seed=seed, index=seed % 5)
    wall, cpu = time.perf_counter() - start_wall, time.process_time() - start_cpu
    logger.removeHandler(handler)
    return recording, wall, cpu, handler.stages


def _bytes_per_topic(path: Path) -> dict[str, int]:
    from datamodules.formats.mcap_file import McapIndex

    index = McapIndex(path)
    sizes: dict[str, int] = defaultdict(int)
    for chunk in index.summary.chunk_indexes:
        topics = sorted({index.summary.channels[c].topic for c in chunk.message_index_offsets})
        sizes["+".join(topics)] += chunk.compressed_size
    return dict(sizes)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minute-seconds", type=float, default=60.0)
    parser.add_argument("--long-seconds", type=float, default=600.0)
    parser.add_argument("--windows", type=int, default=50)
    parser.add_argument("--out", type=Path, default=None, help="keep the long recording here")
    args = parser.parse_args(argv)

    from datamodules.formats import open_recording
    from datamodules.formats.mcap_file import write_mcap

    print(f"== simulate {args.minute_seconds:.0f} s of all sensors (1 thread)")
    _, wall, cpu, stages = _simulate(args.minute_seconds, seed=1)
    for stage, seconds in stages.items():
        print(f"   {stage:<12} {seconds:7.2f} s")
    print(f"   total        {wall:7.2f} s wall, {cpu:.2f} s CPU  ->  {wall / args.minute_seconds:.2f} s per s")

    out_dir = args.out or Path(tempfile.mkdtemp(prefix="aaute-bench-"))
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "long.mcap"
    print(f"== simulate and write {args.long_seconds:.0f} s -> {path}")
    recording, wall, _, _ = _simulate(args.long_seconds, seed=2)
    start = time.perf_counter()
    write_mcap(recording, path, overwrite=True)
    write_s = time.perf_counter() - start
    size = path.stat().st_size
    print(f"   simulate {wall:.1f} s, write {write_s:.1f} s, size {size / 1e6:.1f} MB "
          f"({size / 1e6 * 600 / args.long_seconds:.1f} MB per 10 min)")
    for topic, nbytes in sorted(_bytes_per_topic(path).items(), key=lambda kv: -kv[1]):
        print(f"   {topic:<40} {nbytes / 1e6:8.1f} MB")
    del recording

    print(f"== read 2 s audio windows ({args.windows} random)")
    rng = np.random.default_rng(0)
    start = time.perf_counter()
    rec = open_recording(path)
    first_end = rec.audio.t0 + rec.audio.duration / 2
    rec.audio.window(first_end, 2.0)
    cold = time.perf_counter() - start
    times = []
    for t_end in rec.audio.t0 + rng.uniform(2.0, rec.audio.duration, args.windows):
        start = time.perf_counter()
        rec.audio.window(t_end, 2.0)
        times.append(time.perf_counter() - start)
    times_ms = np.array(times) * 1e3
    print(f"   cold (open + first window) {cold * 1e3:.1f} ms; random windows median {np.median(times_ms):.1f} ms, "
          f"max {times_ms.max():.1f} ms")
    if args.out is None:
        path.unlink()
        out_dir.rmdir()


if __name__ == "__main__":
    main()
