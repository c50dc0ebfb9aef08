"""Builders of small recordings and on-disk dataset layouts, written at test time.

``make_derived`` writes a derived per-sample npy root (AAUTE / AV-FDTI / TAME), ``make_ug2_sequence`` a UG2
challenge folder and ``make_recording`` an in-memory ``Recording`` with every stream. ROS 1 bags, which need the
optional ``rosbags`` package, are built in ``tests.helpers.bags``.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image

from datamodules.recording import (
    ArrayAudio,
    ArrayImages,
    ArrayPointClouds,
    EncodedImage,
    PointCloud,
    Recording,
    Track,
)

# ===================================================================================== derived npy root

CHUNK = 480  # samples per file (TAME files hold 3100; small here to keep the test fast)


def _derived_png() -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(np.full((6, 10, 3), 50, np.uint8)).save(buffer, "PNG")
    return buffer.getvalue()


def make_derived(root: Path, sequences: dict[str, int], seed: int = 0, first: int = 0,
                 images: bool = True) -> dict[str, dict[str, np.ndarray]]:
    """An AAUTE/TAME-style root: int16 audio chunks, gt, pseudo_label, label (class), image, Detection_new."""
    rng = np.random.default_rng(seed)
    truth: dict[str, dict[str, np.ndarray]] = {}
    for seq, count in sequences.items():
        audio = rng.integers(-3000, 3000, (count * CHUNK, 4)).astype(np.int16)
        gt = rng.normal(0, 4, (count, 3))
        pseudo = gt + rng.normal(0, 0.3, (count, 3))
        for folder in ("audio_npy", "gt", "pseudo_label", "label", "image", "Detection_new"):
            (root / folder / seq).mkdir(parents=True, exist_ok=True)
        for k in range(count):
            idx = first + k
            np.save(root / "audio_npy" / seq / f"{idx}.npy", audio[k * CHUNK:(k + 1) * CHUNK])
            np.save(root / "gt" / seq / f"{idx}.npy", gt[k])
            np.save(root / "pseudo_label" / seq / f"{idx}.npy", pseudo[k])
            np.save(root / "label" / seq / f"{idx}.npy", np.array(4))
            np.save(root / "Detection_new" / seq / f"{idx}.npy", np.array([k % 2, 0.0]))
            if images:
                (root / "image" / seq / f"{idx}.png").write_bytes(_derived_png())
        truth[seq] = {"audio": audio, "gt": gt, "pseudo": pseudo}
    return truth


# ======================================================================================== UG2 sequence


def _ug2_png(width: int = 8) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(np.full((4, width, 3), 100, np.uint8)).save(buffer, "PNG")
    return buffer.getvalue()


def make_ug2_sequence(folder: Path, frames: int = 12, class_id: int | None = 2, t0: float = 1706255621.6,
                      skip: tuple[int, ...] = (), seed: int = 0) -> dict:
    """A small UG2 sequence folder: padded scans, images, ground truth and class files."""
    rng = np.random.default_rng(seed)
    written: dict = {"mid360": [], "avia": [], "gt": []}
    for name in ("lidar_360", "livox_avia", "Image", "ground_truth", "class"):
        (folder / name).mkdir(parents=True)
    for k in range(frames):
        if k in skip:
            continue
        t = t0 + 0.1 * k
        for sensor, name, offset, rows in (("mid360", "lidar_360", 0.0, 50), ("avia", "livox_avia", 0.014, 60)):
            real = rng.normal(0, 3, (int(rng.integers(0, 20)), 3))
            padded = np.zeros((rows, 3))
            padded[: len(real)] = real
            np.save(folder / name / f"{t + offset:.6f}.npy", padded)
            written[sensor].append(real.astype(np.float32))
        (folder / "Image" / f"{t + 0.03:.6f}.png").write_bytes(_ug2_png())
        gt = rng.normal(0, 5, 3)
        np.save(folder / "ground_truth" / f"{t:.6f}.npy", gt)
        written["gt"].append(gt)
        if class_id is not None:
            np.save(folder / "class" / f"{t:.6f}.npy", np.array([class_id]))
    return written


# ======================================================================================= MCAP recording

RECORDING_T0 = 1692845357.123456  # when make_recording's audio starts


def _random_png(rng: np.random.Generator) -> EncodedImage:
    buffer = io.BytesIO()
    Image.fromarray(rng.integers(0, 255, (36, 64, 3), dtype=np.uint8)).save(buffer, "PNG")
    return EncodedImage(buffer.getvalue(), "png")


def make_recording(seconds: float = 3.0, seed: int = 0, sample_format: str = "S16LE") -> Recording:
    """A random recording with every stream (4-channel audio, two LiDARs, PNG frames, ground truth, labels)."""
    rng = np.random.default_rng(seed)
    fs = 48000
    samples = rng.normal(0, 0.02, (4, int(seconds * fs)))
    if sample_format == "S16LE":
        samples = np.rint(samples * 32768) / 32768
    audio = ArrayAudio(samples.astype(np.float32), fs, RECORDING_T0, rng.uniform(-2, 2, (4, 3)), sample_format)
    times = RECORDING_T0 + 0.05 + np.arange(int(seconds * 10)) * 0.1
    clouds = [PointCloud(rng.normal(0, 5, (n, 3)).astype(np.float32), rng.uniform(0, 255, n).astype(np.float32),
                         rng.integers(0, 3, n).astype(np.uint8)) for n in rng.integers(0, 500, times.size)]
    valid = rng.random(times.size) > 0.3
    return Recording(
        sequence_id="test-seq",
        drone="phantom4",
        audio=audio,
        lidar={"mid360": ArrayPointClouds(times, clouds), "avia": ArrayPointClouds(times + 0.014, clouds[::-1])},
        frames=ArrayImages(times + 0.03, [_random_png(rng) for _ in times]),
        ground_truth=Track(times, rng.normal(0, 5, (times.size, 3))),
        pseudo_labels=Track(times, rng.normal(0, 5, (times.size, 3)), valid=valid,
                            quality={"support": rng.integers(0, 99, times.size).astype(float)}),
        meta={"scene": "rooftop", "nested": {"a": [1, 2, 3]}},
    )
