"""How much position information does the audio carry? A supervised probe on band levels.

For windows ending at the label times, the probe computes the level of each microphone in
logarithmic frequency bands (absolute, and relative to the array mean, so inter-microphone level
differences are explicit), fits scikit-learn's gradient boosting to ground-truth positions on the
training sequences and reports E (mean Euclidean error, m) on the held-out test sequences, next to
the constant-position predictor. The split is the DataModule's, so the numbers sit beside
``benchmarks.studies.student_check``. A student that cannot beat this probe is limited by its recipe or
its training; a probe that cannot beat the constant means the recordings carry little position
information in those bands. Run: ``python -m benchmarks.studies.audio_probe --data DIR [DIR ...]``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from sklearn.ensemble import HistGradientBoostingRegressor
from threadpoolctl import threadpool_limits

from benchmarks.studies.common import held_out_split
from datamodules.formats import open_recording
from datamodules.mmaud import MMAUDDataModule, SequenceSamples

BAND_EDGES_HZ = np.geomspace(50.0, 20000.0, 25)  #: 24 bands, about 1/3 octave wide


def band_levels(samples: np.ndarray, sample_rate: float, edges: np.ndarray = BAND_EDGES_HZ) -> np.ndarray:
    """Per-microphone band levels (dB, arbitrary reference) of one window, shape 2 x channels x bands:
    absolute levels, then levels relative to the mean over microphones."""
    x = samples.astype(np.float64)
    spectrum = np.abs(np.fft.rfft(x * np.hanning(x.shape[1]), axis=1)) ** 2
    freqs = np.fft.rfftfreq(x.shape[1], 1.0 / sample_rate)
    bands = np.stack([spectrum[:, (freqs >= lo) & (freqs < hi)].sum(axis=1)
                      for lo, hi in zip(edges[:-1], edges[1:], strict=True)], axis=1)
    levels = 10.0 * np.log10(bands + 1e-20)
    return np.stack([levels, levels - levels.mean(axis=0, keepdims=True)])


def probe_features(sequences: list[SequenceSamples], window_seconds: float, stride: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Band levels (N x 2 x channels x bands) and ground truth (N x 3) every ``stride`` label times."""
    features, targets = [], []
    for sequence in sequences:
        audio = open_recording(sequence.path).audio
        start = audio.t0 + window_seconds
        for k in range(0, len(sequence), stride):
            t = float(sequence.times[k])
            if not sequence.gt_valid[k] or t < start or t > audio.t_end:
                continue
            features.append(band_levels(audio.window(t, window_seconds), audio.sample_rate))
            targets.append(sequence.gt[k])
    return np.asarray(features), np.asarray(targets)


def fit_and_score(train: tuple[np.ndarray, np.ndarray], test: tuple[np.ndarray, np.ndarray],
                  band_mask: np.ndarray, seed: int = 0) -> float:
    """Test E of one gradient-boosting regressor per axis on the bands in ``band_mask``.

    One OpenMP thread: on a few thousand windows the boosting's per-iteration parallel overhead
    outweighs its work (measured on 450 windows, 2 busy cores: 16 s of CPU with one thread, 104 s with two).
    """
    (x_train, y_train), (x_test, y_test) = train, test
    a = x_train[..., band_mask].reshape(len(x_train), -1)
    b = x_test[..., band_mask].reshape(len(x_test), -1)
    with threadpool_limits(limits=1, user_api="openmp"):
        prediction = np.stack([HistGradientBoostingRegressor(max_iter=300, random_state=seed)
                               .fit(a, y_train[:, k]).predict(b) for k in range(3)], axis=1)
    return float(np.linalg.norm(prediction - y_test, axis=1).mean())


def run(data: list[Path], seed: int = 0, window_seconds: float = 0.5, stride: int = 2,
        max_hz: float = 1200.0, split: dict | None = None) -> dict[str, float]:
    """Probe E below ``max_hz`` and over all bands, and the constant predictor's E, on the test split
    (``split`` as in :func:`benchmarks.studies.student_check.run`)."""
    module = MMAUDDataModule([str(d) for d in data], split=split or held_out_split(seed),
                             inputs={}, test_lights=["ideal"])
    module.setup("fit")
    train = probe_features(module.sequences["train"], window_seconds, stride)
    test = probe_features(module.sequences["test"], window_seconds, stride)
    if len(train[0]) == 0 or len(test[0]) == 0:
        raise ValueError(f"no labelled windows of {window_seconds} s in the train or test split of {data}")
    centres = np.sqrt(BAND_EDGES_HZ[:-1] * BAND_EDGES_HZ[1:])
    return {
        "constant_E": float(np.linalg.norm(test[1] - train[1].mean(axis=0), axis=1).mean()),
        "probe_E_low": fit_and_score(train, test, centres < max_hz, seed),
        "probe_E_all": fit_and_score(train, test, centres > 0, seed),
        "train_windows": float(len(train[0])),
        "test_windows": float(len(test[0])),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, nargs="+", required=True, help="one or more folders of recordings")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--window", type=float, default=0.5, help="window length (s)")
    parser.add_argument("--stride", type=int, default=2, help="use every n-th label time")
    parser.add_argument("--max-hz", type=float, default=1200.0, help="upper band limit of the first probe")
    args = parser.parse_args(argv)
    r = run(args.data, args.seed, args.window, args.stride, args.max_hz)
    print(f"{r['train_windows']:.0f} training and {r['test_windows']:.0f} test windows of {args.window} s")
    print(f"constant E {r['constant_E']:.2f} m | probe E, bands < {args.max_hz:g} Hz {r['probe_E_low']:.2f} m | "
          f"probe E, all bands {r['probe_E_all']:.2f} m")


if __name__ == "__main__":
    main()
