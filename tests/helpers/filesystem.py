"""Faults of the file system that root does not see: tests run as root here, and root writes through chmod."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


def deny_writes_under(monkeypatch: pytest.MonkeyPatch, folder: Path) -> None:
    """Make every ``os.open`` below ``folder`` fail as a folder of mode 555 does for a user other than root."""
    real_open = os.open

    def read_only(path, *args, **kwargs):
        if str(path).startswith(str(folder)):
            raise PermissionError(13, "Permission denied", str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", read_only)
