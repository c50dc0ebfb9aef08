"""The opening pass over a recording's bags: the few numbers per message the streams need.

Bags are sequential and compressed in chunks, so one pass over the mapped topics' messages is the
only way to learn the audio messages' sizes and the sensors' header stamps. It keeps per topic the
log times and stamps, the audio payload sizes, the first AudioInfo message, each sensor's frame id,
and the (small) ground-truth track.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from datamodules.formats.ros_messages import stamp_ns
from datamodules.formats.rosbag1.bag import AUDIO_TYPES, Bag, audio_payload, raw_header
from datamodules.recording import check_monotonic, ns_to_seconds


@dataclass
class BagIndex:
    """What the opening pass keeps: per topic log times and stamps, audio sample counts, the track."""

    log_ns: dict[str, list[int]] = field(default_factory=dict)
    stamp_ns: dict[str, list[int]] = field(default_factory=dict)
    audio_bytes: dict[str, list[int]] = field(default_factory=dict)  #: per audio topic, each message's sample bytes
    audio_sounding: dict[str, bool] = field(default_factory=dict)  #: per audio topic, whether any sample is not 0
    audio_info: dict[str, Any] = field(default_factory=dict)  #: first message of each AudioInfo topic
    frame_ids: dict[str, str] = field(default_factory=dict)
    track: tuple[np.ndarray, np.ndarray] = (np.zeros(0, np.int64), np.zeros((0, 3)))

    def stamps(self, topic: str, bag: Bag) -> tuple[np.ndarray, np.ndarray]:
        """Log times and header stamps (ns) of the messages of ``topic``; the stamps must increase."""
        log_ns = np.asarray(self.log_ns[topic], dtype=np.int64)
        stamps = np.asarray(self.stamp_ns[topic], dtype=np.int64)
        check_monotonic(ns_to_seconds(stamps), f"{bag.path} {topic} (header stamps)")
        return log_ns, stamps


def index_bags(bags: list[Bag], owner: dict[str, Bag], topics: dict[str, str]) -> BagIndex:
    """One pass over the messages of the mapped ``topics`` (stream key -> topic) in each bag (``owner[topic]``)."""
    index = BagIndex()
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
            if key.startswith("audio_info"):
                if topic not in index.audio_info:
                    index.audio_info[topic] = bag.deserialize(raw, msgtype, what)
                continue
            if key == "audio" or key.startswith("audio["):
                stamped = msgtype == AUDIO_TYPES[1]
                data = audio_payload(raw, stamped, what)
                index.stamp_ns.setdefault(topic, []).append(raw_header(raw, what)[0] if stamped else log_ns)
                index.audio_bytes.setdefault(topic, []).append(len(data))
                if not index.audio_sounding.get(topic):
                    index.audio_sounding[topic] = bool(np.frombuffer(data, np.uint8).any())
                continue
            if key == "ground_truth":
                msg = bag.deserialize(raw, msgtype, what)
                point = msg.point if hasattr(msg, "point") else msg.pose.position
                gt_stamps.append(stamp_ns(msg.header))
                gt_xyz.append((float(point.x), float(point.y), float(point.z)))
                continue
            if with_header[topic]:
                stamp, frame_id, _ = raw_header(raw, what)
                index.frame_ids.setdefault(key, frame_id)
            else:
                stamp = log_ns
            index.stamp_ns.setdefault(topic, []).append(stamp)
    index.track = (np.asarray(gt_stamps, dtype=np.int64), np.asarray(gt_xyz, dtype=np.float64).reshape(-1, 3))
    return index
