"""The ROS 1 bag reader, on bags written at test time by rosbags' own writer."""

from __future__ import annotations

import io
import logging
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from datamodules.formats import discover_recordings, open_recording
from datamodules.formats.mcap_file import read_mcap
from datamodules.recording import RecordingError, ns_to_seconds

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


def _header(ns: int, frame: str = "", seq: int = 0):
    sec, nsec = divmod(ns, 1_000_000_000)
    stamp = TS.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    return TS.types["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame)


def _png(value: int) -> bytes:
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
                msg = TS.types["audio_common_msgs/msg/AudioDataStamped"](header=_header(stamp, "mics"), audio=payload)
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
        msg = TS.types["livox_ros_driver/msg/CustomMsg"](header=_header(stamp, "livox_frame", k), timebase=stamp,
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
            header=_header(stamp, "mid360_frame"), height=1, width=m,
            fields=[field(name=n, offset=4 * i, datatype=7, count=1)
                    for i, n in enumerate(("x", "y", "z", "intensity"))],
            is_bigendian=False, point_step=16, row_step=16 * m, data=np.frombuffer(cloud.tobytes(), np.uint8),
            is_dense=True)
        bag.write(mid360_topic, "sensor_msgs/msg/PointCloud2", msg, stamp + 15_000_000)
        truth["mid360"].append((ns_to_seconds(stamp), np.column_stack([cloud["x"], cloud["y"], cloud["z"]]),
                                cloud["intensity"]))
        for side in ("left", "right"):
            png = _png(k * 3 + (side == "right"))
            msg = TS.types["sensor_msgs/msg/CompressedImage"](header=_header(stamp + 30_000_000), format="png",
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
            msg = TS.types["geometry_msgs/msg/PointStamped"](header=_header(stamp, "leica"),
                                                             point=TS.types["geometry_msgs/msg/Point"](*xyz))
            gt_bag.write("/leica/position", "geometry_msgs/msg/PointStamped", msg, stamp + 1_000_000)
            truth["gt"].append((ns_to_seconds(stamp), xyz))
        gt_bag.close()
    return truth


def assert_matches(rec, truth: dict) -> None:
    assert rec.audio.num_channels == CHANNELS and rec.audio.sample_rate == FS
    assert rec.audio.t0 == ns_to_seconds(T0_NS)  # stamps mark the end of each 0.1 s message
    assert np.array_equal(rec.audio.read(0, rec.audio.num_samples), truth["audio"].astype(np.float32))
    for sensor in ("avia", "mid360"):
        clouds = rec.lidar[sensor]
        assert np.array_equal(clouds.timestamps, [t for t, _, _ in truth[sensor]])  # header stamps, not log times
        for i in reversed(range(len(clouds))):  # random access
            _, xyz, intensity = truth[sensor][i]
            assert np.array_equal(clouds[i].points, xyz) and np.array_equal(clouds[i].intensity, intensity)
    assert [rec.frames[i].data for i in range(len(rec.frames))] == truth["images"]
    assert rec.frames[0].format == "png"
    assert np.array_equal(rec.ground_truth.timestamps, [t for t, _ in truth["gt"]])
    assert np.array_equal(rec.ground_truth.xyz, np.array([x for _, x in truth["gt"]]))


@pytest.mark.parametrize("compression", [None, "BZ2", "LZ4"])
def test_flight_bags_read_into_one_recording(tmp_path, compression, caplog):
    truth = write_flight(tmp_path / "mavic2_flight", compression)
    with caplog.at_level(logging.WARNING, logger="datamodules.formats.rosbag1"):
        rec = open_recording(tmp_path / "mavic2_flight")
    assert rec.sequence_id == "mavic2_flight" and rec.drone == "mavic2"
    assert rec.meta["source_format"] == "rosbag1" and rec.meta["audio_source"]["parameters_from"] == "/audio/audio_info"
    assert rec.meta["topics"] == {"audio": "/audio/audio", "audio_info": "/audio/audio_info", "avia": "/livox/avia",
                                  "mid360": "/livox/lidar_360", "image": "/camera/left/image_raw/compressed",
                                  "ground_truth": "/leica/position"}
    assert rec.meta["frame_ids"] == {"avia": "livox_frame", "mid360": "mid360_frame", "image": ""}
    assert rec.meta["audio_gaps"] == 0
    assert any("several camera topics" in r.getMessage() for r in caplog.records)
    assert_matches(rec, truth)


def test_converts_to_mcap_and_info(tmp_path, capsys):
    from datamodules.cli import main
    from datamodules.convert import convert

    truth = write_flight(tmp_path / "flight", "BZ2")
    (written,) = convert(tmp_path / "flight", tmp_path / "out")
    assert written.name == "flight.mcap"
    back = read_mcap(written)
    assert_matches(back, truth)
    assert back.audio.sample_format == "S16LE" and back.meta["source_format"] == "rosbag1"
    assert main(["info", str(tmp_path / "flight")]) == 0
    row = capsys.readouterr().out.splitlines()[2]
    assert "rosbag1" in row and "4ch 48000Hz 3.0s" in row and f"{SCANS} @10.0Hz" in row


def test_unstamped_audio_with_parameters_and_a_dropped_message(tmp_path, caplog):
    truth = write_flight(tmp_path / "f", audio="plain", info=False, drop=(12,), sample_format="S32LE", channels=3,
                         lidar=False, gt=False)
    with caplog.at_level(logging.WARNING, logger="datamodules.formats.rosbag1"):
        rec = open_recording(tmp_path / "f", channels=3, sample_format="S32LE")
    audio = rec.audio
    assert audio.num_channels == 3 and audio.sample_format == "S32LE" and audio.num_samples == 30 * MSG
    assert rec.meta["audio_gaps"] == 1 and rec.meta["audio_gap_seconds"] == pytest.approx(0.1)
    assert any("1 gap(s) in the audio" in r.getMessage() for r in caplog.records)
    samples = audio.read(0, audio.num_samples)
    expected = truth["audio"].astype(np.float32)
    expected[:, 12 * MSG:13 * MSG] = 0.0
    assert np.array_equal(samples, expected)
    with pytest.raises(RecordingError, match=r"advance at about 48000 samples/s but the sample rate is 46080"):
        open_recording(tmp_path / "f", channels=3, sample_format="S32LE", sample_rate=46080)
    with pytest.raises(RecordingError, match=r"not whole 7-channel S32LE frames"):
        open_recording(tmp_path / "f", channels=7, sample_format="S32LE")


def test_bag_without_audio(tmp_path):
    write_flight(tmp_path / "f", audio="", gt=False)
    with pytest.raises(RecordingError, match=r"no audio topic.*topics: .*/livox/avia \(livox_ros_driver/msg/CustomMsg, "
                                             rf"{SCANS} msgs\)"):
        open_recording(tmp_path / "f")
    rec = open_recording(tmp_path / "f", mapping={"audio": None})
    assert rec.audio is None and len(rec.lidar["avia"]) == SCANS and rec.ground_truth is None


def test_mapping_from_yaml_and_its_errors(tmp_path):
    write_flight(tmp_path / "f", gt=False)
    mapping = tmp_path / "topics.yaml"
    mapping.write_text("image: /camera/right/image_raw/compressed\nmid360: null\nsample_rate: 48000\n")
    rec = open_recording(tmp_path / "f", mapping=mapping)
    assert "mid360" not in rec.lidar and rec.frames[0].data == _png(1)
    mapping.write_text("avia: /livox/lidar\n")
    with pytest.raises(RecordingError, match=r"avia: /livox/lidar names no topic.*/livox/avia \(livox_ros_driver"):
        open_recording(tmp_path / "f", mapping=mapping)
    with pytest.raises(RecordingError, match=r"/audio/audio_info is audio_common_msgs/msg/AudioInfo, expected one of"):
        open_recording(tmp_path / "f", mapping={"avia": "/audio/audio_info"})
    with pytest.raises(RecordingError, match=r"unknown mapping key\(s\) \['lidar'\]"):
        open_recording(tmp_path / "f", mapping={"lidar": "/livox/avia"})
    (tmp_path / "f" / "aaute_layout.yaml").write_text("sample_rate: 44100\n")  # read from the bags' folder
    with pytest.raises(RecordingError, match=r"sample_rate 44100 given but /audio/audio_info says 48000"):
        open_recording(tmp_path / "f")


def test_bags_of_two_flights_in_one_folder_are_refused(tmp_path):
    write_flight(tmp_path / "a", gt=False)
    write_flight(tmp_path / "b", gt=False, seed=1)
    (tmp_path / "b" / "2023-08-24-10-49-05_mavic2.bag").rename(tmp_path / "a" / "other.bag")
    with pytest.raises(RecordingError, match=r"topic /\S+ appears in both .*\(put each flight's bags in its own"):
        open_recording(tmp_path / "a")
    assert discover_recordings(tmp_path) == [tmp_path / "a"]


def test_non_monotonic_header_stamps(tmp_path):
    folder = tmp_path / "f"
    folder.mkdir()
    bag = BagWriter(folder / "x.bag", None)
    for k, stamp in enumerate((3, 2, 4)):
        msg = TS.types["geometry_msgs/msg/PointStamped"](header=_header(T0_NS + stamp * 10**8),
                                                         point=TS.types["geometry_msgs/msg/Point"](1.0, 2.0, 3.0))
        bag.write("/leica/position", "geometry_msgs/msg/PointStamped", msg, T0_NS + k)
    bag.close()
    with pytest.raises(RecordingError, match=r"x\.bag /leica/position: timestamps must increase"):
        open_recording(folder / "x.bag", mapping={"audio": None})


def test_corrupt_and_missing_package(tmp_path, monkeypatch):
    (tmp_path / "broken.bag").write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 64)
    with pytest.raises(RecordingError, match=r"broken\.bag: not a readable ROS 1 bag"):
        open_recording(tmp_path / "broken.bag")
    monkeypatch.setitem(sys.modules, "rosbags.rosbag1", None)
    from datamodules.formats.rosbag1 import MissingDependencyError

    with pytest.raises(MissingDependencyError, match=r"pip install \.\[rosbag\]"):
        open_recording(tmp_path / "broken.bag")
