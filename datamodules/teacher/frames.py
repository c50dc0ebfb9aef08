"""Input hygiene for the teacher: read LiDAR frames, drop padding and broken points, check units.

Real UG2 frames are zero-padded (all-zero rows are padding, ``reference/mmaud_and_teacher.md``
section 2.2 [V]); converted or corrupted recordings can hold NaN/inf points, points in millimetres
or timestamps that go backwards. Each problem is counted per sensor and reported once per
recording (:meth:`FrameStats.report`), or raised as :class:`RecordingError` when the teacher could
only produce nonsense (no LiDAR, no returns at all, millimetres, time going backwards).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from datamodules.recording import PointCloudStream, RecordingError, check_monotonic

log = logging.getLogger(__name__)

#: frames whose median range feeds the unit check
_UNIT_CHECK_FRAMES = 20


@dataclass
class FrameStats:
    """What input hygiene found in one sensor's frames (counts over the recording)."""

    sensor: str
    frames: int = 0
    points: int = 0  #: real returns kept
    padding_rows: int = 0  #: all-zero rows dropped
    empty_frames: int = 0  #: frames without a single real return
    nonfinite_points: int = 0
    nonfinite_frames: int = 0
    far_points: int = 0  #: beyond ``max_range_m`` from the sensor, dropped
    #: median range (before any dropping) of the first non-empty frames, for the unit check
    median_ranges: list[float] = field(default_factory=list)

    def report(self, what: str) -> None:
        """Log the problems found (warnings for data loss, debug for routine padding)."""
        if self.nonfinite_points:
            log.warning("%s %s: dropped %d NaN/inf points in %d of %d frames", what, self.sensor,
                        self.nonfinite_points, self.nonfinite_frames, self.frames)
        if self.far_points:
            log.warning("%s %s: dropped %d points beyond the plausible range", what, self.sensor, self.far_points)
        if self.empty_frames:
            level = logging.WARNING if self.empty_frames == self.frames else logging.INFO
            log.log(level, "%s %s: %d of %d frames hold no returns (all padding / empty)", what, self.sensor,
                    self.empty_frames, self.frames)
        log.debug("%s %s: %d frames, %d returns kept, %d padding rows dropped", what, self.sensor, self.frames,
                  self.points, self.padding_rows)


def check_timestamps(stream: PointCloudStream, what: str) -> np.ndarray:
    """The stream's timestamps as float64, after checking they are finite and strictly increasing."""
    times = np.asarray(stream.timestamps, dtype=np.float64)
    bad = np.count_nonzero(~np.isfinite(times))
    if bad:
        raise RecordingError(f"{what}: {bad} of {times.size} frame timestamps are NaN/inf")
    check_monotonic(times, what)
    return times


def clean_points(
    points: np.ndarray,
    stats: FrameStats,
    sensor_position: np.ndarray,
    unit_scale: float = 1.0,
    max_range_m: float = 1000.0,
) -> np.ndarray:
    """One frame's real returns as float64 N x 3 (metres), counting what was dropped.

    Args:
        points: the frame as stored (N x 3 or more columns; only xyz is used).
        stats: counters to update.
        sensor_position: the sensor's origin (rig frame) from which ranges are measured.
        unit_scale: factor to metres (0.001 for a recording stored in millimetres).
        max_range_m: returns farther than this are implausible for a Livox sensor (Avia range gate
            450 m, ``reference/mmaud_and_teacher.md`` section 4 [V]) and dropped with a count.
    """
    xyz = np.asarray(points)
    if xyz.ndim != 2 or xyz.shape[1] < 3:
        raise RecordingError(f"{stats.sensor}: a frame holds points of shape {xyz.shape}; expected N x 3")
    xyz = xyz[:, :3].astype(np.float64)
    stats.frames += 1
    squared = np.einsum("ij,ij->i", xyz, xyz)  # NaN/inf for a broken point, 0 exactly for padding
    finite = np.isfinite(squared)
    real = squared > 0.0
    if not finite.all():
        stats.nonfinite_points += int(np.count_nonzero(~finite))
        stats.nonfinite_frames += 1
    kept = finite & real
    stats.padding_rows += int(np.count_nonzero(finite & ~real))
    if not kept.all():
        xyz = xyz[kept]
    if unit_scale != 1.0:
        xyz = xyz * unit_scale
    if xyz.shape[0]:
        offset = xyz - sensor_position
        squared = np.einsum("ij,ij->i", offset, offset)
        if len(stats.median_ranges) < _UNIT_CHECK_FRAMES:
            stats.median_ranges.append(float(np.sqrt(np.median(squared))))
        near = squared <= max_range_m**2
        if not near.all():
            stats.far_points += int(np.count_nonzero(~near))
            xyz = xyz[near]
    if xyz.shape[0] == 0:
        stats.empty_frames += 1
    stats.points += int(xyz.shape[0])
    return xyz


def check_units(stats: FrameStats, what: str, max_median_range_m: float = 500.0) -> None:
    """Raise if the returns look like millimetres (a median range far beyond any Livox range).

    A Mid-360 sees its scene at 2-90 m and the Avia's drone returns lie within tens of metres
    (``reference/mmaud_and_teacher.md`` sections 2.2 and 4 [M]); a typical frame whose median
    return lies beyond ``max_median_range_m`` means the coordinates are not metres.
    """
    if not stats.median_ranges:
        return
    median = float(np.median(stats.median_ranges))
    if median > max_median_range_m:
        raise RecordingError(
            f"{what} {stats.sensor}: the median return lies {median:.0f} m from the sensor (over "
            f"{len(stats.median_ranges)} frames), beyond any Livox range: the points look like millimetres "
            f"(or another unit); set TeacherConfig.unit_scale (e.g. 0.001) or fix the recording"
        )
