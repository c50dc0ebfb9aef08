"""The in-memory data model of one flight: audio, LiDAR scans, camera frames and tracks.

A :class:`Recording` is what every reader produces and every later stage (teacher, DataModule,
benchmark) consumes. Large streams are accessed through small lazy interfaces, so a reader can
serve one 2 s window of a 10-minute recording without loading the rest: :class:`AudioStream`
reads sample ranges, :class:`PointCloudStream` and :class:`ImageStream` read single frames.
In-memory implementations (``Array*``) back the simulator and the tests.

Conventions: metres, seconds, Hz; timestamps are float64 seconds (ROS/Unix time); audio is
float32 in digital full-scale units, channels x samples.
"""

from __future__ import annotations

import io
import json
from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from datamodules.errors import AauteError

DRONE_TYPES = ("avata", "m300", "mavic2", "mavic3", "phantom4")
LIDAR_SENSORS = ("mid360", "avia")

#: Values of the per-point ``origin`` field: what produced each LiDAR return (simulated data only).
ORIGIN_BACKGROUND, ORIGIN_DRONE, ORIGIN_FALSE = 0, 1, 2


class RecordingError(AauteError, ValueError):
    """A recording (file or folder) does not hold what was expected."""


def seconds_to_ns(t: np.ndarray | float) -> np.ndarray:
    """Float64 seconds to int64 nanoseconds, exact to the float's precision.

    Splitting whole seconds from the fraction avoids the 256 ns rounding of ``t * 1e9`` at Unix
    epochs, so :func:`ns_to_seconds` gives back the very same float64.
    """
    t = np.asarray(t, dtype=np.float64)
    whole = np.floor(t)
    frac_ns = np.rint((t - whole) * 1e9).astype(np.int64)
    return whole.astype(np.int64) * 1_000_000_000 + frac_ns


def ns_to_seconds(ns: np.ndarray | int) -> np.ndarray:
    """Int64 nanoseconds to float64 seconds (inverse of :func:`seconds_to_ns`)."""
    ns = np.asarray(ns, dtype=np.int64)
    whole, frac = np.divmod(ns, 1_000_000_000)
    return whole.astype(np.float64) + frac.astype(np.float64) / 1e9


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot store {type(value).__name__} in recording metadata")


def to_json(meta: dict[str, Any]) -> str:
    """Recording metadata as JSON (numpy values become plain numbers and lists)."""
    return json.dumps(meta, sort_keys=True, default=_json_default)


def json_safe(meta: dict[str, Any]) -> dict[str, Any]:
    """Metadata exactly as it reads back from disk (tuples become lists, numpy becomes Python)."""
    return json.loads(to_json(meta))


def check_monotonic(timestamps: np.ndarray, what: str, strict: bool = True) -> None:
    """Raise :class:`RecordingError` naming ``what`` if timestamps go backwards (or repeat)."""
    steps = np.diff(np.asarray(timestamps, dtype=np.float64))
    bad = np.flatnonzero(steps <= 0 if strict else steps < 0)
    if bad.size:
        i = int(bad[0])
        raise RecordingError(
            f"{what}: timestamps must increase; {bad.size} step(s) do not, first at index {i + 1} "
            f"({timestamps[i]:.6f} -> {timestamps[i + 1]:.6f})"
        )


#: a step longer than this many median steps counts as a gap (missing frames)
GAP_FACTOR = 1.5


def count_gaps(timestamps: np.ndarray, factor: float = GAP_FACTOR) -> int:
    """Number of steps longer than ``factor`` times the median step (missing frames)."""
    if len(timestamps) < 3:
        return 0
    steps = np.diff(timestamps)
    return int(np.count_nonzero(steps > factor * np.median(steps)))


#: positions farther than this from the rig (median over a track) are implausible: the Leica MS60's prism lock
#: range is about 1000 m and the Livox Avia sees at most 450 m (reference/mmaud_and_teacher.md); MMAUD flights
#: stay within tens of metres. Override with the environment variable ``AAUTE_PLAUSIBLE_RANGE_M``.
PLAUSIBLE_RANGE_M = 1000.0
#: relative disagreement of an audio sample rate with its message stamps that is an error (1 %)
RATE_TOLERANCE = 0.01


def plausible_range_m() -> float:
    """The largest plausible median distance (m) of a track from the rig (:data:`PLAUSIBLE_RANGE_M`)."""
    import os

    value = os.environ.get("AAUTE_PLAUSIBLE_RANGE_M")
    if value is None:
        return PLAUSIBLE_RANGE_M
    try:
        limit = float(value)
    except ValueError:
        raise RecordingError(f"AAUTE_PLAUSIBLE_RANGE_M={value!r}: expected a distance in metres") from None
    if not limit > 0:
        raise RecordingError(f"AAUTE_PLAUSIBLE_RANGE_M={value!r}: expected a positive distance in metres")
    return limit


def check_track_values(timestamps: np.ndarray, xyz: np.ndarray, valid: np.ndarray | None, what: str) -> None:
    """Refuse a track whose labelled positions are NaN/infinite or implausibly far from the rig.

    ``what`` names the file and topic. Points marked invalid may hold anything (NaN by convention).

    Raises:
        RecordingError: the first non-finite labelled position (index and time), or a median distance
            beyond :func:`plausible_range_m` (with the likely unit error: millimetres or centimetres).
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    keep = np.ones(len(xyz), dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    bad = np.flatnonzero(keep & ~np.isfinite(xyz).all(axis=1))
    if bad.size:
        i = int(bad[0])
        raise RecordingError(
            f"{what}: {bad.size} labelled position(s) are NaN or infinite, first at index {i} "
            f"(t = {float(timestamps[i]):.3f} s: {xyz[i].tolist()}); expected finite x, y, z in metres "
            f"(mark missing labels invalid instead)"
        )
    if not keep.any():
        return
    median = float(np.median(np.linalg.norm(xyz[keep], axis=1)))
    limit = plausible_range_m()
    if median > limit:
        units = next((f"; in {name}? /{factor:g} gives {median / factor:.1f} m"
                      for name, factor in (("millimetres", 1000.0), ("centimetres", 100.0))
                      if median / factor <= limit), "")
        raise RecordingError(
            f"{what}: positions lie {median:.0f} m from the rig (median), expected metres within {limit:g} m"
            f"{units} (set AAUTE_PLAUSIBLE_RANGE_M to accept farther tracks)"
        )


def check_audio_rate(values: np.ndarray, steps_s: np.ndarray, rate: float, channels: int, what: str) -> None:
    """Check a sample rate and channel count against the samples and stamps of audio messages.

    ``values[i]`` is the number of samples (all channels together) message ``i`` holds and
    ``steps_s[i]`` the time from its stamp to the next message's. The median samples per second and
    channel must agree with ``rate`` within :data:`RATE_TOLERANCE`; when they do not, but another
    whole channel count fits the rate exactly, the channel count is named as the cause.

    Raises:
        RecordingError: naming the measured rate (or the channel count the data fits).
    """
    values = np.asarray(values, dtype=np.float64)
    steps_s = np.asarray(steps_s, dtype=np.float64)
    usable = (values > 0) & (steps_s > 0)
    if not usable.any():
        return
    per_second = float(np.median(values[usable] / steps_s[usable]))  # all channels together
    measured = per_second / channels
    if abs(measured / rate - 1.0) <= RATE_TOLERANCE:
        return
    fitting = per_second / rate
    whole = int(round(fitting))
    if whole >= 1 and whole != channels and abs(fitting / whole - 1.0) <= RATE_TOLERANCE:
        raise RecordingError(
            f"{what}: the messages hold {per_second:.0f} samples per second of stamps: {whole} channel(s) at "
            f"{rate:g} Hz, not the {channels} channel(s) stated (or {channels} at {measured:.0f} Hz); "
            f"give the right channel count"
        )
    raise RecordingError(
        f"{what}: the message stamps advance at about {measured:.0f} samples/s but the sample rate is "
        f"{rate:g} Hz (per channel, tolerance {RATE_TOLERANCE:.0%}); give the right sample rate"
    )


def check_finite_audio(block: np.ndarray, t0: float, sample_rate: float, what: str,
                       audio_t0: float | None = None) -> None:
    """Refuse audio samples that are NaN or infinite, naming the time of the first (``block`` starts at ``t0``;
    ``audio_t0``, the time of the audio's first sample, adds the time into the recording).

    Raises:
        RecordingError: with the channel, sample time and count of the bad samples.
    """
    finite = np.isfinite(block)
    if finite.all():
        return
    bad = np.argwhere(~finite)
    channel, sample = bad[np.argmin(bad[:, 1])]
    t = t0 + sample / sample_rate
    into = f", {t - audio_t0:.3f} s into the audio" if audio_t0 is not None else ""
    raise RecordingError(
        f"{what}: {len(bad)} NaN or infinite audio sample(s), first at t = {t:.3f} s{into} "
        f"(channel {int(channel)}); expected finite samples"
    )


# --------------------------------------------------------------------------------------------- audio


class AudioStream(ABC):
    """Multichannel audio with one shared sample clock, read lazily by sample range."""

    sample_rate: float
    t0: float  #: time of sample 0 (s)
    mic_positions: np.ndarray  #: channels x 3 (m), in the rig frame
    num_samples: int
    #: on-disk sample format the values lie on exactly ('S16LE', 'F32LE', ...), if known
    sample_format: str | None = None

    @property
    def num_channels(self) -> int:
        return int(self.mic_positions.shape[0])

    @property
    def duration(self) -> float:
        return self.num_samples / self.sample_rate

    @property
    def t_end(self) -> float:
        """Time just after the last sample."""
        return self.t0 + self.duration

    @abstractmethod
    def read(self, start: int, stop: int) -> np.ndarray:
        """Samples ``start:stop`` as float32 (channels x (stop - start)); the range must be inside."""

    def sample_index(self, t: float) -> int:
        """Index of the sample at (or just before) time ``t``.

        A time within a few float64 steps of a sample boundary is that boundary: absolute stamps near
        1.7e9 s hold only 0.24 us, so ``t0 + k / fs`` read back from nanoseconds can land a hair before
        sample ``k`` and would otherwise end a window one sample early.
        """
        position = (t - self.t0) * self.sample_rate
        tolerance = max(1e-9, 4.0 * (np.spacing(abs(t)) + np.spacing(abs(self.t0))) * self.sample_rate)
        return int(np.floor(position + tolerance))

    def window(self, t_end: float, seconds: float) -> np.ndarray:
        """The ``seconds`` of audio ending at ``t_end`` (causal), channels x round(seconds * fs)."""
        n = int(round(seconds * self.sample_rate))
        stop = self.sample_index(t_end)
        start = stop - n
        if start < 0 or stop > self.num_samples:
            raise RecordingError(
                f"audio window [{t_end - seconds:.3f}, {t_end:.3f}] s lies outside the audio "
                f"[{self.t0:.3f}, {self.t_end:.3f}] s"
            )
        return self.read(start, stop)

    def _check_range(self, start: int, stop: int) -> None:
        if not 0 <= start <= stop <= self.num_samples:
            raise RecordingError(f"audio samples {start}:{stop} outside 0:{self.num_samples}")


class ArrayAudio(AudioStream):
    """Audio held in an array (in memory or memory-mapped)."""

    def __init__(
        self,
        samples: np.ndarray,
        sample_rate: float,
        t0: float,
        mic_positions: np.ndarray,
        sample_format: str | None = None,
    ):
        samples = np.asarray(samples)
        mic_positions = np.asarray(mic_positions, dtype=np.float64)
        if samples.ndim != 2 or mic_positions.shape != (samples.shape[0], 3):
            raise RecordingError(
                f"audio must be channels x samples with one mic position per channel; got samples "
                f"{samples.shape} and mic positions {mic_positions.shape}"
            )
        if samples.dtype != np.float32:
            samples = samples.astype(np.float32)
        self.samples = samples
        self.sample_rate = float(sample_rate)
        self.t0 = float(t0)
        self.mic_positions = mic_positions
        self.num_samples = int(samples.shape[1])
        self.sample_format = sample_format

    def read(self, start: int, stop: int) -> np.ndarray:
        self._check_range(start, stop)
        return np.array(self.samples[:, start:stop], dtype=np.float32)


# ------------------------------------------------------------------------------------------- frames


@dataclass
class PointCloud:
    """One LiDAR scan: points (N x 3, float32, sensor/rig frame), intensity and, if known, origin."""

    points: np.ndarray
    intensity: np.ndarray | None = None
    origin: np.ndarray | None = None  #: uint8 per point, ORIGIN_* (simulator only)

    def __len__(self) -> int:
        return int(self.points.shape[0])


class FrameStream(ABC):
    """Timestamped frames (scans or images) read one at a time; timestamps are cheap."""

    timestamps: np.ndarray  #: float64 seconds, increasing

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    @abstractmethod
    def __getitem__(self, index: int) -> Any: ...

    def __iter__(self) -> Iterator[Any]:
        for i in range(len(self)):
            yield self[i]

    def indices_between(self, t_start: float, t_end: float) -> np.ndarray:
        """Indices of frames with ``t_start <= t < t_end``."""
        lo, hi = np.searchsorted(self.timestamps, [t_start, t_end], side="left")
        return np.arange(lo, hi)

    def nearest(self, t: float) -> int:
        """Index of the frame closest in time to ``t``."""
        i = int(np.searchsorted(self.timestamps, t))
        if i == 0:
            return 0
        if i >= len(self):
            return len(self) - 1
        return i if self.timestamps[i] - t < t - self.timestamps[i - 1] else i - 1


class PointCloudStream(FrameStream):
    """A LiDAR sensor's scans."""

    @abstractmethod
    def __getitem__(self, index: int) -> PointCloud: ...


class ArrayPointClouds(PointCloudStream):
    """Scans held in memory."""

    def __init__(self, timestamps: Sequence[float] | np.ndarray, clouds: Sequence[PointCloud]):
        self.timestamps = np.asarray(timestamps, dtype=np.float64)
        self.clouds = list(clouds)
        if len(self.clouds) != len(self.timestamps):
            raise RecordingError(f"{len(self.timestamps)} scan timestamps but {len(self.clouds)} scans")

    def __getitem__(self, index: int) -> PointCloud:
        return self.clouds[index]


@dataclass
class EncodedImage:
    """A compressed camera frame as the camera driver produced it (``format`` is 'png' or 'jpeg')."""

    data: bytes
    format: str

    def decode(self) -> np.ndarray:
        """The image as H x W x 3 uint8 RGB."""
        from PIL import Image

        with Image.open(io.BytesIO(self.data)) as image:
            return np.asarray(image.convert("RGB"))


class ImageStream(FrameStream):
    """A camera's frames, kept encoded until asked for."""

    @abstractmethod
    def __getitem__(self, index: int) -> EncodedImage: ...

    def image(self, index: int) -> np.ndarray:
        return self[index].decode()


class ArrayImages(ImageStream):
    """Encoded frames held in memory."""

    def __init__(self, timestamps: Sequence[float] | np.ndarray, images: Sequence[EncodedImage]):
        self.timestamps = np.asarray(timestamps, dtype=np.float64)
        self.images = list(images)
        if len(self.images) != len(self.timestamps):
            raise RecordingError(f"{len(self.timestamps)} image timestamps but {len(self.images)} images")

    def __getitem__(self, index: int) -> EncodedImage:
        return self.images[index]


# ------------------------------------------------------------------------------------------- tracks


@dataclass
class Track:
    """A timestamped 3D track (ground truth, pseudo-labels or predictions).

    ``quality`` holds optional per-point arrays of the same length (e.g. supporting points,
    distance to the nearest supporting frame); ``valid`` marks points that carry a label.
    """

    timestamps: np.ndarray
    xyz: np.ndarray
    valid: np.ndarray | None = None
    quality: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64)
        self.xyz = np.asarray(self.xyz, dtype=np.float64).reshape(-1, 3)
        if self.xyz.shape[0] != self.timestamps.shape[0]:
            raise RecordingError(f"track has {self.timestamps.shape[0]} timestamps but {self.xyz.shape[0]} points")
        self.valid = (
            np.ones(len(self.timestamps), dtype=bool) if self.valid is None else np.asarray(self.valid, dtype=bool)
        )
        for name, values in self.quality.items():
            if len(values) != len(self.timestamps):
                raise RecordingError(f"track quality '{name}' has {len(values)} values for {len(self)} points")

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    def interpolate(self, t: np.ndarray) -> np.ndarray:
        """Linear interpolation of xyz at times ``t`` (valid points only; clamped at the ends)."""
        keep = self.valid
        return np.stack([np.interp(t, self.timestamps[keep], self.xyz[keep, k]) for k in range(3)], axis=1)


# -------------------------------------------------------------------------------------- recording


@dataclass
class Recording:
    """One flight of one drone as seen by the rig."""

    sequence_id: str
    drone: str | None
    audio: AudioStream | None = None
    lidar: dict[str, PointCloudStream] = field(default_factory=dict)
    frames: ImageStream | None = None
    ground_truth: Track | None = None
    pseudo_labels: Track | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.drone is not None and self.drone not in DRONE_TYPES:
            raise RecordingError(f"unknown drone type {self.drone!r}; expected one of {DRONE_TYPES}")
        unknown = set(self.lidar) - set(LIDAR_SENSORS)
        if unknown:
            raise RecordingError(f"unknown LiDAR sensor(s) {sorted(unknown)}; expected {LIDAR_SENSORS}")

    def time_span(self) -> tuple[float, float]:
        """Earliest and latest time covered by any stream."""
        starts, ends = [], []
        if self.audio is not None:
            starts.append(self.audio.t0)
            ends.append(self.audio.t_end)
        streams: list[Any] = [*self.lidar.values(), self.frames, self.ground_truth, self.pseudo_labels]
        for stream in streams:
            if stream is not None and len(stream):
                starts.append(float(stream.timestamps[0]))
                ends.append(float(stream.timestamps[-1]))
        if not starts:
            raise RecordingError(f"recording {self.sequence_id!r} holds no data")
        return min(starts), max(ends)
