"""Reader of the MMAUD UG2+ 2024 (track 5) challenge folders.

Layout (``reference/mmaud_and_teacher.md`` section 2)::

    <root>/<split>/seqN/
        lidar_360/<ros_time>.npy          Livox Mid-360 scan, float64 (rows x 3), zero rows are padding
        livox_avia/<ros_time>.npy         Livox Avia scan (pointed at the sky), same
        Image/<ros_time>.png              two 1280 x 960 fisheye images side by side (960 x 2560 x 3)
        ground_truth/<ros_time>.npy       Leica position (3,), train split only
        class/<ros_time>.npy              UAV type id 0-3, train split only
        radar_enhance_pcl/<ros_time>.npy  mmWave radar points (not part of a Recording; counted in meta)

File names are ROS times in seconds with 6 decimals; every sensor has its own stamps, and later
stages associate them by nearest timestamp (:meth:`FrameStream.nearest`). Frames are read when
indexed (only the file lists are kept), so memory does not grow with the recording beyond them.

Frame: points, ground truth and tracker output of this release share the Mid-360 sensor frame
(z up; the roof is at about z = -1.3 m there). It is kept as it is (no transform is guessed) and
named in ``meta["frame"]``. The release holds no audio: ``Recording.audio`` is None.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from datamodules.recording import (
    GAP_FACTOR,
    EncodedImage,
    ImageStream,
    PointCloud,
    PointCloudStream,
    Recording,
    RecordingError,
    Track,
    check_monotonic,
    check_track_values,
    count_gaps,
    json_safe,
)

log = logging.getLogger(__name__)

LIDAR_FOLDERS = {"mid360": "lidar_360", "avia": "livox_avia"}
IMAGE_FOLDER = "Image"
GROUND_TRUTH_FOLDER = "ground_truth"
CLASS_FOLDER = "class"
RADAR_FOLDER = "radar_enhance_pcl"
#: sub-folders that make a folder a UG2 sequence
UG2_FOLDERS = (*LIDAR_FOLDERS.values(), IMAGE_FOLDER, GROUND_TRUTH_FOLDER, CLASS_FOLDER, RADAR_FOLDER)
SPLIT_NAMES = ("train", "val", "test")

#: UG2 class ids (dataset24_t5.html: "Mavic 3, M30, M300, Phantom 4") -> our drone names; M30 has none
UG2_CLASSES: tuple[tuple[str, str | None], ...] = (
    ("Mavic 3", "mavic3"), ("M30", None), ("M300", "m300"), ("Phantom 4", "phantom4"),
)

FRAME = "ug2_mid360"
FRAME_DESCRIPTION = (
    "Livox Mid-360 sensor frame as released in the UG2+ 2024 data (z up, origin at the Mid-360; "
    "the roof is at about z = -1.3 m); Avia points, ground truth and the published tracker "
    "output are in the same frame. No transform applied."
)

def is_ug2_sequence(path: Path) -> bool:
    """Whether ``path`` is a folder holding UG2 sensor sub-folders."""
    path = Path(path)
    return path.is_dir() and any((path / name).is_dir() for name in UG2_FOLDERS)


def stamp_from_name(path: Path) -> float:
    """The ROS time (s) a UG2 file is named after, e.g. ``1706255621.600227.npy``."""
    try:
        return float(Path(path).stem)
    except ValueError:
        raise RecordingError(f"{path}: expected a file named <ros_time>.npy|png (seconds, e.g. "
                             f"1706255621.600227.npy)") from None


def list_stamped_files(folder: Path, suffixes: Sequence[str]) -> tuple[np.ndarray, list[str]]:
    """Files of ``folder`` with the given suffixes, sorted by the time in their names.

    Raises:
        RecordingError: a name is not a time, or two files carry the same time.
    """
    files = [p for p in folder.iterdir() if p.suffix.lower() in suffixes and not p.name.startswith(".")]
    others = sum(1 for p in folder.iterdir() if p.suffix.lower() not in suffixes and not p.name.startswith("."))
    if others:
        log.warning("%s: ignoring %d file(s) that are not %s", folder, others, "/".join(suffixes))
    stamps = np.array([stamp_from_name(p) for p in files], dtype=np.float64)
    order = np.argsort(stamps, kind="stable")
    stamps = stamps[order]
    names = [files[i].name for i in order]
    check_monotonic(stamps, str(folder))
    return stamps, names


def load_npy(path: Path) -> np.ndarray:
    """An .npy array, or a :class:`RecordingError` naming the file."""
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as error:
        raise RecordingError(f"{path}: not a readable .npy array ({error})") from error


def points_without_padding(array: np.ndarray, what: str) -> PointCloud:
    """A scan array (rows x 3, or x 4 with intensity) as a :class:`PointCloud` without all-zero rows."""
    array = np.asarray(array)
    if array.ndim != 2 or array.shape[1] not in (3, 4) or array.dtype.kind not in "fiu":
        raise RecordingError(f"{what}: expected a numeric (points x 3) array, got {array.dtype} {array.shape}")
    keep = np.any(array[:, :3] != 0, axis=1)
    array = array[keep]
    intensity = array[:, 3].astype(np.float32) if array.shape[1] == 4 else None
    return PointCloud(np.ascontiguousarray(array[:, :3], dtype=np.float32), intensity)


class NpyPointClouds(PointCloudStream):
    """One LiDAR folder of a UG2 sequence; each scan is loaded from its file when indexed."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.timestamps, self._names = list_stamped_files(self.folder, (".npy",))

    def __getitem__(self, index: int) -> PointCloud:
        path = self.folder / self._names[index]
        return points_without_padding(load_npy(path), str(path))


class FileImages(ImageStream):
    """Encoded image files (PNG/JPEG), read when indexed and kept encoded."""

    def __init__(self, folder: Path, timestamps: np.ndarray, names: Sequence[str]):
        self.folder = Path(folder)
        self.timestamps = np.asarray(timestamps, dtype=np.float64)
        self._names = list(names)
        if len(self._names) != len(self.timestamps):
            raise RecordingError(f"{folder}: {len(self.timestamps)} image times but {len(self._names)} files")

    def __getitem__(self, index: int) -> EncodedImage:
        path = self.folder / self._names[index]
        try:
            data = path.read_bytes()
        except OSError as error:
            raise RecordingError(f"{path}: cannot read image ({error})") from error
        return EncodedImage(data, image_format(path))


def image_format(path: Path) -> str:
    """'png' or 'jpeg' from a file name."""
    suffix = Path(path).suffix.lower()
    if suffix == ".png":
        return "png"
    if suffix in (".jpg", ".jpeg"):
        return "jpeg"
    raise RecordingError(f"{path}: expected a .png or .jpg image")


def read_position_files(folder: Path, stamps: np.ndarray, names: Sequence[str]) -> Track:
    """A track from one (3,) position file per time; non-finite positions become invalid points."""
    xyz = np.full((len(names), 3), np.nan)
    for i, name in enumerate(names):
        value = np.asarray(load_npy(folder / name), dtype=np.float64)
        if value.size != 3:
            raise RecordingError(f"{folder / name}: expected 3 values (x, y, z), got shape {value.shape}")
        xyz[i] = value.reshape(3)
    valid = np.all(np.isfinite(xyz), axis=1)
    if not valid.all():
        log.warning("%s: %d of %d positions are not finite; marked invalid", folder, int((~valid).sum()), len(valid))
    xyz[~valid] = 0.0
    check_track_values(stamps, xyz, valid, str(folder))
    return Track(stamps, xyz, valid)


def class_id(value: np.ndarray, what: str) -> int:
    """The class id held by a ``class/`` file: a single integer or a one-hot vector."""
    value = np.asarray(value).reshape(-1)
    if value.size == 1 and float(value[0]).is_integer():
        return int(value[0])
    if value.size > 1 and np.isin(value, (0, 1)).all() and int(value.sum()) == 1:
        return int(np.argmax(value))
    raise RecordingError(f"{what}: expected a class id or a one-hot vector, got {value.tolist()}")


def _read_class(folder: Path) -> int | None:
    _, names = list_stamped_files(folder, (".npy",))
    if not names:
        return None
    counts = Counter(class_id(load_npy(folder / n), str(folder / n)) for n in names)
    best, count = counts.most_common(1)[0]
    if len(counts) > 1:
        log.warning("%s: class ids differ between frames (%s); using the majority %d (%d of %d frames)",
                    folder, dict(counts), best, count, len(names))
    return best


def default_sequence_id(path: Path) -> str:
    """``<split>_<seq>`` for ``.../<split>/<seq>`` folders (unique across splits), else the folder name."""
    path = Path(path).resolve()
    if path.parent.name.lower() in SPLIT_NAMES:
        return f"{path.parent.name}_{path.name}"
    return path.name


def read_ug2(path: str | Path, *, sequence_id: str | None = None, drone: str | None = None) -> Recording:
    """Open one UG2 sequence folder lazily (file lists now, frames on access).

    Args:
        path: the ``seqN`` folder.
        sequence_id: defaults to ``<split>_<seqN>`` (or the folder name outside a split folder).
        drone: overrides the drone type taken from ``class/`` (validation/test sequences have none).

    Raises:
        RecordingError: the folder holds no UG2 sensor folders, a file name is not a time, two
            files share a time.
    """
    path = Path(path)
    if not is_ug2_sequence(path):
        raise RecordingError(f"{path}: not a UG2 sequence folder (expected sub-folders such as "
                             f"{', '.join(UG2_FOLDERS)})")
    lidar: dict[str, PointCloudStream] = {}
    meta: dict[str, Any] = {"source_format": "ug2", "source_path": str(path.resolve()), "frame": FRAME,
                            "frame_description": FRAME_DESCRIPTION}
    gaps: dict[str, int] = {}
    for sensor, name in LIDAR_FOLDERS.items():
        if not (path / name).is_dir():
            continue
        clouds = NpyPointClouds(path / name)
        if len(clouds) == 0:
            log.warning("%s: no scans in %s", path, name)
            continue
        lidar[sensor] = clouds
        gaps[name] = count_gaps(clouds.timestamps)
    frames = None
    if (path / IMAGE_FOLDER).is_dir():
        stamps, names = list_stamped_files(path / IMAGE_FOLDER, (".png", ".jpg", ".jpeg"))
        if names:
            frames = FileImages(path / IMAGE_FOLDER, stamps, names)
            gaps[IMAGE_FOLDER] = count_gaps(stamps)
    ground_truth = None
    if (path / GROUND_TRUTH_FOLDER).is_dir():
        stamps, names = list_stamped_files(path / GROUND_TRUTH_FOLDER, (".npy",))
        if names:
            ground_truth = read_position_files(path / GROUND_TRUTH_FOLDER, stamps, names)
            gaps[GROUND_TRUTH_FOLDER] = count_gaps(stamps)
    for name, count in gaps.items():
        if count:
            log.warning("%s: %d gap(s) in %s (steps over %.1f x the median step: missing frames)",
                        path, count, name, GAP_FACTOR)
    meta["gaps"] = gaps
    if (path / RADAR_FOLDER).is_dir():
        meta["radar_frames"] = sum(1 for p in (path / RADAR_FOLDER).glob("*.npy"))
    ug2_class = _read_class(path / CLASS_FOLDER) if (path / CLASS_FOLDER).is_dir() else None
    if ug2_class is not None:
        if not 0 <= ug2_class < len(UG2_CLASSES):
            raise RecordingError(f"{path / CLASS_FOLDER}: class id {ug2_class} outside the UG2 ids 0-3")
        meta["ug2_class"] = ug2_class
        meta["ug2_class_name"] = UG2_CLASSES[ug2_class][0]
        if drone is None:
            drone = UG2_CLASSES[ug2_class][1]
            if drone is None:
                log.info("%s: UG2 class %d (%s) has no drone type of ours; drone left unset",
                         path, ug2_class, UG2_CLASSES[ug2_class][0])
    if not lidar and frames is None and ground_truth is None:
        raise RecordingError(f"{path}: UG2 sequence folder without any scans, images or ground truth")
    return Recording(
        sequence_id=sequence_id or default_sequence_id(path),
        drone=drone,
        audio=None,
        lidar=lidar,
        frames=frames,
        ground_truth=ground_truth,
        meta=json_safe(meta),
    )

