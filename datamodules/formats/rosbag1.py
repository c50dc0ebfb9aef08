"""Reader of raw ROS 1 bags (MMAUD V1 is distributed as bz2-compressed ROS 1 bags, ground truth apart).

Needs the optional ``rosbags`` package (``pip install .[rosbag]``), imported only when a bag is opened.

Topics and message types are discovered from the bag itself: a ROS 1 bag stores the full message
definition of every connection, and a typestore is built from those (so Livox ``CustomMsg`` needs
no installed package). Topics are mapped to the recording by message type, with MMAUD-like name
hints where a type is ambiguous:

==============  ==========================================================  =============================
mapping key     message types                                               default choice
==============  ==========================================================  =============================
audio           audio_common_msgs AudioData / AudioDataStamped             the only one, else /audio/audio
audio_info      audio_common_msgs AudioInfo                                 the only one, else beside audio
mid360, avia    livox_ros_driver(2) CustomMsg, sensor_msgs PointCloud2     'avia' / 'mid360' / '360' in the
                                                                            name, else livox_ros_driver2 =
                                                                            Mid-360, livox_ros_driver = Avia
image           sensor_msgs CompressedImage                                 the only one, else 'left'
ground_truth    geometry_msgs PointStamped / PoseStamped                    the only one, else 'leica'/'gt'
==============  ==========================================================  =============================

A ``mapping`` (dict, or a YAML file with the same keys; ``aaute_layout.yaml`` beside the bags is
read too) overrides any of these (``None`` drops a stream) and may carry the audio parameters
``sample_rate``, ``channels``, ``sample_format``, ``audio_stamp`` and ``drone``/``sequence_id``.
A mapping that names a topic the bags lack, or a stream whose type does not fit, raises an error
that lists the bags' topics.

Audio: ``AudioData`` carries raw bytes; channels, rate and sample format come from an AudioInfo
topic when there is one, else from the parameters (defaults 4 channels, S16LE, 48000 Hz). The
stream is rebuilt on one sample clock: message stamps (header stamps of AudioDataStamped, else the
bag's receive times) mark the **end** of each message's samples by default (``audio_stamp='end'``,
as a capture driver stamps a buffer when it is full; 'start' is the other choice). Dropped
messages (a lasting jump of the stamps against the sample clock) are filled with zeros and
counted in a warning and in ``meta["audio_gaps"]``; a sample rate that disagrees with the stamps
by more than 1 % raises an error. A bag without audio raises an error (MMAUD V1's raw bags are the
only source of its audio, so a missing audio topic usually means a wrong bag or mapping); pass
``{"audio": None}`` to read LiDAR/ground truth alone.

Reading: opening makes one pass over the messages of the mapped topics (bags are sequential,
compressed in chunks, so there is no cheaper way to learn the audio messages' sample counts and
the sensors' header stamps). That pass keeps only a few numbers per message and the (small)
ground-truth track. Audio ranges, LiDAR scans and images are then read lazily from the bag when
asked for, so memory does not grow with the recording; each read decompresses the chunks holding
those messages, which makes random access slow on bz2 bags: convert to MCAP (``aaute convert``)
for repeated use. Points are kept in each LiDAR's own sensor frame (``meta["frame"]``).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from datamodules.formats.ros_messages import SAMPLE_FORMATS, full_scale, pointcloud_to_arrays, stamp_ns
from datamodules.recording import (
    DRONE_TYPES,
    RATE_TOLERANCE,
    AudioStream,
    EncodedImage,
    ImageStream,
    PointCloud,
    PointCloudStream,
    Recording,
    RecordingError,
    Track,
    check_audio_rate,
    check_monotonic,
    check_track_values,
    count_gaps,
    json_safe,
    ns_to_seconds,
)

log = logging.getLogger(__name__)

AUDIO_TYPES = ("audio_common_msgs/msg/AudioData", "audio_common_msgs/msg/AudioDataStamped")
AUDIO_INFO_TYPE = "audio_common_msgs/msg/AudioInfo"
LIVOX_TYPES = ("livox_ros_driver/msg/CustomMsg", "livox_ros_driver2/msg/CustomMsg")
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
LIDAR_TYPES = (*LIVOX_TYPES, CLOUD_TYPE)
IMAGE_TYPES = ("sensor_msgs/msg/CompressedImage",)
GROUND_TRUTH_TYPES = ("geometry_msgs/msg/PointStamped", "geometry_msgs/msg/PoseStamped")
STREAM_TYPES: dict[str, tuple[str, ...]] = {
    "audio": AUDIO_TYPES, "audio_info": (AUDIO_INFO_TYPE,), "mid360": LIDAR_TYPES, "avia": LIDAR_TYPES,
    "image": IMAGE_TYPES, "ground_truth": GROUND_TRUTH_TYPES,
}
PARAMETER_KEYS = ("sample_rate", "channels", "sample_format", "audio_stamp", "drone", "sequence_id")
LAYOUT_FILE = "aaute_layout.yaml"
DEFAULT_AUDIO = {"sample_rate": 48000.0, "channels": 4, "sample_format": "S16LE", "audio_stamp": "end"}
DEFAULT_AUDIO_TOPIC = "/audio/audio"
#: name hints of each LiDAR (lower-case substrings of the topic)
LIDAR_HINTS = {"avia": ("avia",), "mid360": ("mid360", "mid_360", "360")}
#: Livox driver package -> the sensor it drives (the Mid-360 needs SDK 2 and livox_ros_driver2)
LIVOX_DRIVER_SENSOR = {"livox_ros_driver2/msg/CustomMsg": "mid360", "livox_ros_driver/msg/CustomMsg": "avia"}
GROUND_TRUTH_HINTS = ("leica", "ground_truth", "groundtruth", "gt")
RATE_MIN_MESSAGES = 10  #: audio messages needed to check the sample rate against the stamps
#: a lasting jump of the stamps against the sample clock longer than this many message durations is a gap
GAP_MESSAGES = 0.6
GAP_WINDOW = 10  #: messages over which receive-time jitter is discounted (future running minimum)

FRAME = "lidar_sensor"
FRAME_DESCRIPTION = (
    "each LiDAR's own sensor frame as its driver published it (frame ids in meta['frame_ids']); "
    "ground truth in the frame of its topic (MMAUD V1: the Leica frame). No transform applied."
)

#: Livox CustomMsg as published by livox_ros_driver and livox_ros_driver2 (the package name varies)
_LIVOX_MSGDEF = """std_msgs/Header header
uint64 timebase
uint32 point_num
uint8 lidar_id
uint8[3] rsvd
CustomPoint[] points
================================================================================
MSG: std_msgs/Header
uint32 seq
time stamp
string frame_id
================================================================================
MSG: {package}/CustomPoint
uint32 offset_time
float32 x
float32 y
float32 z
uint8 reflectivity
uint8 tag
uint8 line
"""
#: serialized CustomPoint (ROS 1 packs fields without padding)
_LIVOX_POINT = np.dtype([("offset_time", "<u4"), ("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                         ("reflectivity", "u1"), ("tag", "u1"), ("line", "u1")])


class MissingDependencyError(RecordingError, ImportError):
    """An optional package needed for this layout is not installed."""


def _rosbags() -> Any:
    try:
        import rosbags.rosbag1 as rosbag1
        import rosbags.typesys as typesys
    except ImportError as error:
        raise MissingDependencyError(
            "reading ROS 1 bags needs the optional 'rosbags' package: pip install .[rosbag] "
            "(or pip install 'rosbags>=0.10,<0.12')"
        ) from error
    return rosbag1, typesys


def _msgdef_text(connection: Any) -> str:
    msgdef = connection.msgdef
    return str(getattr(msgdef, "data", msgdef))


# ============================================================================================== bags


class Bag:
    """One ROS 1 bag: its connections, a typestore built from their definitions, raw message access.

    The reader is reopened after a fork, so DataLoader workers never share a file offset.
    """

    def __init__(self, path: Path):
        self.path = Path(path)
        self._pid = -1
        self._reader: Any = None
        _, typesys = _rosbags()
        reader = self.reader()
        self.connections = list(reader.connections)
        self.topics: dict[str, list[Any]] = {}
        for connection in self.connections:
            self.topics.setdefault(connection.topic, []).append(connection)
        self.types = {topic: conns[0].msgtype for topic, conns in self.topics.items()}
        for topic, conns in self.topics.items():
            if len({c.msgtype for c in conns}) > 1:
                raise RecordingError(f"{self.path}: topic {topic} carries several message types "
                                     f"({sorted({c.msgtype for c in conns})})")
        self.counts = {topic: sum(int(c.msgcount) for c in conns) for topic, conns in self.topics.items()}
        self.store = typesys.get_typestore(typesys.Stores.EMPTY)
        for connection in self.connections:
            try:
                self.store.register(typesys.get_types_from_msg(_msgdef_text(connection), connection.msgtype))
            except Exception as error:  # TypesysError and parser errors share no useful base
                raise RecordingError(f"{self.path}: cannot parse the message definition of {connection.topic} "
                                     f"({connection.msgtype}): {error}") from error
        self._fast_livox = {t: self._is_standard_livox(t) for t in set(self.types.values()) if t in LIVOX_TYPES}

    def reader(self) -> Any:
        if self._reader is None or self._pid != os.getpid():
            rosbag1, _ = _rosbags()
            reader = rosbag1.Reader(self.path)
            try:
                reader.open()
            except rosbag1.ReaderError as error:
                hint = " (an unindexed bag needs 'rosbag reindex')" if "index" in str(error).lower() else ""
                raise RecordingError(f"{self.path}: not a readable ROS 1 bag: {error}{hint}") from error
            self._reader, self._pid = reader, os.getpid()
        return self._reader

    def _is_standard_livox(self, msgtype: str) -> bool:
        """Whether the bag's CustomMsg is the standard Livox layout (then its points parse as one array)."""
        _, typesys = _rosbags()
        package = msgtype.split("/")[0]
        reference = typesys.get_typestore(typesys.Stores.EMPTY)
        reference.register(typesys.get_types_from_msg(_LIVOX_MSGDEF.format(package=package), msgtype))
        point = f"{package}/msg/CustomPoint"
        return all(self.store.fielddefs.get(name) == reference.fielddefs[name]
                   for name in (msgtype, point, "std_msgs/msg/Header"))

    def deserialize(self, raw: bytes | memoryview, msgtype: str, what: str) -> Any:
        try:
            return self.store.deserialize_ros1(raw, msgtype)
        except Exception as error:  # corrupt data raises assorted errors in the deserializer
            raise RecordingError(f"{self.path} {what}: cannot decode {msgtype}: {error}") from error

    def has_header(self, msgtype: str) -> bool:
        fields = self.store.fielddefs[msgtype][1]
        return bool(fields) and fields[0][0] == "header" and "std_msgs/msg/Header" in repr(fields[0][1])

    def messages(self, topics: Sequence[str], start: int | None = None, stop: int | None = None
                 ) -> Iterator[tuple[str, int, memoryview | bytes]]:
        """``(topic, log time ns, raw)`` of the topics' messages in log-time order (ties in connection order)."""
        reader = self.reader()
        wanted = set(topics)
        connections = [c for c in reader.connections if c.topic in wanted]
        rosbag1, _ = _rosbags()
        try:
            for connection, log_ns, raw in reader.messages(connections=connections, start=start, stop=stop):
                yield connection.topic, int(log_ns), raw
        except rosbag1.ReaderError as error:
            raise RecordingError(f"{self.path}: corrupt bag data: {error}") from error

    def message_at(self, topic: str, log_ns: np.ndarray, position: int) -> memoryview | bytes:
        """Raw message number ``position`` of ``topic`` (positions as :meth:`messages` yields them)."""
        t = int(log_ns[position])
        skip = position - int(np.searchsorted(log_ns, t, side="left"))
        for i, (_, _, raw) in enumerate(self.messages([topic], start=t, stop=t + 1)):
            if i == skip:
                return raw
        raise RecordingError(f"{self.path}: message {position} of {topic} not found on re-reading")


def _raw_header(raw: memoryview | bytes, what: str) -> tuple[int, str, int]:
    """Stamp (ns), frame id and byte length of the ROS 1 ``std_msgs/Header`` a message starts with."""
    buffer = bytes(raw[:16])
    if len(buffer) < 16:
        raise RecordingError(f"{what}: message too short for a header ({len(raw)} bytes)")
    sec, nsec, length = np.frombuffer(buffer[4:16], dtype="<u4")
    end = 16 + int(length)
    if end > len(raw):
        raise RecordingError(f"{what}: corrupt header (frame id of {length} bytes in a {len(raw)}-byte message)")
    frame_id = bytes(raw[16:end]).decode("utf-8", "replace")
    return int(sec) * 1_000_000_000 + int(nsec), frame_id, end


def livox_points(raw: memoryview | bytes, what: str) -> np.ndarray:
    """The points of a serialized standard Livox CustomMsg as one structured array."""
    _, _, offset = _raw_header(raw, what)
    offset += 8 + 4 + 1 + 3  # timebase, point_num, lidar_id, rsvd[3]
    count = int(np.frombuffer(bytes(raw[offset:offset + 4]), dtype="<u4")[0])
    offset += 4
    if offset + count * _LIVOX_POINT.itemsize != len(raw):
        raise RecordingError(f"{what}: CustomMsg of {len(raw)} bytes cannot hold {count} points")
    return np.frombuffer(raw, dtype=_LIVOX_POINT, count=count, offset=offset)


# ============================================================================================ mapping


def _load_mapping(mapping: dict[str, Any] | str | Path | None, what: str) -> dict[str, Any]:
    if mapping is None:
        return {}
    if isinstance(mapping, str | Path):
        import yaml

        path = Path(mapping)
        try:
            mapping = yaml.safe_load(path.read_text()) or {}
        except (OSError, yaml.YAMLError) as error:
            raise RecordingError(f"{path}: cannot read the topic mapping ({error})") from error
        what = str(path)
    if not isinstance(mapping, dict):
        raise RecordingError(f"{what}: the topic mapping must be a mapping, got {type(mapping).__name__}")
    unknown = set(mapping) - set(STREAM_TYPES) - set(PARAMETER_KEYS)
    if unknown:
        raise RecordingError(f"{what}: unknown mapping key(s) {sorted(unknown)}; expected topic keys "
                             f"{list(STREAM_TYPES)} or parameters {list(PARAMETER_KEYS)}")
    return dict(mapping)


def _topic_list(types: dict[str, str], counts: dict[str, int]) -> str:
    return "; ".join(f"{topic} ({msgtype}, {counts.get(topic, 0)} msgs)" for topic, msgtype in sorted(types.items()))


def _choose(candidates: list[str], hints: Sequence[str], exact: str | None = None) -> list[str]:
    """Candidates narrowed to the exact name, else to those containing a hint (unchanged if none do)."""
    if exact is not None and exact in candidates:
        return [exact]
    hinted = [t for t in candidates if any(h in t.lower() for h in hints)]
    return hinted or candidates


def map_topics(types: dict[str, str], counts: dict[str, int], given: dict[str, Any], where: str) -> dict[str, str]:
    """Which topic feeds each stream: the given mapping, completed by message type and name hints.

    Raises:
        RecordingError: a mapped topic is absent or of the wrong type, or a choice is ambiguous
            (the message lists the bags' topics).
    """
    listing = _topic_list(types, counts)
    chosen: dict[str, str] = {}
    for key in STREAM_TYPES:
        if key not in given:
            continue
        topic = given[key]
        if topic is None:
            continue
        if topic not in types:
            raise RecordingError(f"{where}: mapping {key}: {topic} names no topic of the bag(s); topics: {listing}")
        if types[topic] not in STREAM_TYPES[key]:
            raise RecordingError(f"{where}: mapping {key}: {topic} is {types[topic]}, expected one of "
                                 f"{list(STREAM_TYPES[key])}; topics: {listing}")
        chosen[key] = topic

    def of_types(accepted: Sequence[str]) -> list[str]:
        return sorted(t for t, m in types.items() if m in accepted and t not in chosen.values())

    def ambiguous(key: str, options: list[str]) -> RecordingError:
        return RecordingError(f"{where}: several topics could be {key} ({', '.join(options)}); name one in the "
                              f"mapping ({key}: <topic>); topics: {listing}")

    if "audio" not in given:
        options = _choose(of_types(AUDIO_TYPES), ("audio",), DEFAULT_AUDIO_TOPIC)
        if len(options) > 1:
            raise ambiguous("audio", options)
        if options:
            chosen["audio"] = options[0]
    if "audio_info" not in given and "audio" in chosen:
        options = of_types((AUDIO_INFO_TYPE,))
        namespace = chosen["audio"].rsplit("/", 1)[0] + "/"
        options = [t for t in options if t.startswith(namespace)] or options
        if len(options) > 1:
            raise ambiguous("audio_info", options)
        if options:
            chosen["audio_info"] = options[0]
    lidar_free = [s for s in ("avia", "mid360") if s not in given]
    assigned: dict[str, list[str]] = {s: [] for s in lidar_free}
    unassigned = []
    for topic in of_types(LIDAR_TYPES):
        name = topic.lower()
        sensor = next((s for s in ("avia", "mid360") if any(h in name for h in LIDAR_HINTS[s])), None)
        sensor = sensor or LIVOX_DRIVER_SENSOR.get(types[topic])
        if sensor in assigned:
            assigned[sensor].append(topic)
        elif sensor is None:
            unassigned.append(topic)
    for sensor, options in assigned.items():
        if len(options) > 1:
            raise ambiguous(sensor, options)
        if options:
            chosen[sensor] = options[0]
    if unassigned:
        log.warning("%s: LiDAR topic(s) %s not assigned to a sensor (no 'avia'/'mid360' in the name); map them "
                    "with mid360: <topic> / avia: <topic> to use them", where, unassigned)
    if "image" not in given:
        options = of_types(IMAGE_TYPES)
        left = _choose(options, ("left",))
        if len(options) > 1:
            log.warning("%s: several camera topics %s; using %s (map image: <topic> to choose)",
                        where, options, left[0])
        if options:
            chosen["image"] = left[0]
    if "ground_truth" not in given:
        options = _choose(of_types(GROUND_TRUTH_TYPES), GROUND_TRUTH_HINTS)
        if len(options) > 1:
            raise ambiguous("ground_truth", options)
        if options:
            chosen["ground_truth"] = options[0]
    return chosen


# ============================================================================================== audio


@dataclass
class AudioLayout:
    """Where each audio message's samples go on the rebuilt sample clock."""

    first: np.ndarray  #: sample index of each message's first sample
    t0: float
    gaps: int
    gap_samples: int
    rate_by_stamps: float | None = None
    notes: list[str] = field(default_factory=list)


def layout_audio(stamps_ns: np.ndarray, counts: np.ndarray, rate: float, stamp_at: str, what: str) -> AudioLayout:
    """Place audio messages on one sample clock, filling dropped messages with zeros.

    ``stamps_ns`` mark each message's first sample (``stamp_at='start'``) or the end of its last
    one ('end'). Receive-time jitter is discounted with a running minimum over the next
    :data:`GAP_WINDOW` messages: a delayed message is followed by punctual ones, whereas after a
    dropped message every stamp stays late. ``t0`` is the median offset of the stamps from the
    sample clock, in whole nanoseconds.

    Raises:
        RecordingError: the stamps disagree with ``rate`` by more than :data:`RATE_TOLERANCE`
            (checked from :data:`RATE_MIN_MESSAGES` messages on).
    """
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    counts = np.asarray(counts, dtype=np.int64)
    end = stamp_at == "end"
    measured = None
    steps_s = np.diff(stamps_ns) / 1e9
    spanned = counts[1:] if end else counts[:-1]  # samples between consecutive stamps
    usable = spanned > 0
    if usable.sum() >= RATE_MIN_MESSAGES:
        # the median step per sample ignores a few dropped messages and symmetric jitter
        measured = float(1.0 / np.median(steps_s[usable] / spanned[usable]))
        if abs(measured / rate - 1.0) > RATE_TOLERANCE:
            raise RecordingError(
                f"{what}: the message stamps advance at about {measured:.0f} samples/s but the sample rate is "
                f"{rate:g} Hz; give the right sample_rate (MMAUD code uses 46080 or 48000)"
            )
    starts = (stamps_ns - stamps_ns[0]) / 1e9 - (counts / rate if end else 0.0)  # relative: full precision
    cumulative = np.concatenate([[0], np.cumsum(counts)[:-1]])
    residual = starts - cumulative / rate
    padded = np.concatenate([residual, np.full(GAP_WINDOW - 1, np.inf)])
    floor = np.lib.stride_tricks.sliding_window_view(padded, GAP_WINDOW).min(axis=1)
    tolerance = GAP_MESSAGES * float(np.median(counts)) / rate
    steps = np.diff(floor)
    extra = np.zeros(counts.size, dtype=np.int64)
    jumps = steps > tolerance
    extra[1:][jumps] = np.rint(steps[jumps] * rate).astype(np.int64)
    first = cumulative + np.cumsum(extra)
    marked = first + counts if end else first
    offsets = np.sort(stamps_ns - np.rint(marked * (1e9 / rate)).astype(np.int64))
    t0 = float(ns_to_seconds(offsets[(offsets.size - 1) // 2]))
    layout = AudioLayout(first, t0, int(jumps.sum()), int(extra.sum()), measured)
    return layout


class BagAudio(AudioStream):
    """Audio of a bag topic on one sample clock; messages are read from the bag for a range only."""

    def __init__(self, bag: Bag, topic: str, log_ns: np.ndarray, layout: AudioLayout, counts: np.ndarray,
                 rate: float, channels: int, sample_format: str):
        self._bag, self._topic, self._log_ns = bag, topic, log_ns
        self._first, self._counts = layout.first, counts
        self._stamped = bag.types[topic] == AUDIO_TYPES[1]
        self.sample_rate = float(rate)
        self.t0 = layout.t0
        self.num_samples = int(layout.first[-1] + counts[-1])
        self.mic_positions = np.zeros((channels, 3))
        self.sample_format = sample_format
        self._dtype = np.dtype(SAMPLE_FORMATS[sample_format])
        self._scale = full_scale(self._dtype)

    def read(self, start: int, stop: int) -> np.ndarray:
        self._check_range(start, stop)
        out = np.zeros((self.num_channels, stop - start), dtype=np.float32)
        if stop == start:
            return out
        lo = max(int(np.searchsorted(self._first, start, side="right")) - 1, 0)
        hi = int(np.searchsorted(self._first, stop, side="left"))
        t_lo, t_hi = int(self._log_ns[lo]), int(self._log_ns[hi - 1])
        position = int(np.searchsorted(self._log_ns, t_lo, side="left"))
        for _, _, raw in self._bag.messages([self._topic], start=t_lo, stop=t_hi + 1):
            if position >= hi:
                break
            if position >= lo:
                block = self._decode(raw, position)
                first = int(self._first[position])
                a, b = max(start, first), min(stop, first + block.shape[1])
                if b > a:
                    out[:, a - start:b - start] = block[:, a - first:b - first]
            position += 1
        return out

    def _decode(self, raw: memoryview | bytes, position: int) -> np.ndarray:
        msg = self._bag.deserialize(raw, self._bag.types[self._topic], f"{self._topic}[{position}]")
        data = np.asarray(msg.audio.data if self._stamped else msg.data, dtype=np.uint8)
        samples = data.view(self._dtype).reshape(-1, self.num_channels).T
        block = samples.astype(np.float32) / np.float32(self._scale) if self._scale != 1.0 else \
            samples.astype(np.float32)
        if not np.isfinite(block).all():
            raise RecordingError(f"{self._bag.path} {self._topic}[{position}]: NaN or infinite audio samples")
        return block


# =========================================================================================== streams


class BagPointClouds(PointCloudStream):
    """A LiDAR topic; each scan is read from the bag when indexed. Exact (0, 0, 0) points (no return) are dropped."""

    def __init__(self, bag: Bag, topic: str, log_ns: np.ndarray, stamps_ns: np.ndarray):
        self._bag, self._topic, self._log_ns = bag, topic, log_ns
        self._msgtype = bag.types[topic]
        self.timestamps = ns_to_seconds(stamps_ns)

    def __getitem__(self, index: int) -> PointCloud:
        what = f"{self._bag.path} {self._topic}[{index}]"
        raw = self._bag.message_at(self._topic, self._log_ns, index)
        if self._msgtype in LIVOX_TYPES:
            if self._bag._fast_livox.get(self._msgtype):
                points = livox_points(raw, what)
                xyz = np.column_stack([points["x"], points["y"], points["z"]])
                intensity = points["reflectivity"]
            else:
                msg = self._bag.deserialize(raw, self._msgtype, what)
                xyz = np.array([[p.x, p.y, p.z] for p in msg.points], dtype=np.float32).reshape(-1, 3)
                intensity = np.array([getattr(p, "reflectivity", 0) for p in msg.points], dtype=np.float32)
        else:
            msg = self._bag.deserialize(raw, self._msgtype, what)
            try:
                arrays = pointcloud_to_arrays(msg, what)
            except ValueError as error:
                raise RecordingError(str(error)) from error
            if not {"x", "y", "z"} <= set(arrays):
                raise RecordingError(f"{what}: PointCloud2 without x, y, z fields (has {sorted(arrays)})")
            xyz = np.column_stack([arrays["x"], arrays["y"], arrays["z"]])
            intensity = arrays.get("intensity", arrays.get("reflectivity"))
        keep = np.any(xyz != 0, axis=1)
        return PointCloud(np.ascontiguousarray(xyz[keep], dtype=np.float32),
                          None if intensity is None else np.asarray(intensity)[keep].astype(np.float32))


def _image_format(value: str, what: str) -> str:
    text = value.lower()
    if "png" in text:
        return "png"
    if "jpeg" in text or "jpg" in text:
        return "jpeg"
    raise RecordingError(f"{what}: CompressedImage format {value!r} is neither PNG nor JPEG")


class BagImages(ImageStream):
    """A CompressedImage topic; frames are read from the bag when indexed and kept encoded."""

    def __init__(self, bag: Bag, topic: str, log_ns: np.ndarray, stamps_ns: np.ndarray):
        self._bag, self._topic, self._log_ns = bag, topic, log_ns
        self.timestamps = ns_to_seconds(stamps_ns)

    def __getitem__(self, index: int) -> EncodedImage:
        what = f"{self._bag.path} {self._topic}[{index}]"
        msg = self._bag.deserialize(self._bag.message_at(self._topic, self._log_ns, index),
                                    self._bag.types[self._topic], what)
        return EncodedImage(bytes(np.asarray(msg.data, dtype=np.uint8)), _image_format(str(msg.format), what))


# =========================================================================================== reading


def _drone_from_names(names: Sequence[str]) -> str | None:
    found = {d for name in names for d in DRONE_TYPES if d in name.lower()}
    if len(found) == 1:
        return found.pop()
    if len(found) > 1:
        log.warning("names %s mention several drone types %s; drone left unset", list(names), sorted(found))
    return None


def _bag_paths(path: Path) -> tuple[list[Path], Path]:
    """The bags of a recording path (one .bag file, or every .bag of a folder) and the folder."""
    if path.is_dir():
        bags = sorted(p for p in path.glob("*.bag") if not p.name.startswith("."))
        if not bags:
            raise RecordingError(f"{path}: no .bag files in this folder")
        return bags, path
    if path.suffix != ".bag" or not path.is_file():
        raise RecordingError(f"{path}: expected a ROS 1 .bag file or a folder of them")
    return [path], path.parent


def read_rosbag1(
    paths: str | Path | Sequence[str | Path],
    mapping: dict[str, Any] | str | Path | None = None,
    *,
    sample_rate: float | None = None,
    channels: int | None = None,
    sample_format: str | None = None,
    audio_stamp: str | None = None,
    sequence_id: str | None = None,
    drone: str | None = None,
) -> Recording:
    """Open the bag(s) of one recording (e.g. a sensor bag and its ground-truth bag).

    Args:
        paths: one ``.bag``, a folder of bags (all of them form the recording), or a list of bags.
        mapping: topic mapping and parameters (dict or YAML file); see the module docstring.
            ``aaute_layout.yaml`` in the bags' folder is read first; this mapping overrides it.
        sample_rate, channels, sample_format: audio parameters when the bag has no AudioInfo topic
            (defaults 48000 Hz, 4 channels, S16LE).
        audio_stamp: 'end' (default) or 'start': which sample a message stamp marks.
        sequence_id: defaults to the folder name (folder given) or the first bag's name.
        drone: defaults to a drone type named in the folder or bag names.

    Raises:
        MissingDependencyError: ``rosbags`` is not installed.
        RecordingError: unreadable bag, mapping that does not fit (lists the topics), no audio
            topic, wrong sample rate or format, non-monotonic stamps.
    """
    if isinstance(paths, str | Path):
        bag_paths, folder = _bag_paths(Path(paths))
        folder_given = Path(paths).is_dir()
    else:
        bag_paths = [Path(p) for p in paths]
        folder, folder_given = bag_paths[0].parent, False
        for p in bag_paths:
            if not p.is_file():
                raise RecordingError(f"{p}: no such bag file")
    where = ", ".join(str(p) for p in bag_paths)
    options = _load_mapping(folder / LAYOUT_FILE if (folder / LAYOUT_FILE).is_file() else None, where)
    options.update(_load_mapping(mapping, where))
    for key, value in (("sample_rate", sample_rate), ("channels", channels), ("sample_format", sample_format),
                       ("audio_stamp", audio_stamp), ("sequence_id", sequence_id), ("drone", drone)):
        if value is not None:
            options[key] = value

    bags = [Bag(p) for p in bag_paths]
    owner: dict[str, Bag] = {}
    types: dict[str, str] = {}
    counts: dict[str, int] = {}
    for bag in bags:
        for topic, msgtype in bag.types.items():
            if topic in owner:
                raise RecordingError(f"topic {topic} appears in both {owner[topic].path} and {bag.path}; the bags "
                                     f"of one recording must not overlap (put each flight's bags in its own folder)")
            owner[topic], types[topic], counts[topic] = bag, msgtype, bag.counts[topic]
    topics = map_topics(types, counts, {k: v for k, v in options.items() if k in STREAM_TYPES}, where)
    if "audio" not in topics and not ("audio" in options and options["audio"] is None):
        raise RecordingError(f"{where}: no audio topic (audio_common_msgs AudioData or AudioDataStamped); topics: "
                             f"{_topic_list(types, counts)}. Map one (audio: <topic>) or pass audio: null to "
                             f"read the other sensors alone")
    for key, topic in topics.items():
        if counts[topic] == 0:
            raise RecordingError(f"{owner[topic].path}: topic {topic} ({key}) holds no messages")

    index = _index_bags(bags, owner, topics)
    unread = sorted(t for t, msgtype in types.items() if msgtype in LIDAR_TYPES and t not in topics.values()
                    and counts[t] > 0)
    meta: dict[str, Any] = {
        "source_format": "rosbag1",
        "unread_lidar_topics": unread,
        "bags": [p.name for p in bag_paths],
        "source_path": str(folder.resolve()),
        "topics": topics,
        "frame": FRAME,
        "frame_description": FRAME_DESCRIPTION,
        "frame_ids": index.frame_ids,
        "mic_positions_known": False,
    }
    audio = _build_audio(owner, topics, index, options, meta) if "audio" in topics else None
    lidar: dict[str, PointCloudStream] = {}
    for sensor in ("mid360", "avia"):
        if sensor in topics:
            topic = topics[sensor]
            lidar[sensor] = BagPointClouds(owner[topic], topic, *index.stamps(topic, owner[topic]))
    frames = None
    if "image" in topics:
        topic = topics["image"]
        frames = BagImages(owner[topic], topic, *index.stamps(topic, owner[topic]))
    ground_truth = None
    if "ground_truth" in topics:
        stamps, xyz = index.track
        check_monotonic(ns_to_seconds(stamps), f"{owner[topics['ground_truth']].path} {topics['ground_truth']}")
        check_track_values(ns_to_seconds(stamps), xyz, None,
                           f"{owner[topics['ground_truth']].path} {topics['ground_truth']}")
        ground_truth = Track(ns_to_seconds(stamps), xyz)
    gaps = {key: count_gaps(stream.timestamps) for key, stream in (*lidar.items(), ("image", frames))
            if stream is not None}
    for key, count in gaps.items():
        if count:
            log.warning("%s: %d gap(s) in %s (missing frames)", where, count, topics[key])
    meta["gaps"] = gaps
    names = [folder.name, *(p.stem for p in bag_paths)]
    chosen_drone = options.get("drone") or _drone_from_names(names)
    return Recording(
        sequence_id=str(options.get("sequence_id") or (folder.name if folder_given else bag_paths[0].stem)),
        drone=chosen_drone,
        audio=audio,
        lidar=lidar,
        frames=frames,
        ground_truth=ground_truth,
        meta=json_safe(meta),
    )


@dataclass
class _BagIndex:
    """What the opening pass keeps: per topic log times and stamps, audio sample counts, the track."""

    log_ns: dict[str, list[int]] = field(default_factory=dict)
    stamp_ns: dict[str, list[int]] = field(default_factory=dict)
    audio_bytes: list[int] = field(default_factory=list)
    audio_info: Any = None
    frame_ids: dict[str, str] = field(default_factory=dict)
    track: tuple[np.ndarray, np.ndarray] = (np.zeros(0, np.int64), np.zeros((0, 3)))

    def stamps(self, topic: str, bag: Bag) -> tuple[np.ndarray, np.ndarray]:
        log_ns = np.asarray(self.log_ns[topic], dtype=np.int64)
        stamps = np.asarray(self.stamp_ns[topic], dtype=np.int64)
        check_monotonic(ns_to_seconds(stamps), f"{bag.path} {topic} (header stamps)")
        return log_ns, stamps


def _index_bags(bags: list[Bag], owner: dict[str, Bag], topics: dict[str, str]) -> _BagIndex:
    index = _BagIndex()
    role = {topic: key for key, topic in topics.items()}
    gt_stamps, gt_xyz = [], []
    for bag in bags:
        mine = [t for t in topics.values() if owner[t] is bag]
        if not mine:
            continue
        with_header = {t: bag.has_header(bag.types[t]) for t in mine}
        for topic, log_ns, raw in bag.messages(mine):
            key = role[topic]
            msgtype = bag.types[topic]
            what = f"{bag.path} {topic}"
            index.log_ns.setdefault(topic, []).append(log_ns)
            if key == "audio_info":
                if index.audio_info is None:
                    index.audio_info = bag.deserialize(raw, msgtype, what)
                continue
            if key == "audio":
                msg = bag.deserialize(raw, msgtype, what)
                stamped = msgtype == AUDIO_TYPES[1]
                index.stamp_ns.setdefault(topic, []).append(stamp_ns(msg.header) if stamped else log_ns)
                index.audio_bytes.append(len(msg.audio.data if stamped else msg.data))
                continue
            if key == "ground_truth":
                msg = bag.deserialize(raw, msgtype, what)
                point = msg.point if hasattr(msg, "point") else msg.pose.position
                gt_stamps.append(stamp_ns(msg.header))
                gt_xyz.append((float(point.x), float(point.y), float(point.z)))
                continue
            if with_header[topic]:
                stamp, frame_id, _ = _raw_header(raw, what)
                index.frame_ids.setdefault(key, frame_id)
            else:
                stamp = log_ns
            index.stamp_ns.setdefault(topic, []).append(stamp)
    index.track = (np.asarray(gt_stamps, dtype=np.int64), np.asarray(gt_xyz, dtype=np.float64).reshape(-1, 3))
    return index


def _build_audio(owner: dict[str, Bag], topics: dict[str, str], index: _BagIndex, options: dict[str, Any],
                 meta: dict[str, Any]) -> BagAudio:
    topic = topics["audio"]
    bag = owner[topic]
    what = f"{bag.path} {topic}"
    info = index.audio_info
    given = {k: options[k] for k in ("sample_rate", "channels", "sample_format") if k in options}
    if info is not None:
        coding = str(getattr(info, "coding_format", "") or "").lower()
        if coding not in ("", "wave", "wav", "raw", "pcm"):
            raise RecordingError(f"{what}: audio coded as {coding!r} ({topics['audio_info']}); only raw PCM "
                                 f"('wave') audio can be read")
        from_info = {"sample_rate": float(info.sample_rate), "channels": int(info.channels),
                     "sample_format": str(info.sample_format).upper()}
        for key, value in given.items():
            if (float(value) if key == "sample_rate" else value) != from_info[key]:
                raise RecordingError(f"{what}: {key} {value!r} given but {topics['audio_info']} says "
                                     f"{from_info[key]!r}")
        params, source = from_info, topics["audio_info"]
    else:
        params = {k: given.get(k, DEFAULT_AUDIO[k]) for k in ("sample_rate", "channels", "sample_format")}
        source = "parameters" if given else "defaults (no AudioInfo topic)"
    rate, channels, fmt = float(params["sample_rate"]), int(params["channels"]), str(params["sample_format"])
    stamp_at = options.get("audio_stamp", DEFAULT_AUDIO["audio_stamp"])
    if fmt not in SAMPLE_FORMATS:
        raise RecordingError(f"{what}: audio sample format {fmt!r} not supported; expected one of "
                             f"{sorted(SAMPLE_FORMATS)}")
    if channels < 1 or rate <= 0:
        raise RecordingError(f"{what}: need at least one channel and a positive rate, got {channels} ch {rate} Hz")
    if stamp_at not in ("end", "start"):
        raise RecordingError(f"{what}: audio_stamp must be 'end' or 'start', got {stamp_at!r}")
    frame = channels * np.dtype(SAMPLE_FORMATS[fmt]).itemsize
    nbytes = np.asarray(index.audio_bytes, dtype=np.int64)
    odd = np.flatnonzero(nbytes % frame)
    if odd.size:
        raise RecordingError(f"{what}: message {int(odd[0])} holds {int(nbytes[odd[0]])} bytes, not whole "
                             f"{channels}-channel {fmt} frames ({odd.size} such messages); check channels/format")
    counts = nbytes // frame
    if (counts == 0).any():
        log.warning("%s: %d empty audio message(s)", what, int((counts == 0).sum()))
    stamps_ns = np.asarray(index.stamp_ns[topic], dtype=np.int64)
    check_monotonic(ns_to_seconds(stamps_ns), what, strict=False)
    log_ns = np.asarray(index.log_ns[topic], dtype=np.int64)
    if counts.size > RATE_MIN_MESSAGES:
        # samples per second of stamps, all channels together: names a wrong channel count as such
        values = nbytes // np.dtype(SAMPLE_FORMATS[fmt]).itemsize
        check_audio_rate(values[1:] if stamp_at == "end" else values[:-1], np.diff(stamps_ns) / 1e9, rate,
                         channels, f"{what} ({source})")
    layout = layout_audio(stamps_ns, counts, rate, stamp_at, what)
    if layout.gaps:
        log.warning("%s: %d gap(s) in the audio (dropped messages?), %.3f s filled with zeros",
                    what, layout.gaps, layout.gap_samples / rate)
    meta["audio_source"] = {"topic": topic, "parameters_from": source, "stamp_marks": stamp_at,
                            "rate_by_stamps": layout.rate_by_stamps}
    meta["audio_gaps"] = layout.gaps
    meta["audio_gap_seconds"] = layout.gap_samples / rate
    return BagAudio(bag, topic, log_ns, layout, counts, rate, channels, fmt)


def open_rosbag1(path: str | Path, **options: Any) -> Recording:
    """Open a ``.bag`` file or a folder of bags (one recording) with :func:`read_rosbag1`."""
    return read_rosbag1(Path(path), **options)


def topic_summary(paths: Sequence[str | Path]) -> dict[str, tuple[str, int]]:
    """``{topic: (message type, count)}`` of bags, e.g. to write a mapping."""
    summary: dict[str, tuple[str, int]] = {}
    for p in paths:
        bag = Bag(Path(p))
        summary.update({t: (bag.types[t], bag.counts[t]) for t in bag.types})
    return summary

