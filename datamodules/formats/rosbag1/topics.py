"""Which bag topic feeds each stream of a recording: the topic mapping and its defaults.

A mapping (dict or YAML file) names topics for the stream keys of :data:`STREAM_TYPES` and may carry
the audio parameters of :data:`PARAMETER_KEYS`; :func:`map_topics` completes it by message type and
MMAUD-like name hints (see the package docstring for the table of defaults).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from datamodules.formats.rosbag1.bag import (
    AUDIO_INFO_TYPE,
    AUDIO_TYPES,
    GROUND_TRUTH_TYPES,
    IMAGE_TYPES,
    LIDAR_TYPES,
)
from datamodules.recording import RecordingError

log = logging.getLogger(__package__)  # one logger for the format

STREAM_TYPES: dict[str, tuple[str, ...]] = {
    "audio": AUDIO_TYPES, "audio_info": (AUDIO_INFO_TYPE,), "mid360": LIDAR_TYPES, "avia": LIDAR_TYPES,
    "image": IMAGE_TYPES, "ground_truth": GROUND_TRUTH_TYPES,
}
PARAMETER_KEYS = ("sample_rate", "channels", "sample_format", "audio_stamp", "drone", "sequence_id", "mic_positions",
                  "nodes_share_clock")
#: per-node parameters an entry of an ``audio:`` list may carry beside its ``topic``
NODE_KEYS = ("topic", "sample_rate", "channels", "sample_format", "audio_stamp")
#: audio topics of separate nodes, found by themselves when a bag has several audio topics (MMAUD V1: /audio1/audio)
NODE_TOPIC = re.compile(r"^/?audio(\d+)/audio$")
LAYOUT_FILE = "aaute_layout.yaml"
DEFAULT_AUDIO_TOPIC = "/audio/audio"
#: name hints of each LiDAR (lower-case substrings of the topic)
LIDAR_HINTS = {"avia": ("avia",), "mid360": ("mid360", "mid_360", "360")}
#: Livox driver package -> the sensor it drives (the Mid-360 needs SDK 2 and livox_ros_driver2)
LIVOX_DRIVER_SENSOR = {"livox_ros_driver2/msg/CustomMsg": "mid360", "livox_ros_driver/msg/CustomMsg": "avia"}
GROUND_TRUTH_HINTS = ("leica", "ground_truth", "groundtruth", "gt")


def load_mapping(mapping: dict[str, Any] | str | Path | None, what: str) -> dict[str, Any]:
    """A topic mapping given as a dict or a YAML file (None: empty), its keys checked.

    Raises:
        RecordingError: unreadable YAML, not a mapping, or an unknown key.
    """
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


def audio_key(node: int, count: int) -> str:
    """The stream key of audio node ``node`` of ``count``: 'audio' alone, else 'audio[0]', 'audio[1]', ..."""
    return "audio" if count == 1 else f"audio[{node}]"


def audio_keys(topics: dict[str, str]) -> list[str]:
    """The audio stream keys of a topic mapping, in node (channel) order."""
    keys = [k for k in topics if k == "audio" or k.startswith("audio[")]
    return sorted(keys, key=lambda k: int(k[6:-1]) if k != "audio" else 0)


def audio_nodes(value: Any, where: str) -> list[dict[str, Any]]:
    """The mapping's ``audio:`` value as a list of nodes: a topic, a list of topics, or a list of
    ``{topic: ..., channels: ..., sample_rate: ...}`` entries (per-node parameters).

    Raises:
        RecordingError: an entry that is neither a topic nor such a mapping, or an unknown key.
    """
    entries = value if isinstance(value, list) else [value]
    if not entries:
        raise RecordingError(f"{where}: mapping audio: an empty list; name at least one topic (or audio: null)")
    nodes = []
    for entry in entries:
        node = {"topic": entry} if isinstance(entry, str) else entry
        if not isinstance(node, dict) or not isinstance(node.get("topic"), str):
            raise RecordingError(f"{where}: mapping audio: entry {entry!r} is neither a topic nor a mapping with "
                                 f"a topic (topic: /audio1/audio, channels: 1)")
        unknown = set(node) - set(NODE_KEYS)
        if unknown:
            raise RecordingError(f"{where}: mapping audio: entry for {node['topic']} has unknown key(s) "
                                 f"{sorted(unknown)}; expected {list(NODE_KEYS)}")
        nodes.append(dict(node))
    return nodes


def topic_list(types: dict[str, str], counts: dict[str, int]) -> str:
    """The bags' topics with their message types and counts, for error messages."""
    return "; ".join(f"{topic} ({msgtype}, {counts.get(topic, 0)} msgs)" for topic, msgtype in sorted(types.items()))


def _choose(candidates: list[str], hints: Sequence[str], exact: str | None = None) -> list[str]:
    """Candidates narrowed to the exact name, else to those containing a hint (unchanged if none do)."""
    if exact is not None and exact in candidates:
        return [exact]
    hinted = [t for t in candidates if any(h in t.lower() for h in hints)]
    return hinted or candidates


def _given_topics(types: dict[str, str], given: dict[str, Any], listing: str, where: str) -> dict[str, str]:
    """The topics the mapping names (``None`` drops a stream), each checked to exist and be of the right type."""
    chosen: dict[str, str] = {}
    requested: list[tuple[str, Any]] = []
    for key in STREAM_TYPES:
        if key not in given or given[key] is None:
            continue
        if key == "audio":
            nodes = audio_nodes(given[key], where)
            requested += [(audio_key(i, len(nodes)), node["topic"]) for i, node in enumerate(nodes)]
        else:
            requested.append((key, given[key]))
    for key, topic in requested:
        stream = "audio" if key.startswith("audio[") else key
        if topic not in types:
            raise RecordingError(f"{where}: mapping {stream}: {topic} names no topic of the bag(s); topics: {listing}")
        if types[topic] not in STREAM_TYPES[stream]:
            raise RecordingError(f"{where}: mapping {stream}: {topic} is {types[topic]}, expected one of "
                                 f"{list(STREAM_TYPES[stream])}; topics: {listing}")
        if topic in chosen.values():
            raise RecordingError(f"{where}: mapping names {topic} twice; each topic feeds one stream")
        chosen[key] = topic
    return chosen


def _lidar_candidates(types: dict[str, str], topics: list[str], free: list[str]
                      ) -> tuple[dict[str, list[str]], list[str]]:
    """LiDAR topics by the sensor their name (else their Livox driver) points to, for the sensors in ``free``.

    Returns the candidates of each free sensor and the topics that point to no sensor.
    """
    assigned: dict[str, list[str]] = {s: [] for s in free}
    unassigned = []
    for topic in topics:
        name = topic.lower()
        sensor = next((s for s in ("avia", "mid360") if any(h in name for h in LIDAR_HINTS[s])), None)
        sensor = sensor or LIVOX_DRIVER_SENSOR.get(types[topic])
        if sensor in assigned:
            assigned[sensor].append(topic)
        elif sensor is None:
            unassigned.append(topic)
    return assigned, unassigned


def map_topics(types: dict[str, str], counts: dict[str, int], given: dict[str, Any], where: str) -> dict[str, str]:
    """Which topic feeds each stream: the given mapping, completed by message type and name hints.

    Raises:
        RecordingError: a mapped topic is absent or of the wrong type, or a choice is ambiguous
            (the message lists the bags' topics).
    """
    listing = topic_list(types, counts)
    chosen = _given_topics(types, given, listing, where)

    def of_types(accepted: Sequence[str]) -> list[str]:
        return sorted(t for t, m in types.items() if m in accepted and t not in chosen.values())

    def choose_one(key: str, options: list[str]) -> None:
        if len(options) > 1:
            raise RecordingError(f"{where}: several topics could be {key} ({', '.join(options)}); name one in the "
                                 f"mapping ({key}: <topic>); topics: {listing}")
        if options:
            chosen[key] = options[0]

    if "audio" not in given:
        candidates = of_types(AUDIO_TYPES)
        nodes = sorted((t for t in candidates if NODE_TOPIC.match(t)), key=lambda t: int(NODE_TOPIC.match(t)[1]))
        if len(nodes) > 1:
            chosen.update({audio_key(i, len(nodes)): t for i, t in enumerate(nodes)})
        else:
            choose_one("audio", _choose(candidates, ("audio",), DEFAULT_AUDIO_TOPIC))
    keys = audio_keys(chosen)
    if "audio_info" not in given:
        for key in keys:
            options = of_types((AUDIO_INFO_TYPE,))
            namespace = chosen[key].rsplit("/", 1)[0] + "/"
            info_key = key.replace("audio", "audio_info", 1)
            if len(keys) == 1:
                choose_one(info_key, [t for t in options if t.startswith(namespace)] or options)
            else:  # several nodes: only an AudioInfo in the node's own namespace is its own
                choose_one(info_key, [t for t in options if t.startswith(namespace)])
    free = [s for s in ("avia", "mid360") if s not in given]
    assigned, unassigned = _lidar_candidates(types, of_types(LIDAR_TYPES), free)
    for sensor, options in assigned.items():
        choose_one(sensor, options)
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
        choose_one("ground_truth", _choose(of_types(GROUND_TRUTH_TYPES), GROUND_TRUTH_HINTS))
    return chosen
