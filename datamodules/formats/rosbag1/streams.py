"""The LiDAR and camera topics of a bag as streams whose frames are read from the bag when indexed.

The opening pass keeps each message's log time (to find it again) and header stamp (its time);
a scan or an image is decoded only when asked for, so memory does not grow with the recording.
"""

from __future__ import annotations

import numpy as np

from datamodules.formats.ros_messages import pointcloud_to_arrays
from datamodules.formats.rosbag1.bag import LIVOX_TYPES, Bag, livox_points
from datamodules.recording import (
    EncodedImage,
    ImageStream,
    PointCloud,
    PointCloudStream,
    RecordingError,
    ns_to_seconds,
)


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
            if self._bag.standard_livox.get(self._msgtype):
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
