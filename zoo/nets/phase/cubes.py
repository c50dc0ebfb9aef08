"""The refinement cubes' steering columns, computed once per cube and geometry and reused across windows.

Which pooled-correlation column each term of a cube reads (:meth:`~zoo.nets.phase.steering.Steering.columns`)
depends on the cube (centre and side) and the microphones alone, never on the audio. The search refines
the best coarse cells of every window into cubes of half and a quarter of their side, and consecutive
windows of a stream (and the groups of one window) ask for largely the same cubes: a drone moves a few
centimetres per update, and noise revisits the same loose cells. :class:`CubeColumns` keeps the columns of
the cubes asked for in a fixed-size table addressed by a hash of the cube's exact coordinates, so a cube is
computed again only after its slot was taken by another one. A cube is found only when its centre and
side are bitwise those stored, so the columns read are exactly those :meth:`Steering.columns` gives.
"""

from __future__ import annotations

import torch

from datamodules.features import mic_pairs
from zoo.nets.phase.steering import POOL_WIDTHS, Steering

#: slots of the table (a power of two): about 27 MB at 24 terms, room for a few minutes of a stream's cubes
CUBE_SLOTS = 1 << 17
#: odd multipliers mixing the bit patterns of a cube's x, y, z and side into one number
_MIX = (0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D, 0x27D4EB2F)
#: 2**64 / golden ratio (as a signed 64-bit number): its product's top bits pick the slot (multiplicative
#: hashing; the low bits of round coordinates are all zero, so they cannot)
_GOLDEN = 0x9E3779B97F4A7C15 - (1 << 64)


class CubeColumns:
    """A geometry's cube -> steering columns table (see the module docstring).

    Args:
        steering: the physics the columns are computed with.
        mics: the microphones (channels x 3, m).
        slots: table size (a power of two).
    """

    def __init__(self, steering: Steering, mics: torch.Tensor, slots: int = CUBE_SLOTS):
        if slots & (slots - 1):
            raise ValueError(f"slots must be a power of two, got {slots}")
        self.steering, self.mics, self.slots = steering, mics, int(slots)
        terms = len(steering.terms(mics.shape[0]).weights)
        #: the pooled correlations' columns, the zero one last: a column of -1 (reads nothing) is stored as it
        self.width = len(POOL_WIDTHS) * len(mic_pairs(mics.shape[0])) * steering.recipe.num_lags() + 1
        self.keys = torch.full((self.slots, 4), float("nan"))  #: each slot's cube: x, y, z, side (NaN: empty)
        self.values = torch.zeros((self.slots, terms), dtype=torch.long)  #: its columns (as indices are: int64)
        self._mix = torch.tensor(_MIX, dtype=torch.int64)
        self._shift = 64 - (self.slots.bit_length() - 1)
        self.hits = 0  #: cubes read from the table
        self.misses = 0  #: cubes computed

    def columns(self, centres: torch.Tensor, sides: torch.Tensor) -> torch.Tensor:
        """The columns (... x terms) of the cubes of ``centres`` (... x 3, float32) and ``sides`` (..., float32):
        :meth:`Steering.columns` of them (the zero column as its index, not -1), from the table where stored."""
        shape = centres.shape[:-1]
        cubes = torch.cat([centres.reshape(-1, 3), sides.reshape(-1, 1)], dim=1).to(torch.float32)
        bits = cubes.view(torch.int32).to(torch.int64)
        mixed = (bits * self._mix).sum(dim=1) * _GOLDEN  # wraps around, as intended
        slot = mixed.bitwise_right_shift_(self._shift).bitwise_and_(self.slots - 1)
        found = (self.keys.index_select(0, slot) == cubes).all(dim=1)
        out = self.values.index_select(0, slot)
        missing = torch.nonzero(~found).flatten()
        if missing.numel():
            new = cubes[missing]
            computed = self.steering.columns(new[:, :3], self.mics, new[:, 3:]).remainder_(self.width)
            out[missing] = computed
            self.keys[slot[missing]] = new
            self.values[slot[missing]] = computed
        self.misses += int(missing.numel())
        self.hits += cubes.shape[0] - int(missing.numel())
        return out.reshape(*shape, out.shape[-1])
