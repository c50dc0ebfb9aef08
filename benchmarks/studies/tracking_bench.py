"""Speed of ``aaute track`` on a simulated recording: end to end, and per stage.

With ``--config configs/model/srp_phat.yaml`` it measures the live phase localiser instead: the tracker's
report (batch 1, latency from block arrival to written row), then the median and p95 ms per update of each
stage alone (the streaming phase front end, the same features recomputed by the offline recipe, the
coarse-to-fine search, the gate, the gated smoother), and where the search's time goes. The detection
threshold is prepared (or read from the cache) before the clock starts, as ``aaute track`` does.

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


def _p95_ms(values: list[float]) -> float:
    return float(np.percentile(values, 95) * 1e3)


def phase_stage_times(model, source) -> dict[str, tuple[float, float, float]]:
    """Median and p95 wall ms and median CPU ms per update of each stage of the live phase localiser alone,
    over ``source``'s windows (CPU time counts this process only: on a shared machine, its own work)."""
    from datamodules.features import IncrementalPhase, PhaseWindows
    from datamodules.recording import ArrayAudio
    from zoo.deploy.live_phase import GatedSmoothing, PhaseRow, prepare_threshold
    from zoo.smoothing import OnlineSmoother

    net = model.net
    mics = torch.from_numpy(source.mic_positions.astype(np.float32)).double()
    prepare_threshold(net, mics)
    threshold = net.threshold(mics)
    block = int(round(0.1 * source.sample_rate))
    front = IncrementalPhase(model.recipe, source.sample_rate, source.channels)
    gated = GatedSmoothing(OnlineSmoother(model.live_smoother.get("preset", "robust")))
    samples = source.audio.read(0, source.audio.num_samples)
    stops = np.arange(block, samples.shape[1] + 1, block)
    stops = stops[stops >= front.window]
    offline = PhaseWindows(ArrayAudio(samples, source.sample_rate, 0.0, source.mic_positions), model.recipe,
                           stops / source.sample_rate)
    names = ("front end (streaming)", "front end (offline recipe, per window)", "search", "gate", "smoother")
    times: dict[str, list[float]] = {name: [] for name in names}  # wall seconds
    cpu: dict[str, list[float]] = {name: [] for name in names}  # CPU seconds of this process

    def clock() -> tuple[float, float]:
        return time.perf_counter(), time.process_time()

    def record(name: str, start: tuple[float, float]) -> None:
        wall, process = clock()
        times[name].append(wall - start[0])
        cpu[name].append(process - start[1])

    done = 0
    for k, stop in enumerate(stops):
        front.push(samples[:, done:stop])
        done = stop
        start = clock()
        features = front.features()
        record(names[0], start)
        start = clock()
        offline(k)
        record(names[1], start)
        start = clock()
        with torch.inference_mode():
            points, peak = net.search.peaks(features[None].permute(0, 2, 1, 3), mics)
        record(names[2], start)
        start = clock()
        hit = peak > threshold
        position, detected = net.hold_or_fallback(net.window_positions(points, hit), hit.any(dim=1),
                                                  torch.zeros(1, dtype=torch.long),
                                                  torch.tensor([stop / source.sample_rate], dtype=torch.float64))
        state = net.gate.states[0]
        record(names[3], start)
        start = clock()
        gated.add(PhaseRow(stop / source.sample_rate, position[0].double().numpy(), float(peak.max() / threshold),
                           bool(detected[0]), state))
        record(names[4], start)
    return {name: (_median_ms(times[name]), _p95_ms(times[name]), _median_ms(cpu[name])) for name in names}


def phase_main(args: argparse.Namespace, path: Path) -> None:
    """The live phase localiser's end-to-end report and stage times on the recording at ``path``."""
    from datamodules.streams import RecordingSource
    from zoo.deploy.live_phase import PhaseTracker, load_phase_model

    model = load_phase_model(config=args.config, source=RecordingSource(path))
    load = os.getloadavg()
    print(f"recording {path}, model {model.name} ({model.recipe.name}) from {args.config}, torch threads "
          f"{torch.get_num_threads()}, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}, load average "
          f"{load[0]:.2f} on {os.cpu_count()} CPUs")
    for name, (median, p95, cpu) in phase_stage_times(model, RecordingSource(path)).items():
        print(f"  {name}: median {median:.2f} ms, p95 {p95:.2f} ms wall, median {cpu:.2f} ms CPU per update")
    source = RecordingSource(path)
    model = load_phase_model(config=args.config, source=source)
    report = PhaseTracker(model, source, [_Discard()], batch=1).run()
    print(f"end to end, batch 1: {report.summary()}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="length of the simulated recording")
    parser.add_argument("--data", type=Path, default=Path("demo_out/tracking_bench"), help="where it is kept")
    parser.add_argument("--weights", type=Path, help="student weights (default: fixed random weights, seed 0)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 8], help="windows per net call, one run each")
    parser.add_argument("--config", type=Path, help="a phase model's config (configs/model/srp_phat.yaml): measure "
                                                    "the live phase localiser instead of the student")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(args.threads)

    from datamodules.formats import open_recording
    from datamodules.streams import RecordingSource
    from zoo.deploy.tracking import Tracker, load_tracking_model

    args.data.mkdir(parents=True, exist_ok=True)
    path = _recording(args.data, args.seconds)
    if args.config is not None:
        phase_main(args, path)
        return
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
