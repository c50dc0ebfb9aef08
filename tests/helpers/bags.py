"""ROS 1 bags of a synthetic MMAUD V1 flight, written at test time with rosbags' own writer.

Kept apart from ``tests.helpers.layouts`` because it needs the optional ``rosbags`` package: importing this
module skips the importing test (or test module) when the package is not installed.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from datamodules.recording import ns_to_seconds

rosbag1 = pytest.importorskip("rosbags.rosbag1", reason="the optional 'rosbags' package is not installed")
typesys = pytest.importorskip("rosbags.typesys")

T0_NS = 1_692_845_357_100_000_000  # 24 Aug 2023, an MMAUD V1 day
FS, CHANNELS, MSG = 48000, 4, 4800  # 0.1 s audio messages
SCANS = 30

LIVOX = """std_msgs/Header header
uint64 timebase
uint32 point_num
uint8 lidar_id
uint8[3] rsvd
CustomPoint[] points
"""
LIVOX_POINT = "uint32 offset_time\nfloat32 x\nfloat32 y\nfloat32 z\nuint8 reflectivity\nuint8 tag\nuint8 line\n"


def typestore():
    """ROS 1 noetic types plus audio_common_msgs and Livox CustomMsg, registered from msgdef text."""
    store = typesys.get_typestore(typesys.Stores.ROS1_NOETIC)
    for text, name in (
        ("uint8[] data", "audio_common_msgs/msg/AudioData"),
        ("std_msgs/Header header\nAudioData audio", "audio_common_msgs/msg/AudioDataStamped"),
        ("uint8 channels\nuint32 sample_rate\nstring sample_format\nuint32 bitrate\nstring coding_format",
         "audio_common_msgs/msg/AudioInfo"),
        (LIVOX_POINT, "livox_ros_driver/msg/CustomPoint"),
        (LIVOX, "livox_ros_driver/msg/CustomMsg"),
    ):
        store.register(typesys.get_types_from_msg(text, name))
    return store


TS = typestore()


def ros_header(ns: int, frame: str = "", seq: int = 0):
    """A ``std_msgs/Header`` stamped ``ns`` nanoseconds after the epoch."""
    sec, nsec = divmod(ns, 1_000_000_000)
    stamp = TS.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    return TS.types["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame)


def solid_png(value: int) -> bytes:
    """A 4 x 6 PNG of one grey ``value`` (the camera frames of ``write_flight``)."""
    buffer = io.BytesIO()
    Image.fromarray(np.full((4, 6, 3), value, np.uint8)).save(buffer, "PNG")
    return buffer.getvalue()


class BagWriter:
    """A rosbags writer that, like ``rosbag record``, writes messages in receive-time order on close."""

    def __init__(self, path: Path, compression: str | None):
        self.writer = rosbag1.Writer(path)
        if compression:
            self.writer.set_compression(getattr(rosbag1.Writer.CompressionFormat, compression))
        self.writer.open()
        self.connections: dict = {}
        self.pending: list = []

    def write(self, topic: str, msgtype: str, msg, log_ns: int) -> None:
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=TS)
        self.pending.append((log_ns, len(self.pending), topic, TS.serialize_ros1(msg, msgtype)))

    def close(self) -> None:
        for log_ns, _, topic, raw in sorted(self.pending, key=lambda item: item[:2]):
            self.writer.write(self.connections[topic], log_ns, raw)
        self.writer.close()


def write_flight(folder: Path, compression: str | None = None, *, audio: str = "stamped", info: bool = True,
                 drop: tuple[int, ...] = (), sample_format: str = "S16LE", channels: int = CHANNELS,
                 lidar: bool = True, gt: bool = True, seed: int = 0, mid360_topic: str = "/livox/lidar_360") -> dict:
    """A sensor bag (audio, Avia CustomMsg, Mid-360 PointCloud2, two cameras) and a ground-truth bag."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    dtype = {"S16LE": "<i2", "S32LE": "<i4", "F32LE": "<f4"}[sample_format]
    scale = 1.0 if sample_format == "F32LE" else 2.0 ** (8 * np.dtype(dtype).itemsize - 1)
    count = 30
    codes = (rng.uniform(-0.2, 0.2, (count * MSG, channels)) * scale).astype(dtype)
    truth: dict = {"audio": codes.T.astype(np.float64) / scale, "avia": [], "mid360": [], "images": [], "gt": []}
    bag = BagWriter(folder / "2023-08-24-10-49-05_mavic2.bag", compression)
    if audio:
        if info:
            msg = TS.types["audio_common_msgs/msg/AudioInfo"](channels=channels, sample_rate=FS, bitrate=0,
                                                              sample_format=sample_format, coding_format="wave")
            bag.write("/audio/audio_info", "audio_common_msgs/msg/AudioInfo", msg, T0_NS)
        for k in range(count):
            if k in drop:
                continue
            stamp = T0_NS + (k + 1) * 100_000_000  # a capture driver stamps a full buffer
            data = np.frombuffer(codes[k * MSG:(k + 1) * MSG].tobytes(), np.uint8)
            payload = TS.types["audio_common_msgs/msg/AudioData"](data=data)
            log_ns = stamp + int(rng.integers(0, 8_000_000))  # receive jitter
            if audio == "stamped":
                msg = TS.types["audio_common_msgs/msg/AudioDataStamped"](header=ros_header(stamp, "mics"),
                                                                         audio=payload)
                bag.write("/audio/audio", "audio_common_msgs/msg/AudioDataStamped", msg, log_ns)
            else:
                bag.write("/audio/audio", "audio_common_msgs/msg/AudioData", payload, stamp)
    for k in range(SCANS if lidar else 0):
        stamp = T0_NS + 14_000_000 + k * 100_000_000
        n = int(rng.integers(0, 40))
        xyz = rng.normal(0, 5, (n, 3)).astype(np.float32)
        xyz[::7] = 0.0  # Livox "no return" points
        reflectivity = rng.integers(0, 255, n).astype(np.uint8)
        point = TS.types["livox_ros_driver/msg/CustomPoint"]
        points = [point(offset_time=i, x=float(p[0]), y=float(p[1]), z=float(p[2]), reflectivity=int(r), tag=0,
                        line=i % 6) for i, (p, r) in enumerate(zip(xyz, reflectivity, strict=True))]
        msg = TS.types["livox_ros_driver/msg/CustomMsg"](header=ros_header(stamp, "livox_frame", k), timebase=stamp,
                                                         point_num=n, lidar_id=0, rsvd=np.zeros(3, np.uint8),
                                                         points=points)
        bag.write("/livox/avia", "livox_ros_driver/msg/CustomMsg", msg, stamp + 20_000_000)
        keep = np.any(xyz != 0, axis=1)
        truth["avia"].append((ns_to_seconds(stamp), xyz[keep], reflectivity[keep].astype(np.float32)))

        stamp = T0_NS + k * 100_000_000
        m = int(rng.integers(5, 60))
        cloud = np.zeros(m, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
        for name in ("x", "y", "z", "intensity"):
            cloud[name] = rng.normal(0, 5, m)
        field = TS.types["sensor_msgs/msg/PointField"]
        msg = TS.types["sensor_msgs/msg/PointCloud2"](
            header=ros_header(stamp, "mid360_frame"), height=1, width=m,
            fields=[field(name=n, offset=4 * i, datatype=7, count=1)
                    for i, n in enumerate(("x", "y", "z", "intensity"))],
            is_bigendian=False, point_step=16, row_step=16 * m, data=np.frombuffer(cloud.tobytes(), np.uint8),
            is_dense=True)
        bag.write(mid360_topic, "sensor_msgs/msg/PointCloud2", msg, stamp + 15_000_000)
        truth["mid360"].append((ns_to_seconds(stamp), np.column_stack([cloud["x"], cloud["y"], cloud["z"]]),
                                cloud["intensity"]))
        for side in ("left", "right"):
            png = solid_png(k * 3 + (side == "right"))
            msg = TS.types["sensor_msgs/msg/CompressedImage"](header=ros_header(stamp + 30_000_000), format="png",
                                                              data=np.frombuffer(png, np.uint8))
            bag.write(f"/camera/{side}/image_raw/compressed", "sensor_msgs/msg/CompressedImage", msg,
                      stamp + 40_000_000)
            if side == "left":
                truth["images"].append(png)
    bag.close()
    if gt:
        gt_bag = BagWriter(folder / "2023-08-24-10-49-05_mavic2_gt.bag", compression)
        for k in range(SCANS):
            stamp = T0_NS + k * 100_000_000
            xyz = rng.normal(0, 4, 3)
            msg = TS.types["geometry_msgs/msg/PointStamped"](header=ros_header(stamp, "leica"),
                                                             point=TS.types["geometry_msgs/msg/Point"](*xyz))
            gt_bag.write("/leica/position", "geometry_msgs/msg/PointStamped", msg, stamp + 1_000_000)
            truth["gt"].append((ns_to_seconds(stamp), xyz))
        gt_bag.close()
    return truth


def write_nodes(path: Path, *, nodes: int = 4, messages: int = 30, starts: tuple[int, ...] = (),
                ends: tuple[int, ...] = (), rates: tuple[int, ...] = (), silent: int | None = None,
                offsets_ns: tuple[int, ...] = (), jitter_ns: int = 3_000_000,
                drop: dict[int, tuple[int, ...]] | None = None, seed: int = 0) -> list[np.ndarray]:
    """A bag of ``nodes`` mono S16LE ``audio_common_msgs/AudioData`` topics ``/audio1/audio`` ... (MMAUD V1's
    layout: no header stamps, placed in time only by receive times), 0.1 s messages on one sample clock.

    Node ``n`` sends messages ``starts[n]`` to ``ends[n]`` (defaults 0 and ``messages``) at ``rates[n]`` Hz
    (default :data:`FS`), received ``offsets_ns[n]`` late plus a jitter below ``jitter_ns`` drawn alike for
    every node; messages ``drop[n]`` are lost. Returns each node's samples (float, full scale 1) from its first
    message on.
    """
    rng = np.random.default_rng(seed)
    jitter = rng.integers(0, max(jitter_ns, 1), messages)
    bag = BagWriter(path, None)
    written = []
    for n in range(nodes):
        rate = rates[n] if rates else FS
        size = rate // 10
        first, last = (starts[n] if starts else 0), (ends[n] if ends else messages)
        codes = (rng.uniform(-0.3, 0.3, (last - first) * size) * 32768).astype("<i2")
        if n == silent:
            codes[:] = 0
        written.append(codes.astype(np.float64) / 32768)
        for k in range(first, last):
            if k in (drop or {}).get(n, ()):
                continue
            stamp = T0_NS + (k + 1) * 100_000_000 + int(jitter[k]) + (offsets_ns[n] if offsets_ns else 0)
            chunk = codes[(k - first) * size:(k - first + 1) * size]
            payload = TS.types["audio_common_msgs/msg/AudioData"](data=np.frombuffer(chunk.tobytes(), np.uint8))
            bag.write(f"/audio{n + 1}/audio", "audio_common_msgs/msg/AudioData", payload, stamp)
    bag.close()
    return written
