"""One audio topic of a bag rebuilt as an audio stream on its own sample clock.

The opening pass (:mod:`~datamodules.formats.rosbag1.index`) keeps each audio message's log time,
stamp and payload size; :func:`open_audio` takes those, resolves the audio parameters (AudioInfo,
else the mapping, else defaults), places the messages on one sample clock (:func:`layout_audio`,
dropped messages filled with zeros) and returns a :class:`BagAudio` that reads sample ranges from
the bag lazily. It knows nothing of the rest of the recording.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from datamodules.formats.ros_messages import SAMPLE_FORMATS, full_scale
from datamodules.formats.rosbag1.bag import AUDIO_TYPES, Bag, audio_payload
from datamodules.recording import (
    RATE_TOLERANCE,
    AudioStream,
    RecordingError,
    check_audio_rate,
    check_monotonic,
    ns_to_seconds,
)

log = logging.getLogger(__package__)  # one logger for the format

DEFAULT_AUDIO = {"sample_rate": 48000.0, "channels": 4, "sample_format": "S16LE", "audio_stamp": "end"}
RATE_MIN_MESSAGES = 10  #: audio messages needed to check the sample rate against the stamps
#: a lasting jump of the stamps against the sample clock longer than this many message durations is a gap
GAP_MESSAGES = 0.6
GAP_WINDOW = 10  #: messages over which receive-time jitter is discounted (future running minimum)


@dataclass
class AudioLayout:
    """Where each audio message's samples go on the rebuilt sample clock."""

    first: np.ndarray  #: sample index of each message's first sample
    t0: float
    gaps: int
    gap_samples: int
    rate_by_stamps: float | None = None
    notes: list[str] = field(default_factory=list)
    #: robust spread (1.4826 MAD) of the stamps about the sample clock: receive-time jitter
    jitter_s: float = 0.0
    #: how fast the sample clock runs against the stamps' clock (ppm), from a line through all stamps
    drift_ppm: float | None = None

    @property
    def t0_uncertainty_s(self) -> float:
        """Standard error of ``t0`` (the median of the stamps' offsets) from the jitter alone."""
        return float(1.2533 * self.jitter_s / np.sqrt(max(self.first.size, 1)))


def layout_audio(stamps_ns: np.ndarray, counts: np.ndarray, rate: float, stamp_at: str, what: str) -> AudioLayout:
    """Place audio messages on one sample clock, filling dropped messages with zeros.

    ``stamps_ns`` mark each message's first sample (``stamp_at='start'``) or the end of its last
    one ('end'). Receive-time jitter is discounted with a running minimum over the next
    :data:`GAP_WINDOW` messages: a delayed message is followed by punctual ones, whereas after a
    dropped message every stamp stays late. ``t0`` is the median offset of the stamps from the
    sample clock, in whole nanoseconds.

    Raises:
        RecordingError: the stamps disagree with ``rate`` by more than :data:`RATE_TOLERANCE`
            (checked from :data:`RATE_MIN_MESSAGES` messages on).
    """
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    counts = np.asarray(counts, dtype=np.int64)
    end = stamp_at == "end"
    measured = None
    steps_s = np.diff(stamps_ns) / 1e9
    spanned = counts[1:] if end else counts[:-1]  # samples between consecutive stamps
    usable = spanned > 0
    if usable.sum() >= RATE_MIN_MESSAGES:
        # the median step per sample ignores a few dropped messages and symmetric jitter
        measured = float(1.0 / np.median(steps_s[usable] / spanned[usable]))
        if abs(measured / rate - 1.0) > RATE_TOLERANCE:
            raise RecordingError(
                f"{what}: the message stamps advance at about {measured:.0f} samples/s but the sample rate is "
                f"{rate:g} Hz; give the right sample_rate (MMAUD code uses 46080 or 48000)"
            )
    starts = (stamps_ns - stamps_ns[0]) / 1e9 - (counts / rate if end else 0.0)  # relative: full precision
    cumulative = np.concatenate([[0], np.cumsum(counts)[:-1]])
    residual = starts - cumulative / rate
    padded = np.concatenate([residual, np.full(GAP_WINDOW - 1, np.inf)])
    floor = np.lib.stride_tricks.sliding_window_view(padded, GAP_WINDOW).min(axis=1)
    tolerance = GAP_MESSAGES * float(np.median(counts)) / rate
    steps = np.diff(floor)
    extra = np.zeros(counts.size, dtype=np.int64)
    jumps = steps > tolerance
    extra[1:][jumps] = np.rint(steps[jumps] * rate).astype(np.int64)
    first = cumulative + np.cumsum(extra)
    marked = first + counts if end else first
    offsets = stamps_ns - np.rint(marked * (1e9 / rate)).astype(np.int64)
    ordered = np.sort(offsets)
    median = ordered[(ordered.size - 1) // 2]
    t0 = float(ns_to_seconds(median))
    relative = (offsets - median) / 1e9  # s, full precision
    jitter = float(1.4826 * np.median(np.abs(relative)))
    drift = None
    if offsets.size >= RATE_MIN_MESSAGES and marked[-1] > marked[0]:
        drift = float(-np.polyfit(marked / rate, relative, 1)[0] * 1e6)
    return AudioLayout(first, t0, int(jumps.sum()), int(extra.sum()), measured, jitter_s=jitter, drift_ppm=drift)


class BagAudio(AudioStream):
    """Audio of a bag topic on one sample clock; messages are read from the bag for a range only."""

    def __init__(self, bag: Bag, topic: str, log_ns: np.ndarray, layout: AudioLayout, counts: np.ndarray,
                 rate: float, channels: int, sample_format: str):
        self._bag, self._topic, self._log_ns = bag, topic, log_ns
        self._first, self._counts = layout.first, counts
        self._stamped = bag.types[topic] == AUDIO_TYPES[1]
        self.sample_rate = float(rate)
        self.t0 = layout.t0
        self.num_samples = int(layout.first[-1] + counts[-1])
        self.mic_positions = np.zeros((channels, 3))
        self.sample_format = sample_format
        self._dtype = np.dtype(SAMPLE_FORMATS[sample_format])
        self._scale = full_scale(self._dtype)
        #: the other audio topics of the same bag, read in the same pass (see :meth:`Bag.messages_together`)
        self.together: list[str] = []

    def read(self, start: int, stop: int) -> np.ndarray:
        self._check_range(start, stop)
        out = np.zeros((self.num_channels, stop - start), dtype=np.float32)
        if stop == start:
            return out
        lo = max(int(np.searchsorted(self._first, start, side="right")) - 1, 0)
        hi = int(np.searchsorted(self._first, stop, side="left"))
        t_lo, t_hi = int(self._log_ns[lo]), int(self._log_ns[hi - 1])
        position = int(np.searchsorted(self._log_ns, t_lo, side="left"))
        if len(self.together) > 1:
            found = self._bag.messages_together(self._topic, t_lo, t_hi + 1, self.together)
        else:
            found = ((t, raw) for _, t, raw in self._bag.messages([self._topic], start=t_lo, stop=t_hi + 1))
        for _, raw in found:
            if position >= hi:
                break
            if position >= lo:
                block = self._decode(raw, position)
                first = int(self._first[position])
                a, b = max(start, first), min(stop, first + block.shape[1])
                if b > a:
                    out[:, a - start:b - start] = block[:, a - first:b - first]
            position += 1
        return out

    def _decode(self, raw: memoryview | bytes, position: int) -> np.ndarray:
        data = audio_payload(raw, self._stamped, f"{self._bag.path} {self._topic}[{position}]")
        samples = np.frombuffer(data, dtype=self._dtype).reshape(-1, self.num_channels).T
        block = samples.astype(np.float32) / np.float32(self._scale) if self._scale != 1.0 else \
            samples.astype(np.float32)
        if not np.isfinite(block).all():
            raise RecordingError(f"{self._bag.path} {self._topic}[{position}]: NaN or infinite audio samples")
        return block



def _parameters(info: Any, info_topic: str | None, options: dict[str, Any], what: str) -> tuple[dict[str, Any], str]:
    """Sample rate, channels and sample format from the AudioInfo message, else the options, else defaults.

    Returns them and where they came from (the AudioInfo topic, 'parameters' or 'defaults ...').

    Raises:
        RecordingError: the AudioInfo says the audio is not raw PCM, or disagrees with a given parameter.
    """
    given = {k: options[k] for k in ("sample_rate", "channels", "sample_format") if k in options}
    if info is None:
        params = {k: given.get(k, DEFAULT_AUDIO[k]) for k in ("sample_rate", "channels", "sample_format")}
        return params, "parameters" if given else "defaults (no AudioInfo topic)"
    coding = str(getattr(info, "coding_format", "") or "").lower()
    if coding not in ("", "wave", "wav", "raw", "pcm"):
        raise RecordingError(f"{what}: audio coded as {coding!r} ({info_topic}); only raw PCM "
                             f"('wave') audio can be read")
    from_info = {"sample_rate": float(info.sample_rate), "channels": int(info.channels),
                 "sample_format": str(info.sample_format).upper()}
    for key, value in given.items():
        if (float(value) if key == "sample_rate" else value) != from_info[key]:
            raise RecordingError(f"{what}: {key} {value!r} given but {info_topic} says {from_info[key]!r}")
    return from_info, info_topic


def _sample_counts(nbytes: np.ndarray, channels: int, fmt: str, what: str) -> np.ndarray:
    """Samples (per channel) of each message from its payload size; payloads must hold whole frames."""
    frame = channels * np.dtype(SAMPLE_FORMATS[fmt]).itemsize
    odd = np.flatnonzero(nbytes % frame)
    if odd.size:
        raise RecordingError(f"{what}: message {int(odd[0])} holds {int(nbytes[odd[0]])} bytes, not whole "
                             f"{channels}-channel {fmt} frames ({odd.size} such messages); check channels/format")
    counts = nbytes // frame
    if (counts == 0).any():
        log.warning("%s: %d empty audio message(s)", what, int((counts == 0).sum()))
    return counts


def open_audio(bag: Bag, topic: str, log_ns: np.ndarray, stamps_ns: np.ndarray, nbytes: np.ndarray, info: Any,
               info_topic: str | None, options: dict[str, Any]) -> tuple[BagAudio, dict[str, Any]]:
    """One audio topic on its own sample clock, and what the recording's meta says about it.

    Args:
        bag: the bag holding ``topic`` (an AudioData or AudioDataStamped topic).
        log_ns, stamps_ns, nbytes: per message, its log time, its stamp (header stamp, else log
            time) in ns and its payload size in bytes, as the opening pass found them.
        info: the topic's AudioInfo message, or None; ``info_topic`` is its topic.
        options: ``sample_rate``, ``channels``, ``sample_format`` (used without an AudioInfo, checked
            against one) and ``audio_stamp`` ('end', the default, or 'start').

    Returns:
        The stream and the meta entries ``audio_source``, ``audio_gaps`` and ``audio_gap_seconds``.

    Raises:
        RecordingError: unsupported parameters, payloads of partial frames, stamps that go back in
            time or disagree with the sample rate.
    """
    what = f"{bag.path} {topic}"
    params, source = _parameters(info, info_topic, options, what)
    rate, channels, fmt = float(params["sample_rate"]), int(params["channels"]), str(params["sample_format"])
    stamp_at = options.get("audio_stamp", DEFAULT_AUDIO["audio_stamp"])
    if fmt not in SAMPLE_FORMATS:
        raise RecordingError(f"{what}: audio sample format {fmt!r} not supported; expected one of "
                             f"{sorted(SAMPLE_FORMATS)}")
    if channels < 1 or rate <= 0:
        raise RecordingError(f"{what}: need at least one channel and a positive rate, got {channels} ch {rate} Hz")
    if stamp_at not in ("end", "start"):
        raise RecordingError(f"{what}: audio_stamp must be 'end' or 'start', got {stamp_at!r}")
    counts = _sample_counts(nbytes, channels, fmt, what)
    check_monotonic(ns_to_seconds(stamps_ns), what, strict=False)
    if counts.size > RATE_MIN_MESSAGES:
        # samples per second of stamps, all channels together: names a wrong channel count as such
        values = nbytes // np.dtype(SAMPLE_FORMATS[fmt]).itemsize
        check_audio_rate(values[1:] if stamp_at == "end" else values[:-1], np.diff(stamps_ns) / 1e9, rate,
                         channels, f"{what} ({source})")
    layout = layout_audio(stamps_ns, counts, rate, stamp_at, what)
    if layout.gaps:
        log.warning("%s: %d gap(s) in the audio (dropped messages?), %.3f s filled with zeros",
                    what, layout.gaps, layout.gap_samples / rate)
    meta = {
        "audio_source": {"topic": topic, "parameters_from": source, "stamp_marks": stamp_at,
                         "rate_by_stamps": layout.rate_by_stamps, "channels": channels, "sample_rate": rate,
                         "stamps": "header" if bag.types[topic] == AUDIO_TYPES[1] else "receive",
                         "messages": int(counts.size), "jitter_s": layout.jitter_s, "drift_ppm": layout.drift_ppm,
                         "t0": layout.t0, "t0_uncertainty_s": layout.t0_uncertainty_s},
        "audio_gaps": layout.gaps,
        "audio_gap_seconds": layout.gap_samples / rate,
    }
    return BagAudio(bag, topic, log_ns, layout, counts, rate, channels, fmt), meta
