"""Pseudo-label recordings on disk: find them, run the teacher (in parallel), store the tracks.

Used by ``aaute label``. Each recording is one job (one process with ``workers > 1``); a failing
recording is reported and leaves its file untouched, the others go on; a write-protected recording
is refused before its teacher runs. Tracks are stored beside
the sensor data atomically: MCAP recordings get their ``/pseudo_label`` topic replaced
(:func:`~datamodules.formats.mcap_file.replace_track`); other layouts are refused with a pointer
to ``aaute convert``.
"""

from __future__ import annotations

import functools
import logging
import os
import stat
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from datamodules.formats import discover_all, open_recording
from datamodules.recording import Recording, RecordingError, Track
from datamodules.teacher import TeacherConfig, TeacherScore, run_teacher, score_recording
from datamodules.workers import interruptible_pool

log = logging.getLogger(__name__)


@dataclass
class LabelOutcome:
    """What labelling one recording gave."""

    path: Path
    sequence_id: str | None = None
    label_times: int = 0
    labelled: int = 0
    evidence_frames: int = 0
    seconds: float = 0.0
    written: Path | None = None
    score: TeacherScore | None = None
    error: str | None = None
    skipped: bool = False
    stats: dict[str, Any] = field(default_factory=dict)

    def as_row(self) -> dict[str, Any]:
        """A flat dict for tables."""
        row: dict[str, Any] = {
            "recording": self.path.name, "sequence": self.sequence_id or "-", "labelled": self.labelled,
            "label_times": self.label_times, "evidence": self.evidence_frames, "seconds": round(self.seconds, 2),
            "written": "skipped" if self.skipped else ("yes" if self.written else "no"),
        }
        if self.score is not None:
            row.update({k: round(v, 3) if isinstance(v, float) else v
                        for k, v in self.score.as_row().items() if k != "sequence"})
        row["error"] = self.error or ""
        return row


def write_pseudo_labels(path: Path, recording: Recording, track: Track) -> Path:
    """Store ``track`` in the MCAP recording at ``path`` atomically; other layouts are refused."""
    path = Path(path)
    if not (path.is_file() and path.suffix == ".mcap"):
        layout = recording.meta.get("source_format") or "unknown"
        raise RecordingError(f"{path}: writing pseudo-labels into {layout} recordings is not supported yet; "
                             f"convert to MCAP with 'aaute convert' and label the MCAP file")
    from datamodules.formats.mcap_file import TOPIC_PSEUDO_LABEL, replace_track

    return replace_track(path, TOPIC_PSEUDO_LABEL, track)


def check_writable(path: Path) -> None:
    """Refuse a write-protected recording file before the teacher runs (it is left exactly as it is).

    Raises:
        RecordingError: the file has no owner write permission (e.g. mode 444) or this user cannot write it.
    """
    if not path.is_file():
        return
    mode = stat.S_IMODE(path.stat().st_mode)
    if not mode & stat.S_IWUSR or not os.access(path, os.W_OK):
        raise RecordingError(f"{path}: write-protected (mode {mode:o}); its pseudo-labels are not written and it "
                             f"is left as it is (make it writable with chmod u+w to label it, or use --no-write)")


def has_pseudo_labels(recording: Recording) -> bool:
    """Whether the recording already carries a pseudo-label track."""
    return recording.pseudo_labels is not None and len(recording.pseudo_labels) > 0


def label_one(path: str | Path, config: TeacherConfig | None = None, *, write: bool = True, evaluate: bool = False,
              skip_existing: bool = False, max_range_m: float | None = None,
              reader_options: dict[str, Any] | None = None,
              progress: Callable[[int, int], None] | None = None) -> LabelOutcome:
    """Label one recording: teacher, optional evaluation against ground truth, then the atomic write.

    Errors (bad input, unsupported layout) are caught and returned in :attr:`LabelOutcome.error`;
    nothing is written for a recording that failed.
    """
    path = Path(path)
    outcome = LabelOutcome(path)
    started = time.perf_counter()
    try:
        if write:
            check_writable(path)
        recording = open_recording(path, **(reader_options or {}))
        outcome.sequence_id = recording.sequence_id
        if skip_existing and has_pseudo_labels(recording):
            outcome.skipped = True
            return outcome
        result = run_teacher(recording, config, progress=progress)
        track = result.track
        outcome.label_times, outcome.labelled = len(track), int(track.valid.sum())
        outcome.evidence_frames = int(result.evidence["time"].size)
        outcome.stats = {name: vars(s) for name, s in result.stats.items()}
        if evaluate:
            outcome.score = score_recording(recording, track, max_range_m=max_range_m)
        if write:
            outcome.written = write_pseudo_labels(path, recording, track)
    except (RecordingError, ValueError, OSError) as error:
        outcome.error = str(error)
        log.error("%s: %s", path, error)
    outcome.seconds = time.perf_counter() - started
    return outcome


def label_paths(paths: Sequence[str | Path], config: TeacherConfig | None = None, *, workers: int = 1,
                write: bool = True, evaluate: bool = False, skip_existing: bool = False,
                max_range_m: float | None = None, reader_options: dict[str, Any] | None = None,
                progress: bool = True) -> list[LabelOutcome]:
    """Label every recording under ``paths``; ``workers`` > 1 labels that many in parallel processes.

    Returns one :class:`LabelOutcome` per recording, in the order found.
    """
    from tqdm import tqdm

    recordings = discover_all(paths)
    config = config or TeacherConfig()
    options = dict(write=write, evaluate=evaluate, skip_existing=skip_existing, max_range_m=max_range_m,
                   reader_options=reader_options)
    outcomes: dict[Path, LabelOutcome] = {}
    if workers > 1 and len(recordings) > 1:
        bar = tqdm(total=len(recordings), desc="label", unit="rec", disable=not progress)
        try:
            # leaving the block terminates the workers: Ctrl-C starts no further recording
            with interruptible_pool(min(workers, len(recordings))) as pool:
                for outcome in pool.imap_unordered(functools.partial(label_one, config=config, **options),
                                                   recordings):
                    outcomes[outcome.path] = outcome
                    bar.update()
        except KeyboardInterrupt:
            log.warning("interrupted: %d of %d recordings finished; the others are unchanged (rerun "
                        "with --skip-existing to label only those)", len(outcomes), len(recordings))
            raise
        finally:
            bar.close()
    else:
        overall = tqdm(total=len(recordings), desc="label", unit="rec", disable=not progress or len(recordings) < 2)
        for path in recordings:
            bar = tqdm(total=0, desc=path.name, unit="frame", disable=not progress, leave=False)

            def advance(done: int, total: int, bar=bar) -> None:
                bar.total = total
                bar.n = done
                bar.refresh()

            outcomes[path] = label_one(path, config, progress=advance, **options)
            bar.close()
            overall.update()
        overall.close()
    return [outcomes[p] for p in recordings]
