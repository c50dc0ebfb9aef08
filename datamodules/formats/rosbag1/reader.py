"""The reader that assembles one :class:`~datamodules.recording.Recording` from the bags of a flight.

It resolves the bags and the topic mapping, opens the bags, maps their topics to streams
(:mod:`~datamodules.formats.rosbag1.topics`), makes the opening pass
(:mod:`~datamodules.formats.rosbag1.index`), and builds the audio
(:mod:`~datamodules.formats.rosbag1.audio`), LiDAR, camera (:mod:`~datamodules.formats.rosbag1.streams`)
and ground-truth streams from what that pass kept.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from datamodules.formats.node_audio import AudioNode, combine_nodes
from datamodules.formats.positions import parse_mic_positions
from datamodules.formats.rosbag1.audio import open_audio
from datamodules.formats.rosbag1.bag import LIDAR_TYPES, Bag
from datamodules.formats.rosbag1.index import BagIndex, index_bags
from datamodules.formats.rosbag1.streams import BagImages, BagPointClouds
from datamodules.formats.rosbag1.topics import (
    LAYOUT_FILE,
    STREAM_TYPES,
    audio_keys,
    audio_nodes,
    load_mapping,
    map_topics,
    topic_list,
)
from datamodules.recording import (
    DRONE_TYPES,
    AudioStream,
    ImageStream,
    PointCloudStream,
    Recording,
    RecordingError,
    Track,
    check_monotonic,
    check_track_values,
    count_gaps,
    json_safe,
    ns_to_seconds,
)

log = logging.getLogger(__package__)  # one logger for the format

FRAME = "lidar_sensor"
FRAME_DESCRIPTION = (
    "each LiDAR's own sensor frame as its driver published it (frame ids in meta['frame_ids']); "
    "ground truth in the frame of its topic (MMAUD V1: the Leica frame). No transform applied."
)


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
        mapping: topic mapping and parameters (dict or YAML file); see the package docstring.
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
    bag_paths, folder, folder_given = _recording_bags(paths)
    where = ", ".join(str(p) for p in bag_paths)
    arguments = {"sample_rate": sample_rate, "channels": channels, "sample_format": sample_format,
                 "audio_stamp": audio_stamp, "sequence_id": sequence_id, "drone": drone}
    options = _options(folder, mapping, arguments, where)

    bags = [Bag(p) for p in bag_paths]
    owner, types, counts = _topics_of(bags)
    topics = map_topics(types, counts, {k: v for k, v in options.items() if k in STREAM_TYPES}, where)
    _check_topics(topics, options, owner, types, counts, where)
    index = index_bags(bags, owner, topics)
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
    audio, audio_meta = _audio(owner, topics, index, options, where)
    meta.update(audio_meta)
    if audio is not None and options.get("mic_positions") is not None:
        audio.mic_positions = parse_mic_positions(options["mic_positions"], audio.num_channels,
                                                  f"{where} (mapping mic_positions)")
        meta["mic_positions_known"] = True
    lidar = _lidar(owner, topics, index)
    frames = _camera(owner, topics, index)
    ground_truth = _ground_truth(owner, topics, index)
    meta["gaps"] = _frame_gaps(lidar, frames, topics, where)
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


def _recording_bags(paths: str | Path | Sequence[str | Path]) -> tuple[list[Path], Path, bool]:
    """The bags of the recording, the folder they are in, and whether that folder was given."""
    if isinstance(paths, str | Path):
        bag_paths, folder = _bag_paths(Path(paths))
        return bag_paths, folder, Path(paths).is_dir()
    bag_paths = [Path(p) for p in paths]
    for p in bag_paths:
        if not p.is_file():
            raise RecordingError(f"{p}: no such bag file")
    return bag_paths, bag_paths[0].parent, False


def _options(folder: Path, mapping: dict[str, Any] | str | Path | None, arguments: dict[str, Any],
             where: str) -> dict[str, Any]:
    """The layout file beside the bags, overridden by the mapping, overridden by the arguments given (not None)."""
    options = load_mapping(folder / LAYOUT_FILE if (folder / LAYOUT_FILE).is_file() else None, where)
    options.update(load_mapping(mapping, where))
    options.update({key: value for key, value in arguments.items() if value is not None})
    return options


def _topics_of(bags: list[Bag]) -> tuple[dict[str, Bag], dict[str, str], dict[str, int]]:
    """The bag, message type and message count of every topic; bags of one recording share no topic."""
    owner: dict[str, Bag] = {}
    types: dict[str, str] = {}
    counts: dict[str, int] = {}
    for bag in bags:
        for topic, msgtype in bag.types.items():
            if topic in owner:
                raise RecordingError(f"topic {topic} appears in both {owner[topic].path} and {bag.path}; the bags "
                                     f"of one recording must not overlap (put each flight's bags in its own folder)")
            owner[topic], types[topic], counts[topic] = bag, msgtype, bag.counts[topic]
    return owner, types, counts


def _check_topics(topics: dict[str, str], options: dict[str, Any], owner: dict[str, Bag], types: dict[str, str],
                  counts: dict[str, int], where: str) -> None:
    """An audio topic is mapped (unless the mapping drops it), and every mapped topic holds messages."""
    if not audio_keys(topics) and not ("audio" in options and options["audio"] is None):
        raise RecordingError(f"{where}: no audio topic (audio_common_msgs AudioData or AudioDataStamped); topics: "
                             f"{topic_list(types, counts)}. Map one (audio: <topic>) or pass audio: null to "
                             f"read the other sensors alone")
    for key, topic in topics.items():
        if counts[topic] == 0:
            raise RecordingError(f"{owner[topic].path}: topic {topic} ({key}) holds no messages")


def _audio(owner: dict[str, Bag], topics: dict[str, str], index: BagIndex, options: dict[str, Any], where: str
           ) -> tuple[AudioStream | None, dict[str, Any]]:
    """The mapped audio topic(s) as one stream on a common clock (:func:`combine_nodes`), and its meta entries.

    Each node (topic) gets its own parameters (its entry of the ``audio:`` list, else the mapping's, else
    defaults: 4 channels for one topic, 1 per topic for several) and its own rate check, gap filling and t0.
    """
    keys = audio_keys(topics)
    if not keys:
        return None, {}
    given = options.get("audio")
    entries = audio_nodes(given, where) if given is not None else [{"topic": topics[k]} for k in keys]
    nodes, meta = [], {}
    for key, entry in zip(keys, entries, strict=True):
        topic = topics[key]
        if not index.audio_sounding.get(topic):
            raise RecordingError(f"{owner[topic].path}: audio node {topic} is silent (every sample is zero); a "
                                 f"dead microphone or driver: drop it from the mapping's audio: list")
        node_options = {k: v for k, v in options.items() if k in ("sample_rate", "channels", "sample_format",
                                                                    "audio_stamp")}
        if len(keys) > 1:
            node_options.setdefault("channels", 1)
        node_options.update({k: v for k, v in entry.items() if k != "topic"})
        info_key = key.replace("audio", "audio_info", 1)
        info_topic = topics.get(info_key)
        stream, node_meta = open_audio(owner[topic], topic, np.asarray(index.log_ns[topic], dtype=np.int64),
                                       np.asarray(index.stamp_ns[topic], dtype=np.int64),
                                       np.asarray(index.audio_bytes[topic], dtype=np.int64),
                                       index.audio_info.get(info_topic), info_topic, node_options)
        source = node_meta["audio_source"]
        nodes.append(AudioNode(topic, stream, source["t0_uncertainty_s"],
                               {**source, "gaps": node_meta["audio_gaps"],
                                "gap_seconds": node_meta["audio_gap_seconds"]}))
        meta = node_meta if not meta else {  # gaps add up over nodes; the first node's source stays as before
            **meta, "audio_gaps": meta["audio_gaps"] + node_meta["audio_gaps"],
            "audio_gap_seconds": meta["audio_gap_seconds"] + node_meta["audio_gap_seconds"]}
    for node in nodes:  # the nodes of one bag are read in one pass over its chunks
        node.stream.together = [n.name for n in nodes if owner[n.name] is owner[node.name]]
    audio, node_meta = combine_nodes(nodes, where, bool(options.get("nodes_share_clock", False)))
    meta.update(node_meta)
    return audio, meta


def _lidar(owner: dict[str, Bag], topics: dict[str, str], index: BagIndex) -> dict[str, PointCloudStream]:
    """The mapped LiDAR topics as streams read from the bags when indexed."""
    lidar: dict[str, PointCloudStream] = {}
    for sensor in ("mid360", "avia"):
        if sensor in topics:
            topic = topics[sensor]
            lidar[sensor] = BagPointClouds(owner[topic], topic, *index.stamps(topic, owner[topic]))
    return lidar


def _camera(owner: dict[str, Bag], topics: dict[str, str], index: BagIndex) -> BagImages | None:
    """The mapped camera topic as a stream read from the bag when indexed (None when none is mapped)."""
    if "image" not in topics:
        return None
    topic = topics["image"]
    return BagImages(owner[topic], topic, *index.stamps(topic, owner[topic]))


def _ground_truth(owner: dict[str, Bag], topics: dict[str, str], index: BagIndex) -> Track | None:
    """The ground-truth track the opening pass read (None when none is mapped); stamps increase, values finite."""
    if "ground_truth" not in topics:
        return None
    topic = topics["ground_truth"]
    stamps, xyz = index.track
    check_monotonic(ns_to_seconds(stamps), f"{owner[topic].path} {topic}")
    check_track_values(ns_to_seconds(stamps), xyz, None, f"{owner[topic].path} {topic}")
    return Track(ns_to_seconds(stamps), xyz)


def _frame_gaps(lidar: dict[str, PointCloudStream], frames: ImageStream | None, topics: dict[str, str],
                where: str) -> dict[str, int]:
    """Missing frames of each LiDAR and the camera (``meta["gaps"]``), with a warning where there are some."""
    gaps = {key: count_gaps(stream.timestamps) for key, stream in (*lidar.items(), ("image", frames))
            if stream is not None}
    for key, count in gaps.items():
        if count:
            log.warning("%s: %d gap(s) in %s (missing frames)", where, count, topics[key])
    return gaps


def open_rosbag1(path: str | Path, **options: Any) -> Recording:
    """Open a ``.bag`` file or a folder of bags (one recording) with :func:`read_rosbag1`."""
    return read_rosbag1(Path(path), **options)
