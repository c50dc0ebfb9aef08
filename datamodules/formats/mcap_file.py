"""The canonical on-disk recording: one MCAP file with ROS 2 (CDR) messages.

Layout (DESIGN.md section 4):

=================  =======================================  =====================================
topic              schema                                   content
=================  =======================================  =====================================
/audio/info        audio_common_msgs/msg/AudioInfo          channels, integer sample rate, format
/audio             audio_common_msgs/msg/AudioDataStamped   interleaved samples, stamp = 1st sample
/livox/mid360      sensor_msgs/msg/PointCloud2              x y z intensity (float32), origin (u8)
/livox/avia        sensor_msgs/msg/PointCloud2              same
/camera/image      sensor_msgs/msg/CompressedImage          PNG or JPEG as the camera produced it
/ground_truth      geometry_msgs/msg/PointStamped           Leica-style positions
/pseudo_label      geometry_msgs/msg/PointStamped           teacher output (valid labels only)
<track>/quality    aaute_msgs/msg/TrackQuality              per label time: valid flag, quality
=================  =======================================  =====================================

MCAP metadata ``mmaud`` holds the sequence id, drone, format version and the recording's ``meta``
as JSON; metadata ``audio`` holds the exact sample rate, t0, sample count, microphone positions
and the sample format. Small topics are written first so they share at most one chunk with the
bulk data; every topic is then written in time order, so a window read touches only the chunks
of that topic and time (found through MCAP's chunk and message indexes, never by a full scan).
"""

from __future__ import annotations

import io
import json
import os
import stat
from collections import OrderedDict
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.reader import SeekingReader, make_reader
from mcap.records import Chunk, Message, MessageIndex
from mcap.stream_reader import CRCValidationError, breakup_chunk
from mcap.writer import Writer as RawWriter
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer

from datamodules.atomic import atomic_write
from datamodules.formats.ros_messages import (
    MSGDEFS,
    SAMPLE_FORMATS,
    full_scale,
    header,
    pointcloud_fields,
    pointcloud_to_arrays,
    stamp_ns,
)
from datamodules.recording import (
    LIDAR_SENSORS,
    AudioStream,
    EncodedImage,
    ImageStream,
    PointCloud,
    PointCloudStream,
    Recording,
    RecordingError,
    Track,
    check_audio_rate,
    check_finite_audio,
    check_monotonic,
    check_track_values,
    ns_to_seconds,
    seconds_to_ns,
    to_json,
)

FORMAT_VERSION = "1"
TOPIC_AUDIO = "/audio"
TOPIC_AUDIO_INFO = "/audio/info"
TOPIC_IMAGE = "/camera/image"
TOPIC_GROUND_TRUTH = "/ground_truth"
TOPIC_PSEUDO_LABEL = "/pseudo_label"
LIDAR_TOPICS = {"mid360": "/livox/mid360", "avia": "/livox/avia"}
QUALITY_SUFFIX = "/quality"
AUDIO_CHUNK_SECONDS = 0.1  #: MMAUD-style 0.1 s audio messages aligned to the 10 Hz labels
RATE_CHECK_MESSAGES = 5  #: audio messages, spread over the recording, decoded to check the rate against the stamps


# ============================================================================================ writing


def _audio_format(audio: AudioStream, requested: str | None) -> str:
    if requested is not None:
        if requested not in SAMPLE_FORMATS:
            raise ValueError(f"unknown audio sample format {requested!r}; known: {sorted(SAMPLE_FORMATS)}")
        return requested
    return getattr(audio, "sample_format", None) or "F32LE"


def _encode_audio(block: np.ndarray, sample_format: str) -> bytes:
    """Channels x samples float32 -> interleaved bytes of ``sample_format``."""
    interleaved = block.T
    if sample_format == "F32LE":
        return np.ascontiguousarray(interleaved, dtype="<f4").tobytes()
    scale = full_scale(SAMPLE_FORMATS[sample_format])
    codes = np.rint(interleaved.astype(np.float64) * scale)
    if np.any(codes != interleaved.astype(np.float64) * scale) or np.any(np.abs(codes) > scale):
        raise ValueError(f"audio samples do not lie on the {sample_format} grid; write them as F32LE")
    return codes.astype(SAMPLE_FORMATS[sample_format]).tobytes()


def write_mcap(
    recording: Recording,
    path: str | Path,
    *,
    overwrite: bool = False,
    audio_format: str | None = None,
    chunk_size: int = 1 << 20,
) -> Path:
    """Write ``recording`` to ``path`` atomically (temporary file, then rename).

    Args:
        recording: what to write; lazily read streams are read block by block.
        path: destination ``.mcap`` file.
        overwrite: replace an existing file (only once the new one is complete).
        audio_format: 'S16LE', 'S32LE' or 'F32LE'; by default the stream's own format (the
            simulator's 16-bit ADC output is exactly S16LE) or F32LE.
        chunk_size: MCAP chunk size in bytes (zstd-compressed per chunk).
    """
    path = Path(path)
    with atomic_write(path, overwrite) as tmp, open(tmp, "wb") as stream:
        writer = Writer(stream, chunk_size=chunk_size)
        schemas = {name: writer.register_msgdef(name, text) for name, text in MSGDEFS.items()}
        _write_metadata(writer, recording, audio_format)
        for topic, track in ((TOPIC_GROUND_TRUTH, recording.ground_truth),
                             (TOPIC_PSEUDO_LABEL, recording.pseudo_labels)):
            if track is not None:
                _write_track(writer, schemas, topic, track)
        if recording.audio is not None:
            _write_audio(writer, schemas, recording.audio, _audio_format(recording.audio, audio_format))
        for sensor, clouds in recording.lidar.items():
            _write_clouds(writer, schemas, LIDAR_TOPICS[sensor], clouds, sensor)
        if recording.frames is not None:
            _write_images(writer, schemas, recording.frames)
        writer.finish()
    return path


def _write_metadata(writer: Writer, recording: Recording, audio_format: str | None) -> None:
    writer.add_metadata("mmaud", {
        "format_version": FORMAT_VERSION,
        "sequence_id": recording.sequence_id,
        "drone": recording.drone or "",
        "meta_json": to_json(recording.meta),
    })
    audio = recording.audio
    if audio is not None:
        writer.add_metadata("audio", {
            "sample_rate": repr(float(audio.sample_rate)),
            "t0": repr(float(audio.t0)),
            "num_samples": str(audio.num_samples),
            "channels": str(audio.num_channels),
            "sample_format": _audio_format(audio, audio_format),
            "mic_positions_json": json.dumps(np.asarray(audio.mic_positions).tolist()),
        })


def _write_track(writer: Writer, schemas: dict, topic: str, track: Track) -> None:
    check_monotonic(track.timestamps, topic)
    stamps = seconds_to_ns(track.timestamps)
    names = sorted(track.quality)
    with_quality = bool(names) or not track.valid.all()
    for i, ns in enumerate(stamps):
        ns = int(ns)
        if track.valid[i]:
            x, y, z = (float(v) for v in track.xyz[i])
            writer.write_message(topic, schemas["geometry_msgs/msg/PointStamped"],
                                 {"header": header(ns, "rig"), "point": {"x": x, "y": y, "z": z}}, ns, ns, i)
        if with_quality:
            values = [float(track.quality[name][i]) for name in names]
            writer.write_message(topic + QUALITY_SUFFIX, schemas["aaute_msgs/msg/TrackQuality"],
                                 {"header": header(ns, "rig"), "valid": bool(track.valid[i]),
                                  "names": names, "values": values}, ns, ns, i)


def _write_audio(writer: Writer, schemas: dict, audio: AudioStream, sample_format: str) -> None:
    rate = float(audio.sample_rate)
    writer.write_message(TOPIC_AUDIO_INFO, schemas["audio_common_msgs/msg/AudioInfo"], {
        "channels": audio.num_channels, "sample_rate": int(round(rate)), "sample_format": sample_format,
        "bitrate": 0, "coding_format": "wave"}, int(seconds_to_ns(audio.t0)), int(seconds_to_ns(audio.t0)))
    chunk = max(1, int(round(AUDIO_CHUNK_SECONDS * rate)))
    block = chunk * 100
    schema = schemas["audio_common_msgs/msg/AudioDataStamped"]
    seq = 0
    for start in range(0, audio.num_samples, block):
        samples = audio.read(start, min(start + block, audio.num_samples))
        if samples.shape[0] != audio.num_channels:
            raise RecordingError(f"audio has {samples.shape[0]} channels but {audio.num_channels} mic positions")
        check_finite_audio(samples, audio.t0 + start / rate, rate, "audio to write", audio.t0)
        for offset in range(0, samples.shape[1], chunk):
            first = start + offset
            ns = int(seconds_to_ns(audio.t0 + first / rate))
            data = _encode_audio(samples[:, offset:offset + chunk], sample_format)
            writer.write_message(TOPIC_AUDIO, schema, {"header": header(ns, "mics"), "audio": {"data": data}},
                                 ns, ns, seq)
            seq += 1


def _write_clouds(writer: Writer, schemas: dict, topic: str, clouds: PointCloudStream, frame_id: str) -> None:
    schema = schemas["sensor_msgs/msg/PointCloud2"]
    check_monotonic(clouds.timestamps, topic)
    for i, ns in enumerate(seconds_to_ns(clouds.timestamps)):
        cloud = clouds[i]
        n = len(cloud)
        fields = {"x": cloud.points[:, 0].astype(np.float32), "y": cloud.points[:, 1].astype(np.float32),
                  "z": cloud.points[:, 2].astype(np.float32)}
        if cloud.intensity is not None:
            intensity = np.asarray(cloud.intensity, dtype=np.float32)
            # Livox reflectivity is an integer 0-255: store it in one byte when that is exact
            as_byte = intensity.astype(np.uint8)
            exact = np.array_equal(as_byte, intensity)
            fields["intensity"] = as_byte if exact else intensity
        if cloud.origin is not None:
            fields["origin"] = np.asarray(cloud.origin, dtype=np.uint8)
        descriptors, step, data = pointcloud_fields(fields)
        writer.write_message(topic, schema, {
            "header": header(int(ns), frame_id), "height": 1, "width": n, "fields": descriptors,
            "is_bigendian": False, "point_step": step, "row_step": step * n, "data": data, "is_dense": True,
        }, int(ns), int(ns), i)


def _write_images(writer: Writer, schemas: dict, frames: ImageStream) -> None:
    schema = schemas["sensor_msgs/msg/CompressedImage"]
    check_monotonic(frames.timestamps, TOPIC_IMAGE)
    for i, ns in enumerate(seconds_to_ns(frames.timestamps)):
        image = frames[i]
        writer.write_message(TOPIC_IMAGE, schema, {"header": header(int(ns), "camera"), "format": image.format,
                                                    "data": image.data}, int(ns), int(ns), i)


def replace_track(path: str | Path, topic: str, track: Track | None) -> Path:
    """Rewrite an MCAP recording with ``topic`` (and its quality topic) replaced by ``track``.

    Used to store pseudo-labels beside the sensor data. The new track goes first (small topics
    first, as :func:`write_mcap` does); every other message is copied byte for byte. The new file
    replaces the old one only once it is complete, so an interrupted run leaves the original
    intact. ``track=None`` removes the topic.
    """
    path = Path(path)
    drop = {topic, topic + QUALITY_SUFFIX}
    index = McapIndex(path)  # validates the file and names it in errors
    encoded = io.BytesIO()
    if track is not None:
        track_writer = Writer(encoded)
        schemas = {name: track_writer.register_msgdef(name, text) for name, text in MSGDEFS.items()}
        _write_track(track_writer, schemas, topic, track)
        track_writer.finish()
        encoded.seek(0)
    mode = stat.S_IMODE(path.stat().st_mode)
    with atomic_write(path) as tmp, open(path, "rb") as source, open(tmp, "wb") as target:
        writer = RawWriter(target)
        writer.start(profile="ros2", library="aaute")
        for name, meta in index.metadata.items():
            writer.add_metadata(name, meta)
        if track is not None:
            _copy_messages(make_reader(encoded), writer, set())
        _copy_messages(make_reader(source, validate_crcs=True), writer, drop)
        writer.finish()
        os.chmod(tmp, mode)  # the rewritten file keeps the recording's permissions
    return path


def _copy_messages(reader: SeekingReader, writer: RawWriter, drop: set[str]) -> None:
    """Copy every message (except ``drop`` topics) with its schema and channel, undecoded."""
    summary = reader.get_summary()
    schema_ids = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in summary.schemas.items()}
    channel_ids = {
        cid: writer.register_channel(c.topic, c.message_encoding, schema_ids.get(c.schema_id, 0), c.metadata)
        for cid, c in summary.channels.items()
        if c.topic not in drop
    }
    for _, channel, message in reader.iter_messages(log_time_order=False):
        if channel.id in channel_ids:
            writer.add_message(channel_ids[channel.id], message.log_time, message.data, message.publish_time,
                               message.sequence)


# ============================================================================================ reading


class McapIndex:
    """Per-topic message index of an MCAP file: log times and chunk of every message.

    Built from the chunk indexes and MessageIndex records of the summary, so no chunk is
    decompressed to learn where messages are. Chunks are decompressed on demand, a few cached.
    The file is reopened after a fork, so DataLoader workers never share a file offset.
    """

    def __init__(self, path: Path, cache_chunks: int = 4):
        self.path = Path(path)
        self._pid = -1
        self._stream = None
        self._cache: OrderedDict[int, dict] = OrderedDict()
        self._cache_chunks = cache_chunks
        reader = self._reader()
        try:
            summary = reader.get_summary()
        except (McapError, EOFError, ValueError, OSError) as error:
            raise RecordingError(f"{self.path}: corrupt or truncated MCAP file ({error})") from error
        if summary is None:
            raise RecordingError(f"{self.path}: MCAP file has no summary section (truncated or not indexed)")
        self.summary = summary
        self.metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        self.topics = {channel.topic: channel for channel in summary.channels.values()}
        self._decoders: dict[int, Any] = {}
        self._entries: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._read_message_indexes()

    def _reader(self) -> SeekingReader:
        if self._pid != os.getpid() or self._stream is None:
            try:
                self._stream = open(self.path, "rb")  # noqa: SIM115 - kept open for lazy reads
                self._reader_obj = make_reader(self._stream)
            except FileNotFoundError:
                raise RecordingError(f"{self.path}: no such file") from None
            except McapError as error:
                raise RecordingError(f"{self.path}: not an MCAP file ({error})") from error
            self._pid = os.getpid()
            self._cache.clear()
        return self._reader_obj

    def _read_message_indexes(self) -> None:
        per_topic: dict[str, list[tuple[int, int]]] = {topic: [] for topic in self.topics}
        stream = self._stream
        for chunk_id, chunk_index in enumerate(self.summary.chunk_indexes):
            for channel_id, offset in chunk_index.message_index_offsets.items():
                stream.seek(offset + 1 + 8)  # opcode and record length
                index = MessageIndex.read(ReadDataStream(stream))
                topic = self.summary.channels[channel_id].topic
                per_topic[topic].extend((log_time, chunk_id) for log_time, _ in index.records)
        for topic, entries in per_topic.items():
            array = np.array(entries, dtype=np.int64).reshape(-1, 2)
            order = np.argsort(array[:, 0], kind="stable")
            self._entries[topic] = (array[order, 0], array[order, 1])

    def log_times(self, topic: str) -> np.ndarray:
        """Log times (ns) of a topic's messages, sorted."""
        return self._entries[topic][0] if topic in self._entries else np.zeros(0, dtype=np.int64)

    def _chunk_messages(self, chunk_id: int) -> dict:
        if chunk_id in self._cache:
            self._cache.move_to_end(chunk_id)
            return self._cache[chunk_id]
        self._reader()
        chunk_index = self.summary.chunk_indexes[chunk_id]
        self._stream.seek(chunk_index.chunk_start_offset + 1 + 8)
        try:
            chunk = Chunk.read(ReadDataStream(self._stream))
            records = breakup_chunk(chunk, validate_crc=True)  # chunks written without a CRC (0) pass unchecked
        except CRCValidationError as error:
            raise RecordingError(f"{self.path}: corrupt chunk ({self._describe_chunk(chunk_id)}): its CRC does not "
                                 f"match its data (expected {error.expected:#010x}, found {error.actual:#010x})") \
                from error
        except Exception as error:  # zstd/lz4 errors have no common base class
            raise RecordingError(f"{self.path}: corrupt chunk ({self._describe_chunk(chunk_id)}): {error}") from error
        messages: dict[tuple[int, int], list[Message]] = {}
        for record in records:
            if isinstance(record, Message):
                messages.setdefault((record.channel_id, record.log_time), []).append(record)
        self._cache[chunk_id] = messages
        if len(self._cache) > self._cache_chunks:
            self._cache.popitem(last=False)
        return messages

    def _describe_chunk(self, chunk_id: int) -> str:
        """Where a chunk lies: its byte offset, time range and topics (for error messages)."""
        chunk_index = self.summary.chunk_indexes[chunk_id]
        start, end = (float(ns_to_seconds(ns)) for ns in (chunk_index.message_start_time,
                                                           chunk_index.message_end_time))
        topics = sorted(self.summary.channels[c].topic for c in chunk_index.message_index_offsets)
        return f"byte {chunk_index.chunk_start_offset}, t = {start:.3f} to {end:.3f} s, topic(s) {', '.join(topics)}"

    def _decode(self, channel_id: int, data: bytes) -> Any:
        decoder = self._decoders.get(channel_id)
        if decoder is None:
            channel = self.summary.channels[channel_id]
            schema = self.summary.schemas[channel.schema_id]
            decoder = DecoderFactory().decoder_for(channel.message_encoding, schema)
            if decoder is None:
                raise RecordingError(f"{self.path}: cannot decode topic {channel.topic} ({schema.name})")
            self._decoders[channel_id] = decoder
        return decoder(data)

    def message(self, topic: str, position: int) -> Any:
        """Decoded message number ``position`` (in log-time order) of ``topic``."""
        times, chunks = self._entries[topic]
        channel_id = self.topics[topic].id
        log_time = int(times[position])
        same_time = int(position - np.searchsorted(times, log_time, side="left"))
        records = self._chunk_messages(int(chunks[position])).get((channel_id, log_time), [])
        if same_time >= len(records):
            raise RecordingError(f"{self.path}: message {position} of {topic} missing from its chunk")
        return self._decode(channel_id, records[same_time].data)

    def messages(self, topic: str) -> Iterator[Any]:
        for position in range(self.log_times(topic).size):
            yield self.message(topic, position)


class McapAudio(AudioStream):
    """Audio of an MCAP recording, decoded message by message for the requested sample range."""

    def __init__(self, index: McapIndex):
        self._index = index
        path = index.path
        meta = index.metadata.get("audio")
        if meta is None:
            raise RecordingError(f"{path}: topic {TOPIC_AUDIO} present but metadata 'audio' missing")
        self.sample_rate = float(meta["sample_rate"])
        self.t0 = float(meta["t0"])
        self.num_samples = int(meta["num_samples"])
        self.mic_positions = np.asarray(json.loads(meta["mic_positions_json"]), dtype=np.float64).reshape(-1, 3)
        self.sample_format = meta["sample_format"]
        if self.sample_format not in SAMPLE_FORMATS:
            raise RecordingError(f"{path}: unknown audio sample format {self.sample_format!r}")
        channels = int(meta["channels"])
        if channels != self.mic_positions.shape[0]:
            raise RecordingError(f"{path}: {channels} audio channels but {len(self.mic_positions)} mic positions")
        if TOPIC_AUDIO_INFO in index.topics and index.log_times(TOPIC_AUDIO_INFO).size:
            info = index.message(TOPIC_AUDIO_INFO, 0)
            if int(info.channels) != channels or int(info.sample_rate) != int(round(self.sample_rate)) \
                    or info.sample_format != self.sample_format:
                raise RecordingError(
                    f"{path}: {TOPIC_AUDIO_INFO} says {info.channels} ch, {info.sample_rate} Hz, "
                    f"{info.sample_format}, metadata says {channels} ch, {self.sample_rate} Hz, {self.sample_format}"
                )
        self._dtype = np.dtype(SAMPLE_FORMATS[self.sample_format])
        self._scale = full_scale(self._dtype)
        stamps = index.log_times(TOPIC_AUDIO)
        check_monotonic(ns_to_seconds(stamps), f"{path} {TOPIC_AUDIO}")
        # sample index of each message's first sample, from its stamp
        self._first = np.rint((ns_to_seconds(stamps) - self.t0) * self.sample_rate).astype(np.int64)
        self._stamps = stamps
        self._check_rate()

    def _check_rate(self) -> None:
        """Decode a few messages spread over the recording and check rate and channels against the stamps."""
        stamps = self._stamps
        if stamps.size < 2:
            return
        picks = np.unique(np.linspace(0, stamps.size - 2, min(RATE_CHECK_MESSAGES, stamps.size - 1)).astype(int))
        values = np.array([self._raw(int(i)).size for i in picks])
        steps = (stamps[picks + 1] - stamps[picks]) / 1e9
        check_audio_rate(values, steps, self.sample_rate, self.num_channels,
                         f"{self._index.path} {TOPIC_AUDIO} (metadata 'audio' and {TOPIC_AUDIO_INFO})")

    def read(self, start: int, stop: int) -> np.ndarray:
        self._check_range(start, stop)
        out = np.zeros((self.num_channels, stop - start), dtype=np.float32)
        if stop == start:
            return out
        first = max(int(np.searchsorted(self._first, start, side="right")) - 1, 0)
        filled = start
        position = first
        while filled < stop and position < self._first.size:
            msg_start = int(self._first[position])
            block = self._decode(position)
            msg_stop = msg_start + block.shape[1]
            if msg_start > filled:
                raise RecordingError(f"{self._index.path}: audio gap at sample {filled} (next message at {msg_start})")
            lo, hi = max(start, msg_start), min(stop, msg_stop)
            if hi > lo:
                out[:, lo - start:hi - start] = block[:, lo - msg_start:hi - msg_start]
                filled = hi
            position += 1
        if filled < stop:
            raise RecordingError(f"{self._index.path}: audio ends at sample {filled}, {stop} requested")
        return out

    def _raw(self, position: int) -> np.ndarray:
        msg = self._index.message(TOPIC_AUDIO, position)
        return np.frombuffer(bytes(msg.audio.data), dtype=self._dtype)

    def _decode(self, position: int) -> np.ndarray:
        raw = self._raw(position)
        if raw.size % self.num_channels:
            raise RecordingError(
                f"{self._index.path}: audio message {position} holds {raw.size} samples, "
                f"not a multiple of {self.num_channels} channels"
            )
        block = (raw.reshape(-1, self.num_channels).T / self._scale).astype(np.float32)
        if self._dtype.kind == "f":
            check_finite_audio(block, float(ns_to_seconds(self._stamps[position])), self.sample_rate,
                               f"{self._index.path} {TOPIC_AUDIO}[{position}]", self.t0)
        return block


class McapPointClouds(PointCloudStream):
    """One LiDAR topic of an MCAP recording."""

    def __init__(self, index: McapIndex, topic: str):
        self._index, self._topic = index, topic
        self.timestamps = ns_to_seconds(index.log_times(topic))
        check_monotonic(self.timestamps, f"{index.path} {topic}")

    def __getitem__(self, i: int) -> PointCloud:
        arrays = pointcloud_to_arrays(self._index.message(self._topic, i), f"{self._index.path} {self._topic}[{i}]")
        try:
            points = np.column_stack([arrays["x"], arrays["y"], arrays["z"]]).astype(np.float32)
        except KeyError as missing:
            raise RecordingError(f"{self._index.path} {self._topic}[{i}]: PointCloud2 lacks field {missing}") from None
        intensity = arrays.get("intensity")
        origin = arrays.get("origin")
        return PointCloud(points, None if intensity is None else intensity.astype(np.float32),
                          None if origin is None else origin.astype(np.uint8))


class McapImages(ImageStream):
    """The camera topic of an MCAP recording (frames stay encoded until decoded)."""

    def __init__(self, index: McapIndex, topic: str = TOPIC_IMAGE):
        self._index, self._topic = index, topic
        self.timestamps = ns_to_seconds(index.log_times(topic))
        check_monotonic(self.timestamps, f"{index.path} {topic}")

    def __getitem__(self, i: int) -> EncodedImage:
        msg = self._index.message(self._topic, i)
        return EncodedImage(bytes(msg.data), str(msg.format))


def _read_track(index: McapIndex, topic: str) -> Track | None:
    quality_topic = topic + QUALITY_SUFFIX
    if topic not in index.topics and quality_topic not in index.topics:
        return None
    points = list(index.messages(topic)) if topic in index.topics else []
    point_ns = np.array([stamp_ns(m.header) for m in points], dtype=np.int64)
    xyz = np.array([[m.point.x, m.point.y, m.point.z] for m in points], dtype=np.float64).reshape(-1, 3)
    if quality_topic not in index.topics:
        track = Track(ns_to_seconds(point_ns), xyz)
    else:
        quality = list(index.messages(quality_topic))
        all_ns = np.array([stamp_ns(m.header) for m in quality], dtype=np.int64)
        valid = np.array([bool(m.valid) for m in quality], dtype=bool)
        full = np.full((all_ns.size, 3), np.nan)
        where = np.searchsorted(all_ns, point_ns)
        if not np.array_equal(all_ns[valid], point_ns):
            raise RecordingError(f"{index.path}: {topic} and {quality_topic} disagree on the labelled times")
        full[where] = xyz
        names = list(quality[0].names) if quality else []
        values = np.array([list(m.values) for m in quality], dtype=np.float64).reshape(len(quality), len(names))
        track = Track(ns_to_seconds(all_ns), full, valid, {n: values[:, k] for k, n in enumerate(names)})
    check_monotonic(track.timestamps, f"{index.path} {topic}")
    check_track_values(track.timestamps, track.xyz, track.valid, f"{index.path} {topic}")
    return track


def read_track(path: str | Path, topic: str) -> Track | None:
    """Any track topic of an MCAP recording (e.g. stored predictions), or None if it is absent."""
    return _read_track(McapIndex(Path(path)), topic)


def read_mcap(path: str | Path) -> Recording:
    """Open an MCAP recording lazily: small topics are read now, audio/LiDAR/images on demand."""
    index = McapIndex(Path(path))
    meta = index.metadata.get("mmaud")
    if meta is None:
        raise RecordingError(f"{path}: MCAP metadata 'mmaud' missing: not a recording written by this project "
                             f"(use 'aaute convert' for other layouts)")
    if meta.get("format_version") != FORMAT_VERSION:
        raise RecordingError(f"{path}: recording format version {meta.get('format_version')!r}, "
                             f"this reader understands {FORMAT_VERSION!r}")
    audio = McapAudio(index) if TOPIC_AUDIO in index.topics else None
    lidar = {s: McapPointClouds(index, LIDAR_TOPICS[s]) for s in LIDAR_SENSORS if LIDAR_TOPICS[s] in index.topics}
    frames = McapImages(index) if TOPIC_IMAGE in index.topics else None
    recording_meta = json.loads(meta.get("meta_json", "{}"))
    return Recording(
        sequence_id=meta["sequence_id"],
        drone=meta.get("drone") or None,
        audio=audio,
        lidar=lidar,
        frames=frames,
        ground_truth=_read_track(index, TOPIC_GROUND_TRUTH),
        pseudo_labels=_read_track(index, TOPIC_PSEUDO_LABEL),
        meta=recording_meta,
    )
