"""Audio of several microphone nodes, each recorded as its own stream, on one common clock.

A real rig (MMAUD's has four audio nodes) may record each node as its own stream: one ROS topic per
node, its samples placed in time only by its messages' stamps (often receive times). Each node
stream arrives here already on its own sample clock (its ``t0`` from its stamps, its gaps filled);
:func:`combine_nodes` puts them on one time axis: the common span is where every node has audio
(the latest start to the earliest end; what is trimmed is warned about, naming the node), and
each node is shifted by the whole number of samples that brings its ``t0`` nearest the common one.

What the stamps cannot tell is reported, not hidden: ``audio_alignment_uncertainty_s`` is the
largest standard uncertainty of the time difference between two nodes that the stamps leave
(each node's ``t0`` error from its jitter, plus the rounding to whole samples). A constant
difference of latency between nodes (driver buffering, separate clocks) is invisible to the
stamps; ``nodes_share_clock`` says whether the rig's nodes sample on one clock (false unless the
mapping says so), and a localiser that uses time differences between nodes must calibrate them.

Bad input, each naming the node: nodes at different sample rates (an error), a node that is
silent (an error), nodes whose spans differ by more than :data:`LENGTH_TOLERANCE_S` (a warning).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from itertools import combinations
from typing import Any

import numpy as np

from datamodules.recording import AudioStream, RecordingError

log = logging.getLogger(__name__)

#: nodes whose audio starts or ends further apart than this are trimmed with a warning (s)
LENGTH_TOLERANCE_S = 0.2


@dataclass
class AudioNode:
    """One node's audio stream on its own sample clock and what its stamps said of it."""

    name: str  #: the node's source (a topic, a file)
    stream: AudioStream
    t0_uncertainty_s: float = 0.0  #: standard error of the stream's t0 from its stamps
    provenance: dict[str, Any] | None = None  #: topic, rate, stamp statistics


class NodeAudio(AudioStream):
    """Several node streams of one sample rate, each shifted by whole samples onto one clock; channels stacked
    in node order."""

    def __init__(self, nodes: list[AudioNode], shifts: list[int], num_samples: int, t0: float):
        self.nodes, self.shifts = nodes, shifts
        self.sample_rate = float(nodes[0].stream.sample_rate)
        self.t0 = float(t0)
        self.num_samples = int(num_samples)
        self.mic_positions = np.concatenate([n.stream.mic_positions for n in nodes]).astype(np.float64)
        formats = {n.stream.sample_format for n in nodes}
        self.sample_format = formats.pop() if len(formats) == 1 else None

    def read(self, start: int, stop: int) -> np.ndarray:
        self._check_range(start, stop)
        return np.concatenate([n.stream.read(start + s, stop + s) for n, s in zip(self.nodes, self.shifts,
                                                                                  strict=True)])


def combine_nodes(nodes: list[AudioNode], where: str, share_clock: bool = False
                  ) -> tuple[AudioStream, dict[str, Any]]:
    """The nodes' audio on one common clock, and the recording's meta entries about it.

    Args:
        nodes: the node streams in channel order (one node: returned unchanged).
        where: the recording, for messages.
        share_clock: the nodes sample on one clock (the mapping's ``nodes_share_clock``).

    Returns:
        The stream and ``audio_nodes`` (per node: name, channels, rate, t0, shift, span and its
        provenance), ``audio_alignment_uncertainty_s`` and ``nodes_share_clock``.

    Raises:
        RecordingError: nodes at different sample rates, or with no common span.
    """
    rates = {n.name: float(n.stream.sample_rate) for n in nodes}
    if len(set(rates.values())) > 1:
        listing = ", ".join(f"{name} {rate:g} Hz" for name, rate in rates.items())
        raise RecordingError(f"{where}: the audio nodes have different sample rates ({listing}); give each node's "
                             f"sample_rate in the mapping's audio: list, or resample the odd node first")
    rate = next(iter(rates.values()))
    start = max(n.stream.t0 for n in nodes)
    end = min(n.stream.t_end for n in nodes)
    if end <= start:
        spans = ", ".join(f"{n.name} {n.stream.t0:.3f}-{n.stream.t_end:.3f} s" for n in nodes)
        raise RecordingError(f"{where}: the audio nodes share no time span ({spans}); are they of one flight?")
    rows, shifts, errors = [], [], []
    for node in nodes:
        shift = int(np.rint((start - node.stream.t0) * rate))
        rounding = node.stream.t0 + shift / rate - start
        trimmed = (start - node.stream.t0, node.stream.t_end - end)
        if len(nodes) > 1 and max(trimmed) > LENGTH_TOLERANCE_S:
            log.warning("%s: audio node %s spans %.3f-%.3f s; %.3f s at the start and %.3f s at the end lie "
                        "outside the other nodes' audio and are left out", where, node.name, node.stream.t0,
                        node.stream.t_end, *trimmed)
        shifts.append(shift)
        errors.append(float(np.hypot(node.t0_uncertainty_s, rounding)))
        rows.append({"name": node.name, "channels": node.stream.num_channels, "sample_rate": rate,
                     "t0": node.stream.t0, "shift_samples": shift, "duration_s": node.stream.duration,
                     "trimmed_s": [max(t, 0.0) for t in trimmed], **(node.provenance or {})})
    num_samples = min(n.stream.num_samples - s for n, s in zip(nodes, shifts, strict=True))
    uncertainty = max((float(np.hypot(a, b)) for a, b in combinations(errors, 2)), default=0.0)
    meta = {"audio_nodes": rows, "audio_alignment_uncertainty_s": uncertainty,
            "nodes_share_clock": bool(share_clock or len(nodes) == 1)}
    if len(nodes) == 1:
        return nodes[0].stream, meta
    return NodeAudio(nodes, shifts, num_samples, start + 0.0), meta


def warn_unshared_clocks(meta: dict[str, Any], where: str, use: str) -> bool:
    """Warn (and say so) when ``use`` takes time differences between audio nodes that do not share a clock.

    Called when the offsets between node clocks are not calibrated (the DataModule's ``clock_calibration:
    off``, :mod:`datamodules.features.clock_calibration`): each 1 ms between two nodes moves their time
    difference by 0.35 m of path, which costs a steering localiser metres (README: clock sensitivity).
    """
    if meta.get("nodes_share_clock", True) is not False:
        return False
    uncertainty = meta.get("audio_alignment_uncertainty_s")
    stamps = "unknown" if uncertainty is None else f"{1e3 * float(uncertainty):.2f} ms from the stamps alone"
    log.warning("%s: %s uses time differences between audio nodes on separate clocks (alignment uncertainty %s; "
                "constant offsets between the nodes are not calibrated)", where, use, stamps)
    return True
