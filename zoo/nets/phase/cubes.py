"""The refinement cubes' steering columns, computed once per cube and geometry and reused across windows.

Which pooled-correlation column each term of a cube reads (:meth:`~zoo.nets.phase.steering.Steering.columns`)
depends on the cube (centre and side) and the microphones alone, never on the audio. The search refines
each of a window's best coarse cells into the 27 cubes of half its side around it, and the best of those
again: every cube it reads is a child of a coarse cell or of such a child, named by the cell's index and
the offsets taken since (:func:`child_ids`). Consecutive windows of a stream (and the groups of one window)
refine largely the same parents: a drone moves a few centimetres per update, and noise revisits the same
loose cells. :class:`CubeColumns` keeps the columns of each parent's 27 children, computed the first time
the parent is refined, so a window reads them with one gather instead of recomputing the geometry of
thousands of cubes. The blocks are exactly what :meth:`Steering.columns` gives for those cubes.

The first level's parents are the coarse cells, a fixed set: :meth:`CubeColumns.fill` computes all their
children at once before the stream starts (about half a second and 50 MB for 18,000 cells at four
microphones), so the first level never computes columns while windows arrive; a stream still visits
new parents at the deeper level, which the table keeps as they come.
"""

from __future__ import annotations

import numpy as np
import torch

from datamodules.features import mic_pairs
from zoo.nets.phase.steering import POOL_WIDTHS, Steering

#: parents whose children's columns are kept (each 27 x terms int64: 5 kB at 24 terms; about 40 MB in all);
#: when full the table starts afresh
CUBE_BLOCKS = 8192
#: children of each parent (the 27 cubes of the refinement)
CHILDREN = 27
#: parents whose children :meth:`CubeColumns.fill` computes in one call (bounds its temporary memory)
FILL_CHUNK = 1024


def child_ids(parents: torch.Tensor, child: torch.Tensor) -> torch.Tensor:
    """The names of children: the parent's name (a coarse cell's is its index in the coarse grid) times 27
    plus the child's offset index (0..26), so a name fixes the cube as long as the grid does."""
    return parents * CHILDREN + child


class CubeColumns:
    """A geometry's parent -> its 27 children's steering columns (see the module docstring).

    Args:
        steering: the physics the columns are computed with.
        mics: the microphones (channels x 3, m).
        capacity: parents kept before the table starts afresh.
    """

    def __init__(self, steering: Steering, mics: torch.Tensor, capacity: int = CUBE_BLOCKS):
        self.steering, self.mics, self.capacity = steering, mics, int(capacity)
        terms = len(steering.terms(mics.shape[0]).weights)
        #: the pooled correlations' columns, the zero one last: a column of -1 (reads nothing) is stored as it
        self.width = len(POOL_WIDTHS) * len(mic_pairs(mics.shape[0])) * steering.recipe.num_lags() + 1
        self.blocks = torch.empty((self.capacity, CHILDREN, terms), dtype=torch.long)  #: per slot, the columns
        #: per refinement level, each parent name's slot (-1: not held), grown as larger names arrive
        self._slot_of: dict[int, torch.Tensor] = {}
        #: per filled level, every parent's children's columns (parents x 27 x terms, int32), by parent name
        self._filled: dict[int, torch.Tensor] = {}
        self.used = 0  #: slots filled
        self.hits = 0  #: parents read from the table
        self.misses = 0  #: parents computed

    @property
    def slots(self) -> dict[tuple[int, int], int]:
        """The parents held: (level, parent name) -> slot."""
        return {(level, int(name)): int(table[name]) for level, table in self._slot_of.items()
                for name in torch.nonzero(table >= 0)[:, 0]}

    def filled(self, level: int) -> bool:
        """Whether :meth:`fill` has computed every parent of ``level``."""
        return level in self._filled

    def fill(self, level: int, centres: torch.Tensor, sides: torch.Tensor) -> None:
        """Compute the children of every parent of ``level`` now: parent ``g``'s cubes are ``centres[g]``
        (27 x 3) of ``sides[g]`` (27). Later calls of :meth:`children` at that level only read them."""
        blocks = []
        for cubes, side in zip(centres.split(FILL_CHUNK), sides.split(FILL_CHUNK), strict=True):
            columns = self.steering.columns(cubes.reshape(-1, 3), self.mics, side.reshape(-1, 1))
            blocks.append(columns.remainder_(self.width).reshape(len(cubes), CHILDREN, -1).int())
        self._filled[level] = torch.cat(blocks)

    def _table(self, level: int, size: int) -> torch.Tensor:
        """The level's name -> slot table, at least ``size`` long."""
        table = self._slot_of.get(level)
        if table is None or table.shape[0] < size:
            grown = torch.full((max(size, 2 * (0 if table is None else table.shape[0])),), -1, dtype=torch.long)
            if table is not None:
                grown[:table.shape[0]] = table
            table = self._slot_of[level] = grown
        return table

    def children(self, level: int, parents: torch.Tensor, centres: torch.Tensor, sides: torch.Tensor
                 ) -> torch.Tensor:
        """The columns (M x 27 x terms) of the children of the parents named ``parents`` (M) at refinement
        ``level``, whose cubes are ``centres`` (M x 27 x 3) and ``sides`` (M x 27): :meth:`Steering.columns`
        of those cubes, the zero column as its index rather than -1. The cubes are read only for parents
        not yet in the table."""
        if level in self._filled:
            self.hits += len(parents)
            return self._filled[level].index_select(0, parents).long()
        table = self._table(level, int(parents.max()) + 1)
        slots = table[parents]
        missing, fresh = slots < 0, 0
        if bool(missing.any()):
            names = parents.numpy()
            new, first = np.unique(names[missing.numpy()], return_index=True)
            rows = np.flatnonzero(missing.numpy())[first]  # each new parent's first row
            if self.used + len(new) > self.capacity:  # full: start afresh with what this call needs
                for held in self._slot_of.values():
                    held.fill_(-1)
                self.used = 0
                new, rows = np.unique(names, return_index=True)
            cubes = centres[rows].reshape(-1, 3)
            computed = self.steering.columns(cubes, self.mics, sides[rows].reshape(-1, 1)).remainder_(self.width)
            self.blocks[self.used:self.used + len(new)] = computed.reshape(len(new), CHILDREN, -1)
            table[torch.from_numpy(new)] = torch.arange(self.used, self.used + len(new))
            self.used += len(new)
            fresh = len(new)
            slots = table[parents]
        self.misses += fresh
        self.hits += len(parents) - fresh
        return self.blocks.index_select(0, slots)
