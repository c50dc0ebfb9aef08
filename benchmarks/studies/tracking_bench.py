"""Speed of ``aaute track`` on a simulated recording: end to end, and per stage.

``python -m benchmarks.studies.tracking_bench [--seconds 60] [--weights FILE] [--threads 1] [--batch 1 8]`` simulates
one recording (kept in ``--data``, reused when it exists) and tracks it as fast as possible with the student
(fixed random weights, seed 0, unless ``--weights`` names trained ones: speed does not depend on the values),
once per net batch size. It prints the tracker's reports (updates, median / p95 latency from a block's arrival
to its line, speed against real time in wall and CPU time, threads) and the load average, then the median time
per update of each stage measured alone on the same audio: the incremental mel front end, the same maps
recomputed from scratch by the offline recipe, the net, and the smoother.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger(__name__)


def _recording(data: Path, seconds: float) -> Path:
    from datamodules.simulate.simulator import SimulationConfig, recording_path, simulate_dataset

    path = recording_path(data, 7, 0)
    if not path.is_file():
        simulate_dataset(data, 1, SimulationConfig(duration=seconds, camera=False), seed=7, progress=False)
    return path


def _weights(path: Path | None, out: Path) -> Path:
    if path is not None:
        return path
    from zoo.registry import get_model
    from zoo.weights import save_weights_file

    target = out / "student_random_seed0.pt"
    if not target.is_file():
        torch.manual_seed(0)
        save_weights_file(get_model("student"), target, net_kwargs={})
    return target


class _Discard:
    def write(self, row) -> None:
        pass


def _median_ms(values: list[float]) -> float:
    return float(np.median(values) * 1e3)


def stage_times(model, audio: np.ndarray, rate: float) -> dict[str, float]:
    """Median ms per update of each stage alone, over the windows of ``audio`` (channels x samples)."""
    from datamodules.features import IncrementalMel, mel_features
    from zoo.deploy.tracking import HOP_SECONDS
    from zoo.smoothing import OnlineSmoother

    block, window = int(round(HOP_SECONDS * rate)), int(round(model.window_seconds * rate))
    front = IncrementalMel(model.recipe, rate, audio.shape[0], window)
    smoother = OnlineSmoother("robust", lag=0.0)
    incremental, offline, net, smooth = [], [], [], []
    for k in range(audio.shape[1] // block):
        stop = (k + 1) * block
        front.push(audio[:, stop - block:stop])
        if stop < window:
            continue
        start = time.perf_counter()
        features = front.features()
        incremental.append(time.perf_counter() - start)
        start = time.perf_counter()
        mel_features(audio[:, stop - window:stop], rate, model.recipe)
        offline.append(time.perf_counter() - start)
        start = time.perf_counter()
        with torch.inference_mode():
            position = model.net({"audio_mel": features[None]})["position"][0].double().numpy()
        net.append(time.perf_counter() - start)
        start = time.perf_counter()
        smoother.update(stop / rate, position)
        smooth.append(time.perf_counter() - start)
    return {"incremental front end": _median_ms(incremental), "offline recipe per window": _median_ms(offline),
            "net": _median_ms(net), "smoother": _median_ms(smooth),
            "frames computed / used": front.computed / max(front.used, 1)}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="length of the simulated recording")
    parser.add_argument("--data", type=Path, default=Path("demo_out/tracking_bench"), help="where it is kept")
    parser.add_argument("--weights", type=Path, help="student weights (default: fixed random weights, seed 0)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 8], help="windows per net call, one run each")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(args.threads)

    from datamodules.formats import open_recording
    from datamodules.streams import RecordingSource
    from zoo.deploy.tracking import Tracker, load_tracking_model

    args.data.mkdir(parents=True, exist_ok=True)
    path = _recording(args.data, args.seconds)
    model = load_tracking_model(weights=_weights(args.weights, args.data))
    load = os.getloadavg()
    print(f"recording {path}, model {model.name} ({model.recipe.name}), torch threads {torch.get_num_threads()}, "
          f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}, load average {load[0]:.2f} on "
          f"{os.cpu_count()} CPUs")
    for batch in args.batch:
        report = Tracker(model, RecordingSource(path), [_Discard()], batch=batch).run()
        print(f"end to end, batch {batch}: {report.summary()}")
    audio = open_recording(path).audio
    samples = audio.read(0, audio.num_samples)
    for name, value in stage_times(model, samples, audio.sample_rate).items():
        print(f"  {name}: {value:.3f}" + (" ms per update" if "/" not in name else ""))


if __name__ == "__main__":
    main()
