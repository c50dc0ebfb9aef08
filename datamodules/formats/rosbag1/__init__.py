"""Reader of raw ROS 1 bags (MMAUD V1 is distributed as bz2-compressed ROS 1 bags, ground truth apart).

Needs the optional ``rosbags`` package (``pip install .[rosbag]``), imported only when a bag is opened.

Topics and message types are discovered from the bag itself: a ROS 1 bag stores the full message
definition of every connection, and a typestore is built from those (so Livox ``CustomMsg`` needs
no installed package). Topics are mapped to the recording by message type, with MMAUD-like name
hints where a type is ambiguous:

==============  ==========================================================  =============================
mapping key     message types                                               default choice
==============  ==========================================================  =============================
audio           audio_common_msgs AudioData / AudioDataStamped             every /audioN/audio (nodes, in N
                                                                            order), else the only one, else
                                                                            /audio/audio
audio_info      audio_common_msgs AudioInfo                                 beside each audio topic (one
                                                                            topic: else the only one)
mid360, avia    livox_ros_driver(2) CustomMsg, sensor_msgs PointCloud2     'avia' / 'mid360' / '360' in the
                                                                            name, else livox_ros_driver2 =
                                                                            Mid-360, livox_ros_driver = Avia
image           sensor_msgs CompressedImage                                 the only one, else 'left'
ground_truth    geometry_msgs PointStamped / PoseStamped                    the only one, else 'leica'/'gt'
==============  ==========================================================  =============================

A ``mapping`` (dict, or a YAML file with the same keys; ``aaute_layout.yaml`` beside the bags is
read too) overrides any of these (``None`` drops a stream) and may carry the audio parameters
``sample_rate``, ``channels``, ``sample_format``, ``audio_stamp``, ``drone``/``sequence_id``, the
microphone positions ``mic_positions`` (one ``[x, y, z]`` in metres per channel, in channel order;
without them ``meta["mic_positions_known"]`` is false and phase models refuse the recording) and
``nodes_share_clock`` (true when the audio nodes sample on one clock).

Several audio nodes (MMAUD V1 records four mono ``/audioN/audio`` topics without header stamps):
``audio:`` takes a list of topics, or of ``{topic, channels, sample_rate, sample_format,
audio_stamp}`` entries, one per node, channels in list order (default 1 channel per node). Each
node is rebuilt on its own sample clock as below, then all are put on one clock by their stamps
(:mod:`datamodules.formats.node_audio`): ``meta["audio_nodes"]`` keeps each node's provenance
(topic, rate, stamp jitter, drift, gaps), ``meta["audio_alignment_uncertainty_s"]`` what the
stamps leave uncertain, ``meta["nodes_share_clock"]`` whether the nodes share a clock.
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

The package: :mod:`.bag` (one bag file, message types, raw layouts), :mod:`.topics` (the topic
mapping), :mod:`.index` (the opening pass), :mod:`.audio` (one audio topic on its sample clock),
:mod:`.streams` (LiDAR and camera streams) and :mod:`.reader` (:func:`read_rosbag1`, which
assembles the recording).
"""

from datamodules.formats.rosbag1.audio import AudioLayout, BagAudio, layout_audio, open_audio
from datamodules.formats.rosbag1.bag import Bag, MissingDependencyError, livox_points
from datamodules.formats.rosbag1.reader import open_rosbag1, read_rosbag1
from datamodules.formats.rosbag1.streams import BagImages, BagPointClouds
from datamodules.formats.rosbag1.topics import map_topics

__all__ = [
    "AudioLayout",
    "Bag",
    "BagAudio",
    "BagImages",
    "BagPointClouds",
    "MissingDependencyError",
    "layout_audio",
    "livox_points",
    "map_topics",
    "open_audio",
    "open_rosbag1",
    "read_rosbag1",
]
