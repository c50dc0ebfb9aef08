"""A disk cache of computed features, memory-mapped for reading.

Each entry is one ``.npy`` array (samples x feature shape) named by a key that hashes everything
the features depend on (the recording's identity, the recipe, the window times). Entries are
built once, into a temporary file that is renamed into place when complete, so concurrent
builders (DataLoader workers, DDP ranks, several runs) never see a half-written entry: the last
rename wins and every builder writes the same bytes. Readers memory-map the file, so memory does
not grow with the dataset.
"""

from __future__ import annotations

import hashlib
import logging
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from datamodules.atomic import atomic_write

log = logging.getLogger(__name__)


def default_cache_dir() -> Path:
    """``$AAUTE_CACHE`` or ``~/.cache/aaute/features``."""
    return Path(os.environ.get("AAUTE_CACHE", Path.home() / ".cache" / "aaute" / "features"))


def path_fingerprint(path: Path) -> str:
    """Identity of a recording on disk: resolved path, size and modification time (of every file)."""
    path = Path(path).resolve()
    if path.is_file():
        stat = path.stat()
        parts = [f"{path}:{stat.st_size}:{stat.st_mtime_ns}"]
    else:
        parts = [str(path)]
        for item in sorted(path.rglob("*")):
            if item.is_file():
                stat = item.stat()
                parts.append(f"{item.relative_to(path)}:{stat.st_size}:{stat.st_mtime_ns}")
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:16]


def array_fingerprint(*arrays: np.ndarray) -> str:
    digest = hashlib.sha256()
    for array in arrays:
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()[:16]


class FeatureCache:
    """Build-once, memory-mapped feature arrays under ``root``."""

    def __init__(self, root: str | Path | None = None):
        self.root = Path(root) if root is not None else default_cache_dir()

    def path(self, key: str) -> Path:
        return self.root / f"{key}.npy"

    def exists(self, key: str) -> bool:
        return self.path(key).is_file()

    def build(
        self,
        key: str,
        count: int,
        shape: tuple[int, ...],
        dtype: np.dtype | type,
        compute: Callable[[int], np.ndarray],
    ) -> Path:
        """Create entry ``key`` of ``count`` items computed by ``compute(i)``, unless it exists."""
        final = self.path(key)
        if final.is_file():
            return final
        with atomic_write(final) as tmp:
            array = np.lib.format.open_memmap(tmp, mode="w+", dtype=dtype, shape=(count, *shape))
            for i in range(count):
                array[i] = compute(i)
            array.flush()
            del array
        log.debug("cached %d items in %s", count, final)
        return final

    def open(self, key: str) -> np.ndarray:
        """The entry as a read-only memory map."""
        return np.load(self.path(key), mmap_mode="r")
