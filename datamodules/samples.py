"""A DataModule's samples: one recording's (or piece's) labelled windows, and the dataset that reads their
cached features (mel, phase, image; the darkness of a test or augmented sample) on access."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from datamodules.cache import FeatureCache
from datamodules.features import MelRecipe, final_resize, published_dark, scale_image


@dataclass
class SequenceSamples:
    """The samples of one recording, or of one piece of it (arrays of equal length), and where their
    features are cached: sample ``i`` is row ``rows[i]`` of the recording's cache entries."""

    path: Path
    sequence_id: str
    drone: str | None
    times: np.ndarray
    gt: np.ndarray
    gt_valid: np.ndarray
    pseudo: np.ndarray
    pseudo_valid: np.ndarray
    image_index: np.ndarray  #: nearest camera frame, -1 if none
    visible: np.ndarray
    class_id: int
    feature_keys: dict[str, str]
    rows: np.ndarray | None = None  #: row of each sample in the cache entries (None: 0, 1, ...)
    recording_id: str = ""  #: the recording a piece comes from ('' : sequence_id)
    blocks: int = 1  #: contiguous time blocks of the recording in this piece
    mic_positions: np.ndarray | None = None  #: channels x 3 (m), given to models that read phase features
    #: nodes on separate clocks whose calibration was refused: the phase features keep their clock offsets
    uncorrected_clocks: bool = False

    def __post_init__(self) -> None:
        if self.rows is None:
            self.rows = np.arange(self.times.size)
        if not self.recording_id:
            self.recording_id = self.sequence_id

    def __len__(self) -> int:
        return int(self.times.size)

    def piece(self, rows: np.ndarray, sequence_id: str, blocks: int) -> SequenceSamples:
        """The samples ``rows`` (time-sorted indices into these samples) as a sequence of their own."""
        rows = np.asarray(rows, dtype=np.int64)
        arrays = {name: getattr(self, name)[rows] for name in ("times", "gt", "gt_valid", "pseudo", "pseudo_valid",
                                                                "image_index", "visible", "rows")}
        return dataclasses.replace(self, sequence_id=sequence_id, blocks=blocks, **arrays)



class WindowDataset(Dataset):
    """Samples of several sequences; features are read from the memory-mapped cache on access."""

    def __init__(self, sequences: list[SequenceSamples], cache: FeatureCache, sequence_index: list[int],
                 light: str, dark_mode: str, dark_probability: float, mel_recipe: MelRecipe | None = None):
        self.sequences = sequences
        self.mel_recipe = mel_recipe  #: its second resize, if any, is applied to the cached map on reading
        self.cache = cache
        self.sequence_index = sequence_index
        self.light, self.dark_mode, self.dark_probability = light, dark_mode, dark_probability
        self.offsets = np.cumsum([0] + [len(s) for s in sequences])
        self._arrays: dict[str, np.ndarray] = {}

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_arrays"] = {}  # memory maps are reopened in each worker
        return state

    def _array(self, key: str) -> np.ndarray:
        if key not in self._arrays:
            self._arrays[key] = self.cache.open(key)
        return self._arrays[key]

    def __getitem__(self, index: int) -> dict[str, Any]:
        s = int(np.searchsorted(self.offsets, index, side="right") - 1)
        seq, i = self.sequences[s], int(index - self.offsets[s])
        item: dict[str, Any] = {
            "gt": torch.as_tensor(seq.gt[i], dtype=torch.float32),
            "gt_valid": torch.as_tensor(bool(seq.gt_valid[i])),
            "pseudo": torch.as_tensor(seq.pseudo[i], dtype=torch.float32),
            "pseudo_valid": torch.as_tensor(bool(seq.pseudo_valid[i])),
            "class_id": torch.as_tensor(seq.class_id, dtype=torch.long),
            "time": torch.as_tensor(seq.times[i], dtype=torch.float64),
            "sequence": torch.as_tensor(self.sequence_index[s], dtype=torch.long),
        }
        row = int(seq.rows[i])  # a piece's samples index into its recording's cache entries
        if "audio_mel" in seq.feature_keys:
            mel = torch.from_numpy(np.array(self._array(seq.feature_keys["audio_mel"])[row]))
            item["audio_mel"] = final_resize(mel, self.mel_recipe) if self.mel_recipe is not None else mel
        if "audio_phase" in seq.feature_keys:
            phase = np.array(self._array(seq.feature_keys["audio_phase"])[row], dtype=np.float32)
            item["audio_phase"] = torch.from_numpy(phase)
            item["mic_positions"] = torch.from_numpy(seq.mic_positions)
            item["uncorrected_clocks"] = torch.as_tensor(seq.uncorrected_clocks)
        visible = float(seq.visible[i])
        dark = self.light == "dark" or (self.dark_probability > 0 and torch.rand(()).item() < self.dark_probability)
        if "image" in seq.feature_keys:
            if dark and self.dark_mode == "physical":
                image = torch.from_numpy(np.array(self._array(seq.feature_keys["image_dark"])[row]))
            else:
                image = torch.from_numpy(np.array(self._array(seq.feature_keys["image"])[row]))
                if dark:
                    image = published_dark(image)
            item["image"] = scale_image(image)
        if dark and self.dark_mode == "published":
            visible = 0.0  # the published protocol marks a darkened frame as "not visible"
        item["visible"] = torch.as_tensor(visible, dtype=torch.float32)
        item["dark"] = torch.as_tensor(dark)
        return item
