"""One ROS 1 bag file: its connections, a typestore built from their definitions, raw message access.

Also the message types the reader maps to streams, and the two raw layouts it parses without the
deserializer (the ``std_msgs/Header`` a message starts with, the points of a Livox ``CustomMsg``).
``rosbags`` is imported only when a bag is opened, so the package imports without it.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from datamodules.recording import RecordingError

#: time (ns) read beyond the asked range when several topics are read together (nodes' stamps differ by jitter)
SHARED_PAD_NS = 500_000_000
#: message types of each kind of stream
AUDIO_TYPES = ("audio_common_msgs/msg/AudioData", "audio_common_msgs/msg/AudioDataStamped")
AUDIO_INFO_TYPE = "audio_common_msgs/msg/AudioInfo"
LIVOX_TYPES = ("livox_ros_driver/msg/CustomMsg", "livox_ros_driver2/msg/CustomMsg")
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
LIDAR_TYPES = (*LIVOX_TYPES, CLOUD_TYPE)
IMAGE_TYPES = ("sensor_msgs/msg/CompressedImage",)
GROUND_TRUTH_TYPES = ("geometry_msgs/msg/PointStamped", "geometry_msgs/msg/PoseStamped")

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


class Bag:
    """One ROS 1 bag: its connections, a typestore built from their definitions, raw message access.

    The reader is reopened after a fork, so DataLoader workers never share a file offset.
    """

    def __init__(self, path: Path):
        self.path = Path(path)
        self._pid = -1
        self._reader: Any = None
        self._shared: tuple[int, int, int, dict[str, list[tuple[int, bytes]]]] | None = None
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
        #: per Livox CustomMsg type: whether it is the standard layout, whose points parse as one array
        self.standard_livox = {t: self._is_standard_livox(t) for t in set(self.types.values()) if t in LIVOX_TYPES}

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

    def messages_together(self, topic: str, start: int, stop: int, together: Sequence[str]
                          ) -> list[tuple[int, bytes]]:
        """``(log time ns, raw)`` of ``topic``'s messages in ``[start, stop)``, read in one pass with the topics
        ``together`` (and :data:`SHARED_PAD_NS` either side) and kept until a read outside that range: the audio
        nodes of one bag are read for the same time range one after the other, and a compressed chunk is then
        decompressed once rather than once per node."""
        cache = self._shared
        if cache is None or cache[0] != os.getpid() or not cache[1] <= start <= stop <= cache[2] \
                or topic not in cache[3]:
            lo, hi = start - SHARED_PAD_NS, stop + SHARED_PAD_NS
            kept: dict[str, list[tuple[int, bytes]]] = {t: [] for t in {topic, *together}}
            for name, log_ns, raw in self.messages(list(kept), start=lo, stop=hi):
                kept[name].append((log_ns, bytes(raw)))
            cache = self._shared = (os.getpid(), lo, hi, kept)
        return [(t, raw) for t, raw in cache[3][topic] if start <= t < stop]

    def message_at(self, topic: str, log_ns: np.ndarray, position: int) -> memoryview | bytes:
        """Raw message number ``position`` of ``topic`` (positions as :meth:`messages` yields them)."""
        t = int(log_ns[position])
        skip = position - int(np.searchsorted(log_ns, t, side="left"))
        for i, (_, _, raw) in enumerate(self.messages([topic], start=t, stop=t + 1)):
            if i == skip:
                return raw
        raise RecordingError(f"{self.path}: message {position} of {topic} not found on re-reading")


def raw_header(raw: memoryview | bytes, what: str) -> tuple[int, str, int]:
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
    _, _, offset = raw_header(raw, what)
    offset += 8 + 4 + 1 + 3  # timebase, point_num, lidar_id, rsvd[3]
    count = int(np.frombuffer(bytes(raw[offset:offset + 4]), dtype="<u4")[0])
    offset += 4
    if offset + count * _LIVOX_POINT.itemsize != len(raw):
        raise RecordingError(f"{what}: CustomMsg of {len(raw)} bytes cannot hold {count} points")
    return np.frombuffer(raw, dtype=_LIVOX_POINT, count=count, offset=offset)



def audio_payload(raw: memoryview | bytes, stamped: bool, what: str) -> memoryview:
    """The sample bytes of a serialized ``AudioData`` (``uint8[] data``) or ``AudioDataStamped`` (header, then
    ``AudioData``), read from the raw layout without the deserializer (it copies every byte array)."""
    offset = raw_header(raw, what)[2] if stamped else 0
    view = memoryview(raw)
    if offset + 4 > len(view):
        raise RecordingError(f"{what}: audio message too short ({len(view)} bytes)")
    length = int.from_bytes(view[offset:offset + 4], "little")
    if offset + 4 + length != len(view):
        raise RecordingError(f"{what}: corrupt audio message ({length} sample bytes in a {len(view)}-byte message)")
    return view[offset + 4:]
