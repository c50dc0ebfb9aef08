"""Readers and writers of on-disk recording layouts; :func:`open_recording` picks the reader."""

from __future__ import annotations

from pathlib import Path

from datamodules.recording import Recording, RecordingError


def open_recording(path: str | Path) -> Recording:
    """Open a recording in any known layout (lazily where the layout allows)."""
    path = Path(path)
    if path.is_file() and path.suffix == ".mcap":
        from datamodules.formats.mcap_file import read_mcap

        return read_mcap(path)
    if not path.exists():
        raise RecordingError(f"{path}: no such file or directory")
    raise RecordingError(f"{path}: not a known recording layout (expected an .mcap file)")
