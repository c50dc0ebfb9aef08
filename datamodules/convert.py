"""Convert recordings of any readable layout to the canonical MCAP format (``aaute convert``)."""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

from datamodules.formats import discover_recordings, open_recording
from datamodules.formats.mcap_file import write_mcap
from datamodules.recording import RecordingError

log = logging.getLogger(__name__)


def mcap_name(sequence_id: str) -> str:
    """A file name for a sequence id (path separators and odd characters become '_')."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", sequence_id).strip("._") + ".mcap"


def check_not_inside(src: Path, dst: Path) -> None:
    """Refuse a destination that is the source folder or lies inside it (its output would become input).

    Raises:
        RecordingError: naming both paths.
    """
    source, target = Path(src).resolve(), Path(dst).resolve()
    if source.is_dir() and (target == source or source in target.parents):
        where = "is the source folder itself" if target == source else "lies inside the source folder"
        raise RecordingError(f"{dst}: destination {where} {src}; the converted copies would sit beside the "
                             f"recordings they copy (same sequence ids); give a destination outside {src}")


def convert(
    src: str | Path,
    dst: str | Path,
    *,
    overwrite: bool = False,
    audio_format: str | None = None,
    drop_unread_lidar: bool = False,
    **reader_options: Any,
) -> list[Path]:
    """Write every recording found at ``src`` as MCAP.

    One recording and a ``dst`` ending in ``.mcap``: that file. Otherwise ``dst`` is a folder and
    each recording becomes ``<dst>/<sequence_id>.mcap``. Every recording is opened and every
    destination checked before anything is written, and each file is written atomically, so a
    failure leaves no partial file and never replaces an existing one unless ``overwrite``.

    Args:
        src: a recording or a root holding recordings (see :func:`discover_recordings`).
        dst: destination ``.mcap`` file or folder.
        overwrite: replace existing destination files.
        audio_format: sample format of the written audio ('S16LE', 'S32LE', 'F32LE'); default the
            source's own.
        drop_unread_lidar: write recordings even when their source holds LiDAR topics the reader could
            not place on a sensor (ROS 1 bags: ``meta["unread_lidar_topics"]``); otherwise refuse them.
        **reader_options: passed to :func:`open_recording` (e.g. ``sample_rate``, ``mapping``).

    Returns:
        The written files.
    """
    src, dst = Path(src), Path(dst)
    check_not_inside(src, dst)
    sources = discover_recordings(src)
    recordings = [(path, open_recording(path, **reader_options)) for path in sources]
    for path, recording in recordings:
        unread = recording.meta.get("unread_lidar_topics") or []
        if unread and not drop_unread_lidar:
            raise RecordingError(f"{path}: LiDAR topic(s) {', '.join(unread)} are not mapped to a sensor and would "
                                 f"be lost; map them (--mapping with mid360: <topic> / avia: <topic>) or pass "
                                 f"--drop-unread-lidar to convert without them")
    if dst.suffix == ".mcap":
        if len(recordings) != 1:
            raise RecordingError(f"{src} holds {len(recordings)} recordings; give a folder, not {dst}, as destination")
        targets = [dst]
    else:
        if dst.exists() and not dst.is_dir():
            raise RecordingError(f"{dst}: exists and is not a folder")
        targets = [dst / mcap_name(rec.sequence_id) for _, rec in recordings]
        clashes = {t for t in targets if targets.count(t) > 1}
        if clashes:
            raise RecordingError(f"{src}: several recordings would be written to {sorted(map(str, clashes))}; "
                                 f"their sequence ids collide")
    for (path, _), target in zip(recordings, targets, strict=True):
        if target.resolve() == path.resolve():
            raise RecordingError(f"{target}: destination is the source itself")
        if path.suffix == ".mcap" and target.resolve().parent == path.resolve().parent:
            raise RecordingError(f"{target}: destination lies beside its source {path}; the copy would hold the "
                                 f"same sequence id; give a destination folder elsewhere")
        if target.exists() and not overwrite:
            raise FileExistsError(f"{target} already exists; refusing to overwrite it (use --overwrite)")
    written = []
    for (path, recording), target in zip(recordings, targets, strict=True):
        log.info("converting %s (%s, %s) -> %s", path, recording.sequence_id,
                 recording.meta.get("source_format", "mcap"), target)
        unread = recording.meta.pop("unread_lidar_topics", None) or []
        if unread:  # the written recording holds what it holds; the metadata keeps what was left out
            recording.meta["dropped_lidar_topics"] = unread
        written.append(write_mcap(recording, target, overwrite=overwrite, audio_format=audio_format))
        if unread:
            log.warning("%s: dropped LiDAR topic(s) %s (not mapped to a sensor)", target, ", ".join(unread))
    return written
