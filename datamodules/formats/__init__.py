"""Readers and writers of on-disk recording layouts; :func:`open_recording` picks the reader.

Known layouts (one recording each):

==============  ===============================================================================
mcap            ``<name>.mcap``: the canonical format (:mod:`datamodules.formats.mcap_file`)
ug2             ``seqN/{lidar_360,livox_avia,Image,ground_truth,class}/<ros_time>.npy|png``
derived_npy     ``<root>/audio_npy/<seq>/`` with ``gt/``, ``pseudo_label/``, ... beside ``audio_npy/``
rosbag1         ``<name>.bag``, or a folder of the bags of one flight (sensor bag + ground-truth bag)
wav_folder      a folder of WAV files (one per channel or node), positions and ground-truth CSV beside
==============  ===============================================================================

:func:`discover_recordings` lists the recordings under a root (any mix of layouts, or a list file
of the derived layout); :func:`open_recording` opens one. Readers are imported when used, so
``rosbags`` is needed only for bags.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from datamodules.recording import Recording, RecordingError

log = logging.getLogger(__name__)

LAYOUTS = ("mcap", "ug2", "derived_npy", "rosbag1", "wav_folder")
EXPECTED = (
    "an .mcap recording, a UG2 sequence folder (seqN/{lidar_360,livox_avia,Image,ground_truth,class}/"
    "<ros_time>.npy), a derived npy root or sequence (audio_npy/<seq>/<idx>.npy beside gt/, pseudo_label/), "
    "a list file of that layout (<seq>/<idx>.npy lines), ROS 1 .bag files, or a folder of .wav files"
)
#: keyword options each reader accepts (open_recording passes on only these)
READER_OPTIONS: dict[str, tuple[str, ...]] = {
    "mcap": (),
    "ug2": ("sequence_id", "drone"),
    "derived_npy": ("sample_rate", "t0", "drone", "missing_audio"),
    "rosbag1": ("mapping", "sample_rate", "channels", "sample_format", "audio_stamp", "sequence_id", "drone"),
    "wav_folder": ("sequence_id", "drone", "t0"),
}


def detect_layout(path: str | Path) -> str:
    """The layout of one recording path: 'mcap', 'ug2', 'derived_npy', 'rosbag1' or 'wav_folder'.

    Raises:
        RecordingError: ``path`` does not exist or is no single recording of a known layout.
    """
    from datamodules.formats import derived_npy, ug2, wav_folder

    path = Path(path)
    if not path.exists():
        raise RecordingError(f"{path}: no such file or directory")
    if path.is_file():
        if path.suffix == ".mcap":
            return "mcap"
        if path.suffix == ".bag":
            return "rosbag1"
        raise RecordingError(f"{path}: not a known recording file; expected {EXPECTED}")
    if ug2.is_ug2_sequence(path):
        return "ug2"
    if derived_npy.locate_sequence(path) is not None or derived_npy.is_derived_root(path):
        return "derived_npy"
    if any(p.suffix == ".bag" for p in path.iterdir()):
        return "rosbag1"
    if wav_folder.is_wav_folder(path):
        return "wav_folder"
    try:
        inside = discover_recordings(path)
    except RecordingError:
        inside = []
    if inside:
        names = ", ".join(str(p.relative_to(path)) for p in inside[:3]) + (", ..." if len(inside) > 3 else "")
        raise RecordingError(f"{path}: not a known recording layout but a folder of {len(inside)} recordings "
                             f"({names}); give one of them here (commands that take a data root, such as "
                             f"'aaute info' or --data.root, read them all)")
    raise RecordingError(f"{path}: folder is not a known recording layout; expected {EXPECTED}")


def open_recording(path: str | Path, **options: Any) -> Recording:
    """Open one recording in any known layout (lazily where the layout allows).

    Args:
        path: an .mcap file, a UG2 sequence folder, a derived sequence folder (or a derived root
            holding one sequence), a .bag file or a folder holding the bags of one recording.
        **options: reader options (see :data:`READER_OPTIONS`), e.g. ``sample_rate=46080`` for the
            derived layout or ``mapping={...}`` for bags; options another layout would take are
            ignored (logged), unknown ones raise ``TypeError``.
    """
    path = Path(path)
    known = {name for names in READER_OPTIONS.values() for name in names}
    unknown = set(options) - known
    if unknown:
        raise TypeError(f"unknown reader option(s) {sorted(unknown)}; known: {sorted(known)}")
    layout = detect_layout(path)
    accepted = {k: v for k, v in options.items() if k in READER_OPTIONS[layout] and v is not None}
    ignored = sorted(k for k, v in options.items() if k not in READER_OPTIONS[layout] and v is not None)
    if ignored:
        log.debug("%s (%s): options %s do not apply", path, layout, ignored)
    if layout == "mcap":
        from datamodules.formats.mcap_file import read_mcap

        return read_mcap(path)
    if layout == "ug2":
        from datamodules.formats.ug2 import read_ug2

        return read_ug2(path, **accepted)
    if layout == "derived_npy":
        from datamodules.formats.derived_npy import open_derived

        return open_derived(path, **accepted)
    if layout == "wav_folder":
        from datamodules.formats.wav_folder import read_wav_folder

        return read_wav_folder(path, **accepted)
    from datamodules.formats.rosbag1 import open_rosbag1

    return open_rosbag1(path, **accepted)


def discover_all(roots: Iterable[str | Path]) -> list[Path]:
    """Every recording at or under each of ``roots`` (:func:`discover_recordings`), in order, once each."""
    found = [path for root in roots for path in discover_recordings(root)]
    return list(dict.fromkeys(found))


def discover_recordings(root: str | Path) -> list[Path]:
    """Every recording at or under ``root``, as paths :func:`open_recording` accepts, sorted.

    ``root`` may be one recording, a folder holding recordings of any layout at any depth (each
    folder of .bag files is one recording), a derived npy root (one path per sequence:
    ``<root>/audio_npy/<seq>``) or a list file of the derived layout (the sequences it names;
    every listed sample must exist).

    Raises:
        RecordingError: ``root`` does not exist or holds no recording of a known layout.
    """
    from datamodules.formats import derived_npy, ug2, wav_folder

    root = Path(root)
    if not root.exists():
        raise RecordingError(f"{root}: no such file or directory")
    if root.is_file():
        if root.suffix in (".mcap", ".bag"):
            return [root]
        if root.suffix == ".txt":
            samples = derived_npy.read_sample_list(root)
            base = derived_npy.find_root_of(root)
            if not samples:
                raise RecordingError(f"{root}: list file names no samples")
            return [derived_npy.sequence_folder(base, seq) for seq in sorted(samples)]
        raise RecordingError(f"{root}: not a known recording file; expected {EXPECTED}")
    found: list[Path] = []

    def walk(folder: Path) -> None:
        if ug2.is_ug2_sequence(folder):
            found.append(folder)
            return
        if derived_npy.locate_sequence(folder) is not None:
            found.append(folder)
            return
        if derived_npy.is_derived_root(folder):
            found.extend(derived_npy.sequence_folder(folder, seq) for seq in derived_npy.derived_sequences(folder))
            return
        entries = sorted(os.scandir(folder), key=lambda e: e.name)
        if any(e.is_file() and e.name.endswith(".bag") for e in entries) or wav_folder.is_wav_folder(folder):
            found.append(folder)
        for entry in entries:
            if entry.name.startswith("."):
                continue
            if entry.is_file() and entry.name.endswith(".mcap"):
                found.append(Path(entry.path))
            elif entry.is_dir():
                walk(Path(entry.path))

    walk(root)
    if not found:
        raise RecordingError(f"{root}: no recordings found; expected {EXPECTED}")
    return sorted(dict.fromkeys(found))
