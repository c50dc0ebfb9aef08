"""Speed and memory of converting a ROS 1 bag of several audio nodes to MCAP (``aaute convert``).

Writes a bag like MMAUD V1's audio: ``--nodes`` mono S16LE ``audio_common_msgs/AudioData`` topics
``/audio1/audio`` ... at 48 kHz in 0.1 s messages, stamped only by receive times (a few ms of
jitter), ``--seconds`` long; then converts it in a child process with single-threaded numerical
libraries and prints the wall time, the CPU time, the real-time factor and the child's peak
resident memory (target: a 10-minute four-node bag at least 5x faster than real time on one core,
memory flat in the recording's length: run two lengths to see it).

Run: ``python -m benchmarks.studies.bag_conversion --seconds 600 60 [--compression bz2]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RATE = 48000
MESSAGE = RATE // 10
T0_NS = 1_692_845_357_100_000_000

CHILD = """
import json, resource, sys, time
from datamodules.convert import convert
wall, cpu = time.perf_counter(), time.process_time()
convert(sys.argv[1], sys.argv[2])
print(json.dumps({"wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def write_node_bag(path: Path, seconds: float, nodes: int, compression: str | None = None, seed: int = 0) -> None:
    """A bag of ``nodes`` mono AudioData topics (noise), ``seconds`` long, receive-time stamps with jitter."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("uint8[] data", "audio_common_msgs/msg/AudioData"))
    audio_data = store.types["audio_common_msgs/msg/AudioData"]
    rng = np.random.default_rng(seed)
    count = int(round(seconds * 10))
    writer = Writer(path)
    if compression:
        writer.set_compression(getattr(Writer.CompressionFormat, compression.upper()))
    with writer:
        connections = [writer.add_connection(f"/audio{n + 1}/audio", "audio_common_msgs/msg/AudioData",
                                             typestore=store) for n in range(nodes)]
        for k in range(count):
            for n, connection in enumerate(connections):
                codes = rng.integers(-3000, 3000, MESSAGE, dtype=np.int16)
                raw = store.serialize_ros1(audio_data(data=np.frombuffer(codes.tobytes(), np.uint8)),
                                           "audio_common_msgs/msg/AudioData")
                stamp = T0_NS + (k + 1) * 100_000_000 + int(rng.integers(0, 3_000_000)) + n * 1000
                writer.write(connection, stamp, raw)


def measure(seconds: float, nodes: int, folder: Path, compression: str | None = None) -> dict:
    bag = folder / f"rig_{int(seconds)}s.bag"
    start = time.perf_counter()
    write_node_bag(bag, seconds, nodes, compression)
    written_s = time.perf_counter() - start
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", CHILD, str(bag), str(folder / f"rig_{int(seconds)}s.mcap")],
                         env=env, check=True, capture_output=True, text=True)
    row = json.loads(out.stdout.strip().splitlines()[-1])
    row.update(seconds=seconds, nodes=nodes, bag_mb=bag.stat().st_size / 1e6, bag_write_s=written_s,
               realtime_factor=seconds / row["wall_s"])
    return row


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, nargs="+", default=[600.0, 60.0])
    parser.add_argument("--nodes", type=int, default=4)
    parser.add_argument("--compression", choices=["bz2", "lz4"], help="chunk compression (MMAUD V1's bags: bz2)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        for seconds in args.seconds:
            row = measure(seconds, args.nodes, Path(tmp), args.compression)
            kind = args.compression or "uncompressed"
            print(f"{row['nodes']} nodes x {row['seconds']:.0f} s ({row['bag_mb']:.0f} MB {kind} bag): convert wall "
                  f"{row['wall_s']:.1f} s, CPU {row['cpu_s']:.1f} s, {row['realtime_factor']:.1f}x real time, "
                  f"peak RSS {row['peak_rss_mb']:.0f} MB (1 thread)")


if __name__ == "__main__":
    main()
