"""Speed and memory of the DataModule: feature extraction, cache build, cached epochs.

Run ``python -m benchmarks.studies.datamodule_bench --data DIR`` on simulated (or real) recordings. It
prints: the time to turn one 2 s window into each recipe's features on one thread (target for the
student recipe: under 2 ms, i.e. 1000x real time), the cache build rate, the samples per second a
cached epoch delivers with 0 and 2 DataLoader workers (target: 5,000 on 2 cores) and the memory
after each stage: anonymous (the process's own) and file-backed (pages of the memory-mapped cache
and recordings, which the kernel reclaims under pressure, so they do not bound the dataset size).
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _memory() -> str:
    """Current anonymous and file-backed resident memory (Linux), as text."""
    try:
        fields = dict(line.split(":", 1) for line in Path("/proc/self/status").read_text().splitlines())
    except OSError:
        return "n/a"
    mb = {k: int(fields[k].split()[0]) / 1024 for k in ("RssAnon", "RssFile") if k in fields}
    return ", ".join(f"{k[3:].lower()} {v:.0f} MB" for k, v in mb.items())


def window_times(data: Path, repeats: int) -> dict[str, float]:
    """Median milliseconds per 2 s window for each mel recipe (one thread)."""
    from datamodules.features import MEL_RECIPES, audio_window, mel_features
    from datamodules.formats import open_recording
    from datamodules.mmaud import discover

    torch.set_num_threads(1)
    audio = open_recording(discover(data)[0]).audio
    result = {}
    for name, recipe in MEL_RECIPES.items():
        t_end = audio.t0 + 3.0
        mel_features(audio_window(audio, t_end, recipe, 2.0), audio.sample_rate, recipe)  # warm-up
        times = []
        for k in range(repeats):
            window = audio_window(audio, t_end + 0.1 * k, recipe, 2.0)
            start = time.perf_counter()
            mel_features(window, audio.sample_rate, recipe)
            times.append(time.perf_counter() - start)
        result[name] = float(np.median(times) * 1e3)
    return result


def loader_rate(data: Path, cache: Path, workers: int, epochs: int) -> tuple[float, float, int]:
    """(cache build seconds, samples per second of a cached epoch, samples) for the student recipe."""
    from datamodules.mmaud import MMAUDDataModule

    module = MMAUDDataModule(str(data), split={"seed": 0, "val": 0.0, "test": 0.0}, inputs={"audio_mel": "aaute"},
                             batch_size=32, num_workers=workers, cache_dir=str(cache))
    start = time.perf_counter()
    module.prepare_data()
    build = time.perf_counter() - start
    loader = module.train_dataloader()
    count = 0
    start = time.perf_counter()
    for _ in range(epochs):
        for batch in loader:
            count += len(batch["gt"])
    return build, count / (time.perf_counter() - start), len(loader.dataset)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--epochs", type=int, default=2)
    args = parser.parse_args(argv)

    print("== feature extraction, one 2 s window, 1 thread (median ms)")
    for name, ms in window_times(args.data, args.repeats).items():
        print(f"   {name:<12} {ms:6.2f} ms  ({2000.0 / ms:6.0f}x real time)")
    with tempfile.TemporaryDirectory(prefix="aaute-cache-") as cache:
        for workers in (0, 2):
            build, rate, samples = loader_rate(args.data, Path(cache), workers, args.epochs)
            print(f"== cached epochs, {workers} workers: {rate:8.0f} samples/s over {samples} samples "
                  f"(cache {'built' if workers == 0 else 'reused'} in {build:.1f} s); memory: {_memory()}")
    print(f"== peak resident memory {_peak_rss_mb():.0f} MB (anonymous and file-backed)")


if __name__ == "__main__":
    main()
