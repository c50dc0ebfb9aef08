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
"""

from __future__ import annotations

import torch

from datamodules.features import mic_pairs
from zoo.nets.phase.steering import POOL_WIDTHS, Steering

#: parents whose children's columns are kept (each 27 x terms int64: 5 kB at 24 terms; about 40 MB in all);
#: when full the table starts afresh
CUBE_BLOCKS = 8192
#: children of each parent (the 27 cubes of the refinement)
CHILDREN = 27


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
        self.slots: dict[tuple[int, int], int] = {}  #: (level, parent name) -> its slot
        self.hits = 0  #: parents read from the table
        self.misses = 0  #: parents computed

    def children(self, level: int, parents: torch.Tensor, centres: torch.Tensor, sides: torch.Tensor
                 ) -> torch.Tensor:
        """The columns (M x 27 x terms) of the children of the parents named ``parents`` (M) at refinement
        ``level``, whose cubes are ``centres`` (M x 27 x 3) and ``sides`` (M x 27): :meth:`Steering.columns`
        of those cubes, the zero column as its index rather than -1. The cubes are read only for parents
        not yet in the table."""
        names = [(level, parent) for parent in parents.tolist()]
        new = list(dict.fromkeys(name for name in names if name not in self.slots))
        if len(self.slots) + len(new) > self.capacity:  # full: start afresh with what this call needs
            self.slots.clear()
            new = list(dict.fromkeys(names))
        if new:
            rows = torch.tensor([names.index(name) for name in new])
            cubes = centres[rows].reshape(-1, 3)
            computed = self.steering.columns(cubes, self.mics, sides[rows].reshape(-1, 1)).remainder_(self.width)
            first = len(self.slots)
            self.blocks[first:first + len(new)] = computed.reshape(len(new), CHILDREN, -1)
            self.slots.update((name, first + i) for i, name in enumerate(new))
        self.misses += len(new)
        self.hits += len(names) - len(new)
        return self.blocks.index_select(0, torch.tensor([self.slots[name] for name in names]))
