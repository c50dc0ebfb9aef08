"""Where the real MMAUD samples live, for the ``shared_data`` fixture and for tests that use them when present."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def shared_data_dir() -> Path:
    """Where the real MMAUD samples live: ``$AAUTE_SHARED_DATA`` or ``<repo>/../shared/data``."""
    return Path(os.environ.get("AAUTE_SHARED_DATA", REPO.parent / "shared" / "data"))
