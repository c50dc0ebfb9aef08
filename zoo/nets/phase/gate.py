"""SRP-PHAT's per-sequence detection memory: confirmation, hold and fallback.

Windows arrive per sequence in time order. A detection counts when confirmed (the sequence's previous
detection lies within ``confirm_seconds`` and ``confirm_distance``); a window without a counted
detection holds the sequence's last one for ``hold_seconds``, then falls back to the mean of its counted
detections (``fallback: mean``) or the search region's centre (``fallback: centre``). A
:class:`SequenceMemory` per sequence keeps what that needs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

#: what an undetected window returns once the hold has expired
FALLBACKS = ("mean", "centre")
#: what each window of the last :meth:`DetectionGate.apply` returned: a counted detection, a held one, a fallback
STATES = ("detected", "held", "fallback")
#: a window's state as SRP-PHAT reports it (its ``state`` output holds indices into this): the gate's, or
#: ``uncorrected`` (nodes on separate clocks whose offsets were not corrected: no detection counts there)
WINDOW_STATES = (*STATES, "uncorrected")


@dataclass
class SequenceMemory:
    """What the gate remembers of one sequence."""

    time: float  #: the time of its latest window (s)
    last: torch.Tensor | None = None  #: its latest counted detection (3)
    last_time: float = -math.inf  #: that detection's time (s)
    total: torch.Tensor | float = 0.0  #: the sum of its counted detections
    count: int = 0  #: how many detections counted
    previous: tuple[float, torch.Tensor] | None = None  #: its latest detection, counted or not: (time, position)


class DetectionGate:
    """Confirmation, hold and fallback over the windows of each sequence (see the module docstring)."""

    def __init__(self, hold_seconds: float = 10.0, confirm_seconds: float = 0.0, confirm_distance: float = 5.0,
                 fallback: str = "mean"):
        """Args:
            hold_seconds: how long a sequence keeps its last detection before falling back.
            confirm_seconds, confirm_distance: a detection counts only when the sequence's previous one lies
                within ``confirm_seconds`` before it and ``confirm_distance`` (m) of it; 0 s: every one counts.
            fallback: after the hold, one of :data:`FALLBACKS`.
        """
        self.hold_seconds = float(hold_seconds)
        self.confirm_seconds, self.confirm_distance = float(confirm_seconds), float(confirm_distance)
        if fallback not in FALLBACKS:
            raise ValueError(f"srp_phat fallback must be one of {FALLBACKS}, got {fallback!r}")
        self.fallback = fallback
        self.sequences: dict[int, SequenceMemory] = {}  #: sequence index -> its memory
        self.states: list[str] = []  #: per window of the last :meth:`apply`, one of :data:`STATES`

    def apply(self, positions: torch.Tensor, detected: torch.Tensor, sequence: torch.Tensor | None,
              time: torch.Tensor | None, centre: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Positions (B x 3, NaN where not ``detected``) with the hold and fallback applied, and the
        detections that count (with ``confirm_seconds``, the confirmed ones). Windows of a sequence come in
        time order; a sequence whose time goes back starts afresh. Without ``sequence`` and ``time`` every
        window stands alone: undetected ones take ``centre`` (3)."""
        if sequence is None or time is None:
            self.states = ["detected" if hit else "fallback" for hit in detected.tolist()]
            return torch.where(detected[:, None], positions, centre), detected
        out, detected = positions.clone(), detected.clone()
        self.states = []
        for i, (seq, t) in enumerate(zip(sequence.tolist(), time.tolist(), strict=True)):
            memory = self.sequences.get(seq)
            if memory is None or t < memory.time:  # a new sequence, or the same one again from its start
                memory = self.sequences[seq] = SequenceMemory(time=t)
            memory.time = t
            if bool(detected[i]) and self.confirm_seconds > 0:
                previous, memory.previous = memory.previous, (t, positions[i])
                confirmed = previous is not None and t - previous[0] <= self.confirm_seconds and \
                    float(torch.linalg.vector_norm(positions[i] - previous[1])) <= self.confirm_distance
                detected[i] = confirmed
            if bool(detected[i]):
                memory.last, memory.last_time = positions[i], t
                memory.total, memory.count = memory.total + positions[i], memory.count + 1
                self.states.append("detected")
                continue
            held = memory.last is not None and t - memory.last_time <= self.hold_seconds
            if held:
                out[i] = memory.last
            elif memory.count and self.fallback == "mean":
                out[i] = memory.total / memory.count
            else:
                out[i] = centre
            self.states.append("held" if held else "fallback")
        return out, detected
