"""How much clock error between microphone nodes costs ``srp_phat``: E against constant offsets and drifts.

For each ambient condition (quiet: 45 dB(A), no wind, no HVAC; default: the simulator's ambient), the
held-out flights (``--sequences`` x ``--seconds``, ``--seed``) are simulated once on one shared clock,
then given each clock setting: node ``n`` sampling ``n * X`` ms late (consecutive nodes ``X`` apart,
the first and last ``3 X``) or drifting ``n * D`` ppm (as ``aaute simulate --clock-offset-ms X`` /
``--clock-drift-ppm D``). The setting is applied by reading each channel at its node's sample times
(:func:`datamodules.simulate.clocks.resample_at_clock`, what the simulator does to the noise; for the
drone it renders those times directly, which agrees to a correlation above 0.999), so every row sees
the very same flights and noise. ``srp_phat`` with its config's settings (``configs/model/srp_phat.yaml``,
recipe ``gcc_phat_2s_static``) localises every 10 Hz window, steering with the true positions and
assuming one shared clock; E is the mean 3D error over the windows with ground truth.

Run: ``python -m benchmarks.studies.clock_sensitivity [--sequences 3 --seconds 20 --seed 101]``; it
prints a Markdown table and writes ``--out`` (CSV). One torch thread. ``--identifiability`` instead asks
whether four single-microphone nodes' direct-path time differences can tell the offsets at all.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from benchmarks.studies.common import recordings_module, srp_phat_error, srp_phat_kwargs
from datamodules.atomic import atomic_write
from datamodules.formats.mcap_file import read_mcap, write_mcap
from datamodules.recording import ArrayAudio
from datamodules.simulate.acoustics import AudioConfig
from datamodules.simulate.ambient import AmbientConfig
from datamodules.simulate.clocks import ClockConfig, draw_clocks, resample_at_clock
from datamodules.simulate.simulator import SimulationConfig, simulate_dataset

log = logging.getLogger(__name__)

RECIPE = "gcc_phat_2s_static"
OFFSETS_MS = (0.0, 0.1, 0.3, 1.0, 3.0)
DRIFTS_PPM = (10.0, 50.0)
CONDITIONS = {
    "quiet": AmbientConfig(level_dba=(45.0, 45.0), wind_speed=(0.0, 0.0), hvac=False),
    "default": AmbientConfig(),
}


def settings() -> list[tuple[str, ClockConfig | None]]:
    """The clock settings of the table: one shared clock, constant offsets, drifts."""
    rows: list[tuple[str, ClockConfig | None]] = [("shared clock", None)]
    rows += [(f"offset {x:g} ms", ClockConfig(offset_ms=x)) for x in OFFSETS_MS if x]
    rows += [(f"drift {d:g} ppm", ClockConfig(drift_ppm=d)) for d in DRIFTS_PPM]
    return rows


def with_clocks(source: Path, target: Path, clocks: ClockConfig) -> None:
    """The recording at ``source`` with its nodes on the clocks of ``clocks`` (fixed values only), at ``target``."""
    recording = read_mcap(source)
    audio = recording.audio
    drawn = draw_clocks(clocks, audio.num_channels, audio.duration, np.random.default_rng(0))
    samples = resample_at_clock(audio.read(0, audio.num_samples), audio.sample_rate, drawn.offsets_s,
                                drawn.drifts_ppm)
    recording.audio = ArrayAudio(samples, audio.sample_rate, audio.t0, audio.mic_positions)
    recording.meta.update(clocks_truth=drawn.meta(), nodes_share_clock=False)
    write_mcap(recording, target)


def evaluate(folder: Path, cache: Path, template: torch.nn.Module | None) -> tuple[float, torch.nn.Module]:
    """``srp_phat``'s E (m) over every window with ground truth of the recordings in ``folder``, uncalibrated,
    and the prepared net (reused from ``template``)."""
    module = recordings_module([folder], RECIPE, cache, clock_calibration="off")  # what clock error costs
    return srp_phat_error(module, template)


def identifiability(offsets_ms: tuple[float, ...] = (0.1, 0.3, 1.0), trials: int = 200, seed: int = 0) -> str:
    """How often an offset ramp between four single-microphone nodes is explained exactly by another source
    position: the direct-path time differences of a random position in the flight region plus the ramp,
    fitted by a position (least squares from four starts, not restricted to the region)."""
    from scipy.optimize import least_squares

    from datamodules.simulate.microphones import mic_geometry

    mics, c = mic_geometry("distributed4"), float(srp_phat_kwargs()["speed_of_sound"])

    def tdoa(point: np.ndarray) -> np.ndarray:
        arrival = np.linalg.norm(point - mics, axis=1) / c
        return arrival[1:] - arrival[0]

    rng, lines = np.random.default_rng(seed), []
    for offset in offsets_ms:
        ramp = np.arange(len(mics)) * offset * 1e-3
        fits, moved = [], []
        for _ in range(trials):
            point = np.array([rng.uniform(-2, 8), rng.uniform(-5, 25), rng.uniform(3, 25)])
            target = tdoa(point) + ramp[1:] - ramp[0]
            starts = (point, point * [1, 1, 0.5], point * [1, 1, 2], np.array([3.0, 10.0, 10.0]))
            fitted = [least_squares(lambda p, t=target: (tdoa(p) - t) * 1e6, s0) for s0 in starts]
            best = min(fitted, key=lambda r: r.cost)
            fits.append(np.abs(best.fun).max() < 1.0)  # within 1 us on every pair
            moved.append(np.linalg.norm(best.x - point))
        fits, moved = np.array(fits), np.array(moved)
        lines.append(f"offset ramp {offset:g} ms: {fits.mean():.0%} of positions explained exactly by another one, "
                     f"median {np.median(moved[fits]):.1f} m away")
    return "\n".join(lines)


def markdown(table: pd.DataFrame) -> str:
    """The table as Markdown: clock settings by rows, E (m) per condition."""
    lines = ["| clocks | " + " | ".join(f"E {c}" for c in table.columns) + " |",
             "|:--|" + "--:|" * len(table.columns)]
    lines += [f"| {name} | " + " | ".join(f"{value:.2f} m" for value in row) + " |" for name, row in table.iterrows()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--seed", type=int, default=101)
    parser.add_argument("--out", type=Path, help="write the table as CSV")
    parser.add_argument("--identifiability", action="store_true",
                        help="only say whether direct-path time differences can tell the offsets (seconds)")
    args = parser.parse_args(argv)
    if args.identifiability:
        print(identifiability())
        return
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(1)
    rows, template = [], None
    with tempfile.TemporaryDirectory() as tmp:
        for condition, ambient in CONDITIONS.items():
            shared = Path(tmp) / condition / "shared"
            config = SimulationConfig(duration=args.seconds, camera=False, lidar_sensors=(),
                                      audio=dataclasses.replace(AudioConfig(), ambient=ambient))
            flights = simulate_dataset(shared, args.sequences, config, seed=args.seed, progress=False)
            for number, (name, clocks) in enumerate(settings()):
                folder = shared
                if clocks is not None:
                    folder = Path(tmp) / condition / f"setting{number}"
                    for flight in flights:
                        with_clocks(flight, folder / flight.name, clocks)
                error, template = evaluate(folder, Path(tmp) / "cache", template)
                rows.append({"condition": condition, "clocks": name, "E": error})
                log.warning("%s, %s: E %.2f m", condition, name, error)
    table = pd.DataFrame(rows).pivot(index="clocks", columns="condition", values="E")
    table = table.loc[[name for name, _ in settings()], list(CONDITIONS)]
    print(markdown(table))
    if args.out is not None:
        with atomic_write(args.out) as path:
            table.to_csv(path)


if __name__ == "__main__":
    main()
