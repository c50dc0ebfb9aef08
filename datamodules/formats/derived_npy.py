"""Reader of the derived per-sample npy layout of the AAUTE / AV-FDTI / TAME code (MMAUD V1).

Layout (``reference/baselines.md`` section 12, ``reference/mmaud_and_teacher.md`` section 1.7)::

    <root>/audio_npy/<seq>/<idx>.npy     one audio chunk, (samples x channels); AV-FDTI: np_data_align/
    <root>/gt/<seq>/<idx>.npy            ground-truth xyz (3,); AV-FDTI keeps it in label/
    <root>/pseudo_label/<seq>/<idx>.npy  LiDAR pseudo-label xyz (3,); TAME/AV-DTEC keep it in lidar/
    <root>/label/<seq>/<idx>.npy         TAME/AV-DTEC: class id (1 value); AV-FDTI: xyz (3 values)
    <root>/image/<seq>/<idx>.png         camera frame
    <root>/Detection_new/<seq>/<idx>.npy element 0 = drone visible in the image (0/1)
    list files: one ``<seq>/<idx>.npy`` line per sample (train/val splits)

``<seq>`` may be nested (``a/b``); it is also the sequence id. Each sequence is rebuilt as one
continuous :class:`Recording`:

* Timing convention: consecutive indices are consecutive, non-overlapping chunks of one audio
  stream. With chunk length ``L`` samples at ``sample_rate`` the chunk duration is
  ``D = L / sample_rate``; chunk ``idx`` covers ``[t0 + idx * D, t0 + (idx + 1) * D)`` and its
  labels (gt, pseudo-label, image, visibility) are stamped at the **end of the chunk**,
  ``t0 + (idx + 1) * D``, rounded up to a whole nanosecond (causal: a window ending at a label
  time includes its chunk as the latest audio, as in the AAUTE window ``idx, idx-2, ..., idx-8``).
  ``t0`` is 0 unless given (per sequence if wanted): the layout holds no real timestamps.
* The sample rate is not stored in the layout: 46080 Hz in the AAUTE code, 48000 Hz in AV-FDTI,
  TAME and AV-DTEC. The default here is 48000; pass ``sample_rate`` or put it in
  ``<root>/aaute_layout.yaml``. ``meta["sample_rate_assumed"]`` says whether it was given.
* Microphone positions are unknown for real MMAUD: zeros, with ``meta["mic_positions_known"] = False``.
* Audio is read lazily, chunk files for the requested sample range only.
"""

from __future__ import annotations

import logging
import os
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from datamodules.formats.ug2 import FileImages, load_npy
from datamodules.recording import (
    DRONE_TYPES,
    AudioStream,
    Recording,
    RecordingError,
    Track,
    check_track_values,
    count_gaps,
    json_safe,
    ns_to_seconds,
    seconds_to_ns,
)

log = logging.getLogger(__name__)

AUDIO_FOLDERS = ("audio_npy", "np_data_align", "audio_numpy")
GROUND_TRUTH_FOLDERS = ("gt", "ground_truth", "label")  #: label/ only when it holds positions (AV-FDTI)
PSEUDO_LABEL_FOLDERS = ("pseudo_label", "lidar")  #: lidar/ only when it holds positions (TAME, AV-DTEC)
CLASS_FOLDER = "label"  #: when it holds one value per sample (TAME, AV-DTEC)
IMAGE_FOLDERS = ("image", "Image")
DETECTION_FOLDERS = ("Detection_new", "detect_new")
LAYOUT_FILE = "aaute_layout.yaml"
LAYOUT_KEYS = ("sample_rate", "t0", "drone", "missing_audio")
DEFAULT_SAMPLE_RATE = 48000.0

#: class ids of the "Data-M" layout (TAME ``evaluate.py``): folder names 0-4 and label/ values
DATA_M_CLASSES = ("mavic2", "mavic3", "phantom4", "avata", "m300")
#: AV-FDTI sequence-name prefixes (``image_process.make_class``); M30 has no drone type of ours
AVFDTI_PREFIXES = (("m300s", "m300"), ("m30s", None), ("m3e", "mavic3"), ("p4s", "phantom4"),
                   ("b1", "mavic3"), ("b2", None), ("b3", "m300"), ("b4", "phantom4"))

FRAME = "mmaud_v1_derived"
FRAME_DESCRIPTION = (
    "positions as stored in the derived per-sample files: ground truth in the fixed Leica frame of "
    "MMAUD V1 (metres); pseudo-labels in whatever frame their teacher wrote (not checked). No "
    "transform applied."
)


# ============================================================================================ layout


def audio_folder(root: Path) -> Path | None:
    """The audio folder of a derived root (``audio_npy/``, ``np_data_align/`` ...), if any."""
    for name in AUDIO_FOLDERS:
        if (Path(root) / name).is_dir():
            return Path(root) / name
    return None


def is_derived_root(path: Path) -> bool:
    return Path(path).is_dir() and audio_folder(path) is not None


def _index_of(path: Path) -> int | None:
    try:
        return int(path.stem)
    except ValueError:
        return None


def derived_sequences(root: Path) -> list[str]:
    """Sequence names (relative paths below the audio folder) of a derived root, sorted."""
    base = audio_folder(root)
    if base is None:
        raise RecordingError(f"{root}: no audio folder ({' or '.join(AUDIO_FOLDERS)}) of the derived npy layout")
    found = []
    for folder, _dirs, files in os.walk(base):
        if any(f.endswith(".npy") for f in files):
            found.append(Path(folder).relative_to(base).as_posix())
    return sorted(found)


def locate_sequence(path: Path) -> tuple[Path, str] | None:
    """``(root, seq)`` if ``path`` is a sequence folder ``<root>/audio_npy/<seq>`` of the layout."""
    path = Path(path).resolve()
    if not path.is_dir():
        return None
    for ancestor in path.parents:
        if ancestor.name in AUDIO_FOLDERS:
            if ancestor == path:
                return None
            return ancestor.parent, path.relative_to(ancestor).as_posix()
    return None


def sequence_folder(root: Path, seq: str) -> Path:
    base = audio_folder(root)
    if base is None:
        raise RecordingError(f"{root}: no audio folder ({' or '.join(AUDIO_FOLDERS)})")
    return base / seq


def read_sample_list(list_file: str | Path, root: str | Path | None = None) -> dict[str, list[int]]:
    """The samples a list file names, ``{seq: [idx, ...]}``; every named sample must exist.

    Lines are ``<seq>/<idx>.<ext>`` (the extension is ignored, as the original loaders do).
    ``root`` defaults to the nearest ancestor of the list file that holds an audio folder.

    Raises:
        RecordingError: a line is malformed, or names samples whose audio file is missing.
    """
    list_file = Path(list_file)
    root = Path(root) if root is not None else find_root_of(list_file)
    base = audio_folder(root)
    if base is None:
        raise RecordingError(f"{list_file}: {root} has no audio folder ({' or '.join(AUDIO_FOLDERS)})")
    samples: dict[str, list[int]] = {}
    missing: list[str] = []
    for number, line in enumerate(list_file.read_text().splitlines(), start=1):
        line = line.strip()
        if not line:
            continue
        rel = Path(line)
        index = _index_of(rel)
        if index is None or rel.parent == Path("."):
            raise RecordingError(f"{list_file}:{number}: expected a '<seq>/<idx>.npy' line, got {line!r}")
        seq = rel.parent.as_posix()
        if not (base / seq / f"{rel.stem}.npy").is_file():
            missing.append(line)
        samples.setdefault(seq, []).append(index)
    if missing:
        raise RecordingError(f"{list_file}: {len(missing)} listed sample(s) have no audio file under {base} "
                             f"(first: {', '.join(missing[:5])})")
    return {seq: sorted(set(indices)) for seq, indices in samples.items()}


def find_root_of(list_file: Path) -> Path:
    """The nearest ancestor of ``list_file`` that is a derived root."""
    for ancestor in Path(list_file).resolve().parents:
        if is_derived_root(ancestor):
            return ancestor
    raise RecordingError(f"{list_file}: no folder above it holds an audio folder ({' or '.join(AUDIO_FOLDERS)}); "
                         f"pass the derived root explicitly")


def read_layout_file(root: Path, keys: tuple[str, ...] = LAYOUT_KEYS) -> dict[str, Any]:
    """Options from ``<root>/aaute_layout.yaml``, if present: by default a derived root's (sample_rate, t0, drone,
    missing_audio); another layout passes the ``keys`` it takes."""
    path = Path(root) / LAYOUT_FILE
    if not path.is_file():
        return {}
    import yaml

    try:
        options = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as error:
        raise RecordingError(f"{path}: not valid YAML ({error})") from error
    if not isinstance(options, dict) or set(options) - set(keys):
        raise RecordingError(f"{path}: expected a mapping with keys among {list(keys)}, got {options!r}")
    return options


# ============================================================================================= audio


@dataclass
class _ChunkHeader:
    shape: tuple[int, ...]
    fortran: bool
    dtype: np.dtype
    offset: int


def _npy_header(path: Path) -> _ChunkHeader:
    try:
        with open(path, "rb") as stream:
            version = np.lib.format.read_magic(stream)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(stream)
            else:
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(stream)
            return _ChunkHeader(tuple(shape), bool(fortran), np.dtype(dtype), stream.tell())
    except (OSError, ValueError) as error:
        raise RecordingError(f"{path}: not a readable .npy array ({error})") from error


#: chunk dtypes whose values the MCAP writer can store exactly in the same sample format
_SAMPLE_FORMATS = {"<i2": "S16LE", "<i4": "S32LE", "<f4": "F32LE"}


class ChunkedNpyAudio(AudioStream):
    """Audio of one derived sequence: consecutive ``<idx>.npy`` chunks read for a sample range only.

    Integer chunks are scaled to full scale (int16 / 32768, as the MCAP layout does); float chunks
    are taken as they are.
    """

    def __init__(self, folder: Path, indices: Sequence[int], sample_rate: float, t0: float,
                 missing_audio: str = "error"):
        self.folder = Path(folder)
        indices = sorted(indices)
        if not indices:
            raise RecordingError(f"{folder}: no <idx>.npy audio chunks")
        headers = {i: _npy_header(self.folder / f"{i}.npy") for i in indices}
        first = headers[indices[0]]
        shapes = Counter((h.shape, h.dtype.str) for h in headers.values())
        if len(shapes) > 1:
            common = shapes.most_common(1)[0][0]
            odd = next(i for i, h in headers.items() if (h.shape, h.dtype.str) != common)
            found = ", ".join(f"{shape} {dtype}: {n} file(s)" for (shape, dtype), n in shapes.items())
            raise RecordingError(
                f"{folder}: audio chunks differ in shape or dtype ({found}; first odd one {odd}.npy); every "
                f"chunk must be (samples x channels) of one length, since a chunk lasts its length / sample rate"
            )
        if len(first.shape) != 2 or first.dtype.kind not in "fi" or first.shape[0] == 0:
            raise RecordingError(f"{self.folder / f'{indices[0]}.npy'}: expected a (samples x channels) numeric "
                                 f"array, got {first.dtype} {first.shape}")
        span = range(indices[0], indices[-1] + 1)
        missing = sorted(set(span) - set(indices))
        if missing and missing_audio != "zeros":
            raise RecordingError(
                f"{folder}: {len(missing)} audio chunk(s) missing between {indices[0]}.npy and {indices[-1]}.npy "
                f"(first: {', '.join(f'{i}.npy' for i in missing[:5])}); the chunks must be consecutive "
                f"(or pass missing_audio='zeros' to fill them with silence)"
            )
        if missing:
            log.warning("%s: %d missing audio chunk(s) filled with zeros", folder, len(missing))
        self.missing_chunks = len(missing)
        self.first_index = indices[0]
        self.chunk_length = int(first.shape[0])
        self._channels = int(first.shape[1])
        self._dtype = first.dtype
        self._fortran = {i: h.fortran for i, h in headers.items()}
        self._offsets = {i: h.offset for i, h in headers.items()}
        self.sample_rate = float(sample_rate)
        self.t0 = float(t0)
        self.num_samples = self.chunk_length * len(span)
        self.mic_positions = np.zeros((self._channels, 3))
        self.sample_format = _SAMPLE_FORMATS.get(self._dtype.str)
        kind = self._dtype.kind
        self._scale = 2.0 ** (8 * self._dtype.itemsize - 1) if kind == "i" else 1.0

    @property
    def chunk_duration(self) -> float:
        return self.chunk_length / self.sample_rate

    def _chunk(self, index: int) -> np.ndarray:
        """Chunk ``index`` as float32, channels x samples."""
        if index not in self._offsets:
            return np.zeros((self._channels, self.chunk_length), dtype=np.float32)
        path = self.folder / f"{index}.npy"
        count = self.chunk_length * self._channels
        try:
            flat = np.fromfile(path, dtype=self._dtype, count=count, offset=self._offsets[index])
        except OSError as error:
            raise RecordingError(f"{path}: cannot read audio chunk ({error})") from error
        if flat.size != count:
            raise RecordingError(f"{path}: truncated audio chunk ({flat.size} of {count} values)")
        if self._fortran[index]:
            block = flat.reshape(self._channels, self.chunk_length)
        else:
            block = flat.reshape(self.chunk_length, self._channels).T
        block = (block / self._scale).astype(np.float32) if self._scale != 1.0 else block.astype(np.float32)
        if not np.isfinite(block).all():
            raise RecordingError(f"{path}: audio chunk holds NaN or infinite samples")
        return block

    def read(self, start: int, stop: int) -> np.ndarray:
        self._check_range(start, stop)
        out = np.zeros((self.num_channels, stop - start), dtype=np.float32)
        if stop == start:
            return out
        length = self.chunk_length
        for k in range(start // length, (stop - 1) // length + 1):
            lo, hi = max(start, k * length), min(stop, (k + 1) * length)
            block = self._chunk(self.first_index + k)
            out[:, lo - start:hi - start] = block[:, lo - k * length:hi - k * length]
        return out


# ============================================================================================ tracks


def label_times(offset: float, indices: np.ndarray, duration: float) -> np.ndarray:
    """Chunk-end times ``offset + (idx + 1) * duration``, rounded up to whole nanoseconds.

    Whole nanoseconds survive the MCAP round trip bit for bit, and rounding up (by < 1 ns) keeps
    the sample a label time points at from falling one sample short of its chunk's end.
    """
    exact = offset + (np.asarray(indices, dtype=np.float64) + 1.0) * duration
    ns = seconds_to_ns(exact)
    ns = ns + (ns_to_seconds(ns) < exact)
    return ns_to_seconds(ns)


def _values(path: Path) -> np.ndarray:
    return np.asarray(load_npy(path), dtype=np.float64).reshape(-1)


def _sample_files(folder: Path) -> dict[int, Path]:
    files = {}
    if folder.is_dir():
        for path in folder.iterdir():
            index = _index_of(path)
            if index is not None and path.suffix in (".npy", ".png", ".jpg", ".jpeg"):
                files[index] = path
    return files


def _values_per_sample(folder: Path) -> int | None:
    """How many values the first file of a label folder holds (3 = position, 1 = class id)."""
    files = _sample_files(folder)
    if not files:
        return None
    return int(_values(files[min(files)]).size)


def _read_track(folder: Path, indices: np.ndarray, times: np.ndarray, what: str) -> tuple[Track, int]:
    """A track at ``times`` (one per chunk index) from ``<idx>.npy`` 3-vectors; absent files are invalid.

    Returns the track and the number of label files outside the audio's index range.
    """
    files = _sample_files(folder)
    xyz = np.zeros((indices.size, 3))
    valid = np.zeros(indices.size, dtype=bool)
    position = {int(i): k for k, i in enumerate(indices)}
    outside = 0
    bad = 0
    for index, path in files.items():
        k = position.get(index)
        if k is None:
            outside += 1
            continue
        value = _values(path)
        if value.size != 3:
            raise RecordingError(f"{path}: expected 3 values (x, y, z) for the {what}, got {value.size}")
        if np.isfinite(value).all():
            xyz[k] = value
            valid[k] = True
        else:
            bad += 1
    absent = int(indices.size - valid.sum())
    if absent:
        log.warning("%s: %d of %d chunks have no (finite) %s; those label times are marked invalid",
                    folder, absent, indices.size, what)
    if bad:
        log.warning("%s: %d %s file(s) hold non-finite values", folder, bad, what)
    check_track_values(times, xyz, valid, f"{folder} ({what})")
    return Track(times, xyz, valid), outside


def _sequence_drone(seq: str, root: Path, labels: Path | None) -> tuple[str | None, str]:
    """The drone type from the sequence name or the label/ class ids, and where it came from."""
    name = seq.split("/")[0].lower()
    if name in DRONE_TYPES:
        return name, "sequence name"
    for prefix, drone in AVFDTI_PREFIXES:
        if name.startswith(prefix):
            return drone, f"AV-FDTI sequence name prefix {prefix!r}"
    if name.isdigit() and int(name) < len(DATA_M_CLASSES):
        return DATA_M_CLASSES[int(name)], "Data-M class folder (0 Mavic2, 1 Mavic3, 2 Phantom4, 3 Avata, 4 M300)"
    if labels is not None:
        files = _sample_files(labels)
        counts = Counter(int(_values(p)[0]) for p in files.values())
        if counts:
            best = counts.most_common(1)[0][0]
            if len(counts) > 1:
                log.warning("%s: class ids differ between samples (%s); using the majority", labels, dict(counts))
            if 0 <= best < len(DATA_M_CLASSES):
                return DATA_M_CLASSES[best], "label/ class id (Data-M classes)"
    return None, "unknown"


def _per_sequence(value: Any, seq: str) -> Any:
    """``value[seq]`` for a per-sequence mapping (None when absent), else ``value``."""
    if isinstance(value, dict):
        return value.get(seq)
    return value


# =========================================================================================== reading


def read_derived_npy(
    root: str | Path,
    seq: str,
    *,
    sample_rate: float | None = None,
    t0: float | dict[str, float] | None = None,
    drone: str | dict[str, str] | None = None,
    missing_audio: str | None = None,
) -> Recording:
    """Rebuild sequence ``seq`` of a derived root as one continuous recording.

    Args:
        root: the folder holding ``audio_npy/`` (or ``np_data_align/``), ``gt/``, ...
        seq: the sequence name, the ``<seq>`` of ``<seq>/<idx>.npy``.
        sample_rate: audio sample rate (Hz); default from ``aaute_layout.yaml``, else 48000.
        t0: time (s) of the start of chunk index 0, or a ``{seq: t0}`` mapping; default 0.
        drone: drone type (or ``{seq: drone}``), overriding the one read from names / class ids.
        missing_audio: 'error' (default) or 'zeros' for missing chunk files inside the index range.

    Raises:
        RecordingError: no audio chunks, chunks of different lengths, missing chunks, malformed labels.
    """
    root = Path(root)
    layout = read_layout_file(root)
    folder = sequence_folder(root, seq)
    if not folder.is_dir():
        raise RecordingError(f"{folder}: no such sequence folder in the derived layout")
    given_rate = sample_rate if sample_rate is not None else layout.get("sample_rate")
    rate = float(given_rate) if given_rate is not None else DEFAULT_SAMPLE_RATE
    if not rate > 0:
        raise RecordingError(f"{root}: sample rate must be positive, got {rate}")
    offset = _per_sequence(t0 if t0 is not None else layout.get("t0"), seq)
    offset = 0.0 if offset is None else float(offset)
    missing = missing_audio or layout.get("missing_audio") or "error"
    if missing not in ("error", "zeros"):
        raise RecordingError(f"{root}: missing_audio must be 'error' or 'zeros', got {missing!r}")

    audio = _audio(folder, rate, offset, missing)
    duration = audio.chunk_duration
    indices = np.arange(audio.first_index, audio.first_index + audio.num_samples // audio.chunk_length)
    times = label_times(offset, indices, duration)
    meta: dict[str, Any] = {
        "source_format": "derived_npy",
        "source_path": str(root.resolve()),
        "layout_sequence": seq,
        "frame": FRAME,
        "frame_description": FRAME_DESCRIPTION,
        "timing": "chunk idx covers [t0 + idx*D, t0 + (idx+1)*D); labels at the chunk end t0 + (idx+1)*D (ceil to ns)",
        "chunk_samples": audio.chunk_length,
        "chunk_duration_s": duration,
        "first_index": int(audio.first_index),
        "sample_rate_assumed": given_rate is None,
        "mic_positions_known": False,
        "audio_missing_chunks": audio.missing_chunks,
        "folders": {},
    }
    outside: dict[str, int] = {}
    ground_truth, pseudo = _tracks(root, seq, indices, times, meta["folders"], outside)
    class_folder = root / CLASS_FOLDER / seq
    class_folder = class_folder if class_folder.is_dir() and _values_per_sample(class_folder) == 1 else None
    frames = _images(root, seq, audio.first_index, indices, offset, duration, meta["folders"], outside)
    _visibility(root, seq, audio.first_index, indices, ground_truth, meta["folders"])
    for what, count in outside.items():
        if count:
            log.warning("%s: %d %s file(s) lie outside the audio's chunk range %d..%d; ignored",
                        root, count, what, audio.first_index, int(indices[-1]))
    given_drone = drone if drone is not None else layout.get("drone")
    chosen, meta["drone_source"] = _drone(seq, root, given_drone, class_folder)
    return Recording(
        sequence_id=seq,
        drone=chosen,
        audio=audio,
        ground_truth=ground_truth,
        pseudo_labels=pseudo,
        frames=frames,
        meta=json_safe(meta),
    )


def _audio(folder: Path, rate: float, offset: float, missing: str) -> ChunkedNpyAudio:
    """The sequence's audio, its chunk index 0 starting at ``offset`` seconds."""
    files = _sample_files(folder)
    not_indexed = [p.name for p in folder.glob("*.npy") if _index_of(p) is None]
    if not_indexed:
        raise RecordingError(f"{folder}: audio files must be named <idx>.npy with an integer idx; "
                             f"found {len(not_indexed)} others (e.g. {not_indexed[0]})")
    audio = ChunkedNpyAudio(folder, sorted(files), rate, 0.0, missing)
    audio.t0 = offset + audio.first_index * audio.chunk_duration
    return audio


def _pick(root: Path, seq: str, candidates: Sequence[str], values: int | None = 3) -> Path | None:
    """The sequence's folder under the first candidate name that exists (and holds ``values`` per sample)."""
    for name in candidates:
        path = root / name / seq
        if path.is_dir() and (values is None or _values_per_sample(path) == values):
            return path
    return None


def _tracks(root: Path, seq: str, indices: np.ndarray, times: np.ndarray, folders: dict[str, str],
            outside: dict[str, int]) -> tuple[Track | None, Track | None]:
    """Ground truth and pseudo-labels at the label times (None when the layout has none).

    Adds the folders read to ``folders`` and the count of label files outside the chunk range to ``outside``.
    """
    ground_truth = pseudo = None
    gt_folder = _pick(root, seq, GROUND_TRUTH_FOLDERS)
    if gt_folder is not None:
        ground_truth, outside["ground_truth"] = _read_track(gt_folder, indices, times, "ground truth")
        folders["ground_truth"] = gt_folder.parent.name
    pseudo_folder = _pick(root, seq, PSEUDO_LABEL_FOLDERS)
    if pseudo_folder is not None:
        pseudo, outside["pseudo_label"] = _read_track(pseudo_folder, indices, times, "pseudo-label")
        folders["pseudo_labels"] = pseudo_folder.parent.name
    return ground_truth, pseudo


def _images(root: Path, seq: str, first: int, indices: np.ndarray, offset: float, duration: float,
            folders: dict[str, str], outside: dict[str, int]) -> FileImages | None:
    """The camera frames of the chunks of the audio's range, stamped like the labels (None without any).

    Adds the folder read to ``folders`` and the count of images outside the chunk range to ``outside``.
    """
    image_folder = _pick(root, seq, IMAGE_FOLDERS, values=None)
    if image_folder is None:
        return None
    images = {i: p for i, p in _sample_files(image_folder).items() if p.suffix != ".npy"}
    inside = sorted(i for i in images if first <= i < indices[-1] + 1)
    outside["image"] = len(images) - len(inside)
    if not inside:
        return None
    stamps = label_times(offset, np.asarray(inside), duration)
    frames = FileImages(image_folder, stamps, [images[i].name for i in inside])
    folders["frames"] = image_folder.parent.name
    gaps = count_gaps(stamps)
    if gaps:
        log.warning("%s: %d gap(s) in the images", image_folder, gaps)
    return frames


def _visibility(root: Path, seq: str, first: int, indices: np.ndarray, ground_truth: Track | None,
                folders: dict[str, str]) -> None:
    """Attach the ``Detection_new`` flags (drone visible in the image) to the ground truth's quality."""
    detection = _pick(root, seq, DETECTION_FOLDERS, values=None)
    if detection is None:
        return
    if ground_truth is None:
        log.warning("%s: visibility flags ignored: the sequence has no ground truth to attach them to", detection)
        return
    visible = np.full(indices.size, np.nan)
    for index, path in _sample_files(detection).items():
        if first <= index <= indices[-1]:
            visible[index - first] = _values(path)[0]
    ground_truth.quality["image_visible"] = visible
    folders["image_visible"] = detection.parent.name


def _drone(seq: str, root: Path, given: str | dict[str, str] | None, labels: Path | None) -> tuple[str | None, str]:
    """The drone type as given (for this sequence), else from the names or class ids, and where it came from."""
    chosen = _per_sequence(given, seq) if given is not None else None
    if chosen is not None:
        return chosen, "given"
    return _sequence_drone(seq, root, labels)


def open_derived(path: str | Path, **options: Any) -> Recording:
    """Open a derived sequence folder (``<root>/audio_npy/<seq>``) or a root holding one sequence."""
    path = Path(path)
    located = locate_sequence(path)
    if located is not None:
        return read_derived_npy(*located, **options)
    if is_derived_root(path):
        sequences = derived_sequences(path)
        if len(sequences) == 1:
            return read_derived_npy(path, sequences[0], **options)
        raise RecordingError(
            f"{path}: derived npy root with {len(sequences)} sequences ({', '.join(sequences[:5])}"
            f"{', ...' if len(sequences) > 5 else ''}); open one sequence folder "
            f"({audio_folder(path).name}/<seq>), or give the root where a data root is expected (--data.root)"
        )
    raise RecordingError(f"{path}: not a derived npy sequence (expected <root>/{AUDIO_FOLDERS[0]}/<seq>/<idx>.npy)")
