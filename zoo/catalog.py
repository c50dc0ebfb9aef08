"""What the task reads from its DataModule: the :class:`SequenceCatalog` protocol, read once per run.

Batches carry an index into the DataModule's sequences, and the test run has one loader per light
condition. The names and files behind those indices, the conditions of the test loaders and the
bird's-eye area the data covers come from the DataModule; :class:`~datamodules.mmaud.MMAUDDataModule`
satisfies the protocol. A run without such a DataModule (plain DataLoaders, or another DataModule)
gets the defaults of :class:`CatalogSnapshot`: no names or files, test loaders ``ideal`` then
``dark``, no bounds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

#: the test loaders' light conditions when the DataModule does not name them
DEFAULT_TEST_LIGHTS = ("ideal", "dark")


@runtime_checkable
class SequenceCatalog(Protocol):
    """The sequences and loaders of a DataModule, as the task and its prediction writers name them."""

    @property
    def sequence_ids(self) -> Sequence[str]:
        """All sequence ids; batches carry an index into this list."""
        ...

    @property
    def sequence_paths(self) -> Sequence[Path]:
        """The file or folder of each sequence, in ``sequence_ids`` order."""
        ...

    @property
    def test_lights(self) -> Sequence[str]:
        """The light condition of each test loader, in loader order."""
        ...

    @property
    def bev_bounds(self) -> Sequence[Sequence[float]] | None:
        """The bird's-eye area [[x_min, x_max], [y_min, y_max]] (m) the data covers, if known."""
        ...


@dataclass(frozen=True)
class CatalogSnapshot:
    """A :class:`SequenceCatalog` read at one moment; its defaults stand for a DataModule that has none."""

    sequence_ids: tuple[str, ...] = ()
    sequence_paths: tuple[Path, ...] = ()
    test_lights: tuple[str, ...] = DEFAULT_TEST_LIGHTS
    bev_bounds: Sequence[Sequence[float]] | None = None

    def test_light(self, dataloader_idx: int) -> str:
        """The light condition of test loader ``dataloader_idx`` (its index as text past the known ones)."""
        lights = self.test_lights
        return lights[dataloader_idx] if dataloader_idx < len(lights) else str(dataloader_idx)


def read_catalog(datamodule: object | None) -> CatalogSnapshot:
    """Snapshot ``datamodule`` if it is a :class:`SequenceCatalog` (after its ``setup``), else the defaults."""
    if not isinstance(datamodule, SequenceCatalog):
        return CatalogSnapshot()
    return CatalogSnapshot(sequence_ids=tuple(datamodule.sequence_ids),
                           sequence_paths=tuple(datamodule.sequence_paths),
                           test_lights=tuple(datamodule.test_lights) or DEFAULT_TEST_LIGHTS,
                           bev_bounds=datamodule.bev_bounds)
