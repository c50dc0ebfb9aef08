"""ROS 2 message definitions used by the canonical MCAP layout, and numpy <-> message payloads.

The definitions are the standard ``sensor_msgs``, ``geometry_msgs``, ``std_msgs`` and
``audio_common_msgs`` ones (as concatenated message definitions, the form MCAP's ``ros2msg``
schema encoding carries), so Foxglove, the ``mcap`` CLI and ROS 2 tools can open the files.
One project schema, ``aaute_msgs/msg/TrackQuality``, carries per-label quality of a track.
"""

from __future__ import annotations

import numpy as np

_SEP = "\n" + "=" * 80 + "\n"
_HEADER = "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id"
_TIME = "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec"

MSGDEFS: dict[str, str] = {
    "audio_common_msgs/msg/AudioDataStamped": _SEP.join(
        ["std_msgs/Header header\naudio_common_msgs/AudioData audio", _HEADER, _TIME,
         "MSG: audio_common_msgs/AudioData\nuint8[] data"]
    ),
    "audio_common_msgs/msg/AudioInfo": (
        "uint8 channels\nuint32 sample_rate\nstring sample_format\nuint32 bitrate\nstring coding_format"
    ),
    "sensor_msgs/msg/PointCloud2": _SEP.join(
        [
            "std_msgs/Header header\nuint32 height\nuint32 width\nsensor_msgs/PointField[] fields\n"
            "bool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense",
            _HEADER, _TIME,
            "MSG: sensor_msgs/PointField\nuint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\n"
            "uint8 INT32=5\nuint8 UINT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\n"
            "string name\nuint32 offset\nuint8 datatype\nuint32 count",
        ]
    ),
    "sensor_msgs/msg/CompressedImage": _SEP.join(
        ["std_msgs/Header header\nstring format\nuint8[] data", _HEADER, _TIME]
    ),
    "geometry_msgs/msg/PointStamped": _SEP.join(
        ["std_msgs/Header header\ngeometry_msgs/Point point", _HEADER, _TIME,
         "MSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z"]
    ),
    "aaute_msgs/msg/TrackQuality": _SEP.join(
        ["std_msgs/Header header\nbool valid\nstring[] names\nfloat64[] values", _HEADER, _TIME]
    ),
}

#: sensor_msgs/PointField datatype codes -> numpy dtypes (little-endian)
POINT_FIELD_DTYPES = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}
_DTYPE_CODES = {np.dtype(v).str.lstrip("<|"): k for k, v in POINT_FIELD_DTYPES.items()}

#: audio sample formats (audio_common_msgs/AudioInfo.sample_format) -> numpy dtypes
SAMPLE_FORMATS = {"S16LE": "<i2", "S32LE": "<i4", "F32LE": "<f4"}


def full_scale(dtype: np.dtype | str) -> float:
    """The value of a full-scale sample: 1 for float samples, 2 ** (bits - 1) for signed integers."""
    dtype = np.dtype(dtype)
    return 1.0 if dtype.kind == "f" else 2.0 ** (8 * dtype.itemsize - 1)


def header(stamp_ns: int, frame_id: str = "") -> dict:
    """A ``std_msgs/Header`` as a dict for the CDR encoder."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": frame_id}


def stamp_ns(msg_header) -> int:
    """Nanoseconds of a decoded ``std_msgs/Header`` (ROS 1 or ROS 2 style)."""
    stamp = msg_header.stamp
    if hasattr(stamp, "nanosec"):
        return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nsec)


def pointcloud_fields(fields: dict[str, np.ndarray]) -> tuple[list[dict], int, bytes]:
    """Pack named per-point arrays into PointCloud2 ``fields``, ``point_step`` and ``data``."""
    dtype = np.dtype([(name, np.asarray(values).dtype.newbyteorder("<")) for name, values in fields.items()])
    packed = np.empty(len(next(iter(fields.values()))), dtype=dtype)
    for name, values in fields.items():
        packed[name] = values
    descriptors = []
    for name in dtype.names:
        sub, offset = dtype.fields[name][:2]
        code = _DTYPE_CODES.get(sub.str.lstrip("<|"))
        if code is None:
            raise ValueError(f"point field {name!r} has dtype {sub} that PointCloud2 cannot hold")
        descriptors.append({"name": name, "offset": int(offset), "datatype": code, "count": 1})
    return descriptors, dtype.itemsize, packed.tobytes()


def pointcloud_to_arrays(msg, what: str) -> dict[str, np.ndarray]:
    """Unpack a decoded PointCloud2 into named arrays (one value per point)."""
    if getattr(msg, "is_bigendian", False):
        raise ValueError(f"{what}: big-endian PointCloud2 is not supported")
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if f.datatype not in POINT_FIELD_DTYPES or int(getattr(f, "count", 1)) != 1:
            continue  # skip field types we do not use (e.g. arrays)
        names.append(f.name)
        formats.append(POINT_FIELD_DTYPES[f.datatype])
        offsets.append(f.offset)
    point_step = int(msg.point_step)
    count = int(msg.width) * int(msg.height)
    data = bytes(msg.data)
    if point_step <= 0 or len(data) < count * point_step:
        raise ValueError(
            f"{what}: PointCloud2 holds {len(data)} bytes for {count} points of {point_step} bytes"
        )
    if int(msg.height) > 1 and int(msg.row_step) != int(msg.width) * point_step:
        rows = np.frombuffer(data, np.uint8).reshape(int(msg.height), int(msg.row_step))
        data = rows[:, : int(msg.width) * point_step].tobytes()
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})
    packed = np.frombuffer(data, dtype=dtype, count=count)
    return {name: np.ascontiguousarray(packed[name]) for name in names}
