"""Evaluation protocols: which windows of which recordings go to train, val and test.

The ``split`` of :class:`datamodules.mmaud.MMAUDDataModule` names a protocol (key ``protocol``):

- ``by_sequence`` (default): whole recordings in train, val or test. Either explicit lists of
  sequence ids per split (or list files of the derived layout), or seeded fractions
  ``{seed, val, test}`` stratified by drone. Honest, but needs several flights per drone. With
  ``train_flights: N`` only N of the training recordings train (drones in turn, nested as N grows;
  val and test unchanged): the data sizes of a learning curve.
- ``time_blocks``: every recording is cut into ``blocks`` contiguous time blocks of equal length
  (or blocks of about ``block_seconds``), assigned at random (seeded per recording) to the splits by
  the fractions, so every flight contributes to every split its length allows (train keeps at least
  one block; when blocks are too few, val gives way first, then test). A purge gap keeps windows of
  different splits at least ``purge_seconds`` apart (default and minimum: the window's audio span),
  so no val or test window shares audio with a training window: a window at label time t covers
  ``[t - window, t]``. Windows in a gap are dropped: test windows never, val windows near test
  windows, training windows near val or test windows. For datasets with few flights (MMAUD V1).
- ``random_windows``: the papers' protocol: windows of the same flights assigned at random (seeded)
  by the fractions. Neighbouring windows overlap (95 % for 2 s windows at 10 Hz), so test windows
  share audio with training windows and errors come out optimistic. Opt-in, and labelled as such.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from datamodules.errors import AauteError

PROTOCOLS = ("by_sequence", "time_blocks", "random_windows")
SPLITS = ("train", "val", "test")
#: per-window split codes; the code is also the purge priority (a higher split keeps its windows)
TRAIN, VAL, TEST, DROPPED = 0, 1, 2, -1
CODES = {"train": TRAIN, "val": VAL, "test": TEST}
#: how tables label each protocol (``random_windows`` says that its numbers are optimistic)
LABELS = {"by_sequence": "by_sequence", "time_blocks": "time_blocks",
          "random_windows": "random_windows (test overlaps train)"}
_COMMON_KEYS = {"protocol", "seed", "val", "test", "train", "train_flights"}
_BLOCK_KEYS = {"blocks", "block_seconds", "purge_seconds"}


class SplitError(AauteError, ValueError):
    """A split setting is invalid, or the split leaves a split a stage needs empty."""


@dataclass(frozen=True)
class SplitConfig:
    """A parsed and checked ``split`` setting (see the module docstring)."""

    protocol: str = "by_sequence"
    seed: int = 0
    val: float = 0.2
    test: float = 0.2
    lists: dict[str, Any] = field(default_factory=dict)  #: explicit members per split (by_sequence)
    blocks: int = 5
    block_seconds: float | None = None
    purge_seconds: float = 0.0
    train_flights: int | None = None  #: by_sequence: train on this many of the training recordings only

    @classmethod
    def from_dict(cls, split: Mapping[str, Any] | None, window_span: float) -> SplitConfig:
        """Parse ``split`` for windows covering ``window_span`` seconds of audio; raise :class:`SplitError`."""
        split = dict(split or {})
        protocol = str(split.get("protocol", "by_sequence"))
        if protocol not in PROTOCOLS:
            raise SplitError(f"split: unknown protocol {protocol!r}; known: {', '.join(PROTOCOLS)}")
        unknown = sorted(set(split) - _COMMON_KEYS - _BLOCK_KEYS)
        if unknown:
            raise SplitError(f"split: unknown key(s) {unknown}; known: {sorted(_COMMON_KEYS | _BLOCK_KEYS)}")
        if protocol != "time_blocks" and set(split) & _BLOCK_KEYS:
            raise SplitError(f"split: {sorted(set(split) & _BLOCK_KEYS)} apply to protocol time_blocks only, "
                             f"not {protocol}")
        lists = {name: split[name] for name in SPLITS if isinstance(split.get(name), list | tuple | str)}
        if lists:
            if protocol != "by_sequence":
                raise SplitError(f"split: explicit lists of sequences are protocol by_sequence, not {protocol}; "
                                 f"drop the lists or the protocol")
            numbers = sorted(name for name in SPLITS if name in split and name not in lists)
            if numbers:
                raise SplitError(f"split: with explicit lists, {numbers} must be lists of sequence ids or list "
                                 f"files too (or be left out)")
            return cls(protocol, int(split.get("seed", 0)), 0.0, 0.0, lists)
        train_flights = split.get("train_flights")
        if train_flights is not None and (protocol != "by_sequence" or lists or isinstance(train_flights, bool)
                                          or not isinstance(train_flights, int) or train_flights < 1):
            raise SplitError(f"split: train_flights must be a positive whole number, with protocol by_sequence and "
                             f"fractions (not lists); got {train_flights!r} under {protocol}")
        if "train" in split:
            raise SplitError("split: train takes what val and test leave; give only val and test fractions "
                             "(or explicit lists for all splits)")
        fractions = {}
        for name in ("val", "test"):
            value = split.get(name, 0.2)
            if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= value < 1.0:
                raise SplitError(f"split: {name} must be a fraction in [0, 1), got {value!r}")
            fractions[name] = float(value)
        if sum(fractions.values()) >= 1.0:
            raise SplitError(f"split: val + test must be below 1 so that training keeps windows, got "
                             f"{fractions['val']:g} + {fractions['test']:g}")
        blocks = split.get("blocks", 5)
        block_seconds = split.get("block_seconds")
        if "blocks" in split and block_seconds is not None:
            raise SplitError("split: give either blocks (a count per recording) or block_seconds, not both")
        if isinstance(blocks, bool) or not isinstance(blocks, int) or blocks < 1:
            raise SplitError(f"split: blocks must be a positive whole number, got {blocks!r}")
        if block_seconds is not None and not (isinstance(block_seconds, int | float) and block_seconds > 0):
            raise SplitError(f"split: block_seconds must be positive, got {block_seconds!r}")
        purge = split.get("purge_seconds", window_span)
        if not isinstance(purge, int | float) or purge < window_span:
            raise SplitError(f"split: purge_seconds must be at least the window's audio span ({window_span:g} s), "
                             f"or windows of different splits would share audio; got {purge!r}")
        return cls(protocol, int(split.get("seed", 0)), fractions["val"], fractions["test"], {}, int(blocks),
                   None if block_seconds is None else float(block_seconds), float(purge), train_flights)

    @property
    def fractions(self) -> dict[str, float]:
        return {"val": self.val, "test": self.test}

    @property
    def label(self) -> str:
        """The protocol as tables label it."""
        return LABELS[self.protocol]

    def describe(self) -> str:
        """One phrase naming the protocol and its settings, for messages."""
        if self.lists:
            return "by_sequence (explicit lists)"
        text = f"{self.protocol} (seed {self.seed}, val {self.val:g}, test {self.test:g}"
        if self.protocol == "time_blocks":
            size = f"blocks of {self.block_seconds:g} s" if self.block_seconds else f"{self.blocks} blocks"
            text += f", {size}, purge {self.purge_seconds:g} s"
        if self.train_flights is not None:
            text += f", {self.train_flights} training flights"
        return text + ")"


# ---------------------------------------------------------------------------------- by_sequence


def sequence_counts(count: int, fractions: Mapping[str, float]) -> dict[str, int]:
    """How many of one drone's ``count`` recordings the seeded by_sequence split gives to each of val, test."""
    counts = {name: int(round(frac * count)) for name, frac in fractions.items()}
    if count >= 3:
        counts = {name: max(1, c) if fractions[name] > 0 else 0 for name, c in counts.items()}
    return counts


def recordings_needed(fractions: Mapping[str, float], split: str, limit: int = 100) -> int | None:
    """The fewest recordings of one drone from which the seeded by_sequence split gives ``split`` one."""
    if fractions.get(split, 0.0) <= 0:
        return None
    return next((n for n in range(1, limit + 1) if sequence_counts(n, fractions)[split] > 0), None)


def _members(entry: str | Sequence[str] | None) -> list[str]:
    """Sequence ids of one split entry: a list of ids, or a list file of the derived layout."""
    if entry is None:
        return []
    if isinstance(entry, str):
        from datamodules.formats.derived_npy import read_sample_list

        return sorted(read_sample_list(entry))
    return list(entry)


def assign_sequences(names: Sequence[tuple[str, str]], drones: Sequence[str | None],
                     config: SplitConfig) -> list[str | None]:
    """The by_sequence split of each recording (None: not used).

    Args:
        names: (sequence id, file stem) of each recording; explicit lists may name either.
        drones: drone of each recording (the seeded split is stratified by it).
        config: the split.
    """
    from datamodules.recording import RecordingError

    if config.lists:
        lookup: dict[str, str] = {}
        for name in SPLITS:
            for item in _members(config.lists.get(name)):
                if item in lookup:
                    raise SplitError(f"sequence {item!r} is listed in both {lookup[item]!r} and {name!r}")
                lookup[item] = name
        known = {n for pair in names for n in pair}
        missing = sorted(set(lookup) - known)
        if missing:
            raise RecordingError(f"split names sequences that were not found: {missing}")
        return [lookup.get(seq, lookup.get(stem)) for seq, stem in names]
    rng = np.random.default_rng(config.seed)
    result: list[str | None] = ["train"] * len(names)
    groups: dict[str, list[int]] = {}
    for i, drone in enumerate(drones):
        groups.setdefault(drone or "unknown", []).append(i)
    for members in groups.values():
        order = rng.permutation(members)
        counts = sequence_counts(len(order), config.fractions)
        cursor = 0
        for name in ("test", "val"):
            for i in order[cursor:cursor + counts[name]]:
                result[int(i)] = name
            cursor += counts[name]
    if config.train_flights is not None:
        for index in training_order(result, drones, config.seed)[config.train_flights:]:
            result[index] = None
    return result


def training_order(splits: Sequence[str | None], drones: Sequence[str | None], seed: int) -> list[int]:
    """The training recordings in the order ``train_flights`` takes them: drone by drone in turn, each drone's
    in a seeded order, so N flights are the first N of N + 1 (nested data sizes) and cover the drones evenly."""
    rng = np.random.default_rng([seed, 1])
    groups: dict[str, list[int]] = {}
    for i, (split, drone) in enumerate(zip(splits, drones, strict=True)):
        if split == "train":
            groups.setdefault(drone or "unknown", []).append(i)
    queues = [list(rng.permutation(groups[drone])) for drone in sorted(groups)]
    order: list[int] = []
    while any(queues):
        for queue in queues:
            if queue:
                order.append(int(queue.pop(0)))
    return order


# ---------------------------------------------------------------------------------- windows


@dataclass(frozen=True)
class WindowAssignment:
    """The split of every window of one recording (window-level protocols)."""

    split: np.ndarray  #: code per window: TRAIN, VAL, TEST or DROPPED (in a purge gap)
    block: np.ndarray  #: the time block of each window (random_windows: every window is its own block)

    def rows(self, name: str) -> np.ndarray:
        """Indices of the windows of split ``name``, in time order."""
        return np.flatnonzero(self.split == CODES[name])

    def blocks(self, name: str) -> int:
        """Number of blocks that kept windows of split ``name``."""
        return int(np.unique(self.block[self.split == CODES[name]]).size)

    @property
    def dropped(self) -> int:
        return int((self.split == DROPPED).sum())


def block_counts(count: int, fractions: Mapping[str, float]) -> dict[str, int]:
    """Blocks of a ``count``-block recording for val and test: at least one each where its fraction is
    positive, and train keeps at least one (val gives way first, then test)."""
    counts = {name: max(1, int(round(frac * count))) if frac > 0 else 0 for name, frac in fractions.items()}
    for name in ("val", "test"):
        counts[name] = max(0, min(counts[name], count - 1 - sum(c for n, c in counts.items() if n != name)))
    return counts


def nearest_distance(times: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Distance from each time to the nearest of the sorted ``reference`` times (inf if there are none)."""
    times = np.asarray(times, dtype=np.float64)
    if reference.size == 0:
        return np.full(times.shape, np.inf)
    right = np.clip(np.searchsorted(reference, times), 0, reference.size - 1)
    left = np.clip(right - 1, 0, reference.size - 1)
    return np.minimum(np.abs(reference[right] - times), np.abs(reference[left] - times))


def purge(times: np.ndarray, split: np.ndarray, seconds: float) -> np.ndarray:
    """Drop windows closer than ``seconds`` to a kept window of a higher split (test > val > train).

    Afterwards any two kept windows of different splits lie at least ``seconds`` apart: the lower
    one of a closer pair would have been dropped, since the higher one was kept.
    """
    kept = np.array(split, dtype=np.int8)
    for level in (VAL, TRAIN):
        higher = times[kept > level]
        mine = kept == level
        close = mine & (nearest_distance(times, higher) < seconds)
        kept[close] = DROPPED
    return kept


def assign_windows(times: np.ndarray, config: SplitConfig, key: str) -> WindowAssignment:
    """Split the (time-sorted) windows of one recording under a window-level protocol.

    ``key`` (the recording's id) seeds the recording's own generator with ``config.seed``, so an
    assignment does not depend on which other recordings are present or in which order.
    """
    times = np.asarray(times, dtype=np.float64)
    rng = np.random.default_rng([config.seed, zlib.crc32(key.encode())])
    if config.protocol == "random_windows":
        counts = {name: int(round(frac * times.size)) for name, frac in config.fractions.items()}
        order = rng.permutation(times.size)
        split = np.full(times.size, TRAIN, dtype=np.int8)
        split[order[:counts["test"]]] = TEST
        split[order[counts["test"]:counts["test"] + counts["val"]]] = VAL
        return WindowAssignment(split, np.arange(times.size))
    if config.protocol != "time_blocks":
        raise SplitError(f"protocol {config.protocol!r} does not split windows")
    span = float(times[-1] - times[0]) if times.size else 0.0
    count = config.blocks if config.block_seconds is None else max(1, int(round(span / config.block_seconds)))
    edges = np.linspace(times[0], times[-1], count + 1) if times.size else np.zeros(count + 1)
    block = np.clip(np.searchsorted(edges, times, side="right") - 1, 0, count - 1)
    counts = block_counts(count, config.fractions)
    order = rng.permutation(count)
    labels = np.full(count, TRAIN, dtype=np.int8)
    labels[order[:counts["test"]]] = TEST
    labels[order[counts["test"]:counts["test"] + counts["val"]]] = VAL
    return WindowAssignment(purge(times, labels[block], config.purge_seconds), block)


# ---------------------------------------------------------------------------------- reporting


def shortfall_message(config: SplitConfig, stage: str, empty: Sequence[str], summary: Mapping[str, Any],
                      drones: Mapping[str, int]) -> str:
    """One line: why ``stage`` cannot run (splits ``empty`` have no windows), what each split got, the fix."""
    got = "; ".join(f"{name}: {summary[name]['sequences']} sequences, {summary[name]['blocks']} blocks, "
                    f"{summary[name]['windows']} windows" for name in SPLITS)
    need = " and ".join(repr(name) for name in empty)
    zero = [name for name in empty if name != "train" and not config.lists and config.fractions[name] == 0]
    if zero:
        fix = f"set split.{zero[0]} above 0 (it is 0)"
    elif config.lists:
        fix = f"list at least one found recording under split.{empty[0]}"
    elif config.protocol == "by_sequence":
        per_drone = ", ".join(f"{drone} {n}" for drone, n in sorted(drones.items()))
        needed = {name: recordings_needed(config.fractions, name) for name in empty if name != "train"}
        want = max((n for n in needed.values() if n is not None), default=1)
        fix = (f"the seeded by_sequence split gives a drone's flights to {need} only from {want} recordings of "
               f"that drone on (found per drone: {per_drone}); add recordings, use protocol time_blocks "
               f"(blocks of every flight in every split), or give explicit lists of sequence ids per split")
    elif config.protocol == "time_blocks":
        fix = ("the recordings are too short for these blocks and purge gaps: use fewer blocks (split.blocks), "
               "longer or more recordings, or larger fractions")
    else:
        fix = "use larger fractions or more recordings"
    return f"cannot {stage}: split {config.describe()} leaves {need} empty ({got}); {fix}"
