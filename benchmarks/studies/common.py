"""What more than one study uses: the learning checks' split, a DataModule over test recordings, ``srp_phat``'s
error on them, live phase rows, a simulated recording's true node clocks.

The studies never import one another; a helper that two of them share lives here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from datamodules.mmaud import MMAUDDataModule, discover

SRP_PHAT_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "model" / "srp_phat.yaml"


def held_out_split(seed: int) -> dict[str, float]:
    """The learning checks' split: seeded by sequence, 15 % validation and 20 % test sequences."""
    return {"seed": seed, "val": 0.15, "test": 0.2}


def recordings_module(data: list[Path], recipe: str, cache: Path | None, batch_size: int = 64,
                      label_rate: float | None = None, clock_calibration: str = "auto") -> MMAUDDataModule:
    """A DataModule, set up, whose test split is every recording under ``data``, with the phase ``recipe``
    (its features made through the cache), windows at ``label_rate`` (default: the DataModule's) and the
    DataModule's ``clock_calibration`` mode."""
    stems = [path.stem for path in discover([str(d) for d in data])]
    rate = {} if label_rate is None else {"label_rate": label_rate}
    module = MMAUDDataModule([str(d) for d in data], split={"train": [], "val": [], "test": stems},
                             inputs={"audio_phase": recipe}, test_lights=["ideal"], batch_size=batch_size,
                             cache_dir=None if cache is None else str(cache), clock_calibration=clock_calibration,
                             **rate)
    module.setup("test")
    return module


def srp_phat_kwargs() -> dict:
    """``srp_phat``'s settings as its model config (``configs/model/srp_phat.yaml``) gives them."""
    return dict(yaml.safe_load(SRP_PHAT_CONFIG.read_text())["model"]["init_args"]["net_kwargs"])


def srp_phat_errors(module: MMAUDDataModule, template: torch.nn.Module | None = None
                    ) -> tuple[dict[str, np.ndarray], torch.nn.Module]:
    """``srp_phat``'s 3D errors (m) per recording (stem) over ``module``'s test windows with ground truth, as
    ``aaute test`` computes them with the config's settings, and the prepared net: its coarse grid and null
    thresholds depend on the geometry alone and are costly, so they are reused from ``template`` (the gate
    and hold start afresh: each module numbers its sequences from 0)."""
    from zoo.registry import get_model

    if template is None:
        template = get_model("srp_phat", **srp_phat_kwargs())
        template.set_bounds(module.hparams.bev_bounds)
        batch = next(iter(module.test_dataloader()[0]))
        template.prepare({name: batch[name] for name in ("audio_phase", "mic_positions")})
    net = template
    net.gate.sequences.clear()
    stems = [Path(sequence.path).stem for sequence in module.sequences["test"]]
    errors: dict[str, list[np.ndarray]] = {}
    for batch in module.test_dataloader()[0]:
        inputs = {name: batch[name] for name in ("audio_phase", *net.context_keys) if name in batch}  # as aaute test
        with torch.no_grad():
            position = net(inputs)["position"].numpy()
        valid = batch["gt_valid"].numpy()
        error = np.linalg.norm(position - batch["gt"].numpy(), axis=1)
        for index in np.unique(batch["sequence"].numpy()):
            rows = valid & (batch["sequence"].numpy() == index)
            errors.setdefault(stems[index], []).append(error[rows])
    return {stem: np.concatenate(parts) for stem, parts in errors.items()}, template


def srp_phat_error(module: MMAUDDataModule, template: torch.nn.Module | None = None
                   ) -> tuple[float, torch.nn.Module]:
    """``srp_phat``'s E (m, mean 3D error over all windows with ground truth; :func:`srp_phat_errors`)."""
    errors, template = srp_phat_errors(module, template)
    return float(np.concatenate(list(errors.values())).mean()), template


class _Rows:
    def __init__(self):
        self.rows: list = []

    def write(self, row) -> None:
        self.rows.append(row)


def live_rows(path: Path, config: Path, store: Path | None) -> tuple[list, str]:
    """The live localiser's rows of one recording (from ``store`` when kept there) and the config's preset."""
    from datamodules.streams import RecordingSource
    from zoo.deploy.live_phase import PhaseRow, PhaseTracker, load_phase_model

    source = RecordingSource(path)
    model = load_phase_model(config=config, source=source)
    preset = model.live_smoother.get("preset", "robust")
    kept = None if store is None else store / f"{path.stem}.npz"
    if kept is not None and kept.is_file():
        data = np.load(kept)
        return [PhaseRow(float(t), raw, float(score), bool(hit), str(state)) for t, raw, score, hit, state in
                zip(data["t"], data["raw"], data["score"], data["detected"], data["state"], strict=True)], preset
    keep = _Rows()
    PhaseTracker(model, source, [keep], preset=preset).run()
    if kept is not None:
        kept.parent.mkdir(parents=True, exist_ok=True)
        np.savez(kept, t=[r.timestamp for r in keep.rows], raw=[r.raw for r in keep.rows],
                 score=[r.score for r in keep.rows], detected=[r.detected for r in keep.rows],
                 state=[r.state for r in keep.rows])
    return keep.rows, preset


def true_clocks(meta: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """The nodes' true offsets (s, at the first sample) and drifts (ppm), relative to node 0."""
    truth = meta.get("clocks_truth")
    if truth is None:
        raise ValueError("the recording has no clocks_truth (not simulated with separate node clocks)")
    offsets = np.asarray(truth["effective_offsets_s"], dtype=np.float64)
    drifts = np.asarray(truth["drifts_ppm"], dtype=np.float64)
    return offsets - offsets[0], drifts - drifts[0]
