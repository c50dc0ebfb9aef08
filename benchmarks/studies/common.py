"""What more than one study uses: the learning checks' split and a DataModule over test recordings.

The studies never import one another; a helper that two of them share lives here.
"""

from __future__ import annotations

from pathlib import Path

from datamodules.mmaud import MMAUDDataModule, discover


def held_out_split(seed: int) -> dict[str, float]:
    """The learning checks' split: seeded by sequence, 15 % validation and 20 % test sequences."""
    return {"seed": seed, "val": 0.15, "test": 0.2}


def recordings_module(data: list[Path], recipe: str, cache: Path | None, batch_size: int = 64,
                      label_rate: float | None = None) -> MMAUDDataModule:
    """A DataModule, set up, whose test split is every recording under ``data``, with the phase ``recipe``
    (its features made through the cache) and windows at ``label_rate`` (default: the DataModule's)."""
    stems = [path.stem for path in discover([str(d) for d in data])]
    rate = {} if label_rate is None else {"label_rate": label_rate}
    module = MMAUDDataModule([str(d) for d in data], split={"train": [], "val": [], "test": stems},
                             inputs={"audio_phase": recipe}, test_lights=["ideal"], batch_size=batch_size,
                             cache_dir=None if cache is None else str(cache), **rate)
    module.setup("test")
    return module
