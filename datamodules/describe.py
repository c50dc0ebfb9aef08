"""Summaries of what a recording holds, for ``aaute info``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from datamodules.formats import detect_layout, open_recording
from datamodules.recording import AudioStream, check_finite_audio, count_gaps

#: seconds of audio read at a time when scanning floating-point audio for NaN or infinite samples
SCAN_BLOCK_SECONDS = 10.0


def _rate(timestamps: np.ndarray) -> float:
    return float(1.0 / np.median(np.diff(timestamps))) if len(timestamps) > 1 else float("nan")


def _gaps(timestamps: np.ndarray) -> int:
    """Gaps as ``aaute info`` reports them: steps over twice the median step."""
    return count_gaps(timestamps, factor=2.0)


def _format(path: Path, source: str | None) -> str:
    """The on-disk layout, with the original source of a converted MCAP in brackets."""
    layout = detect_layout(path)
    return f"{layout} ({source})" if source and source != layout else layout


def _mics(meta: dict[str, Any]) -> str:
    """Whether the microphone positions were given ('given') or are missing ('unknown': no phase models)."""
    return "unknown" if meta.get("mic_positions_known", True) is False else "given"


def _nodes(meta: dict[str, Any]) -> str:
    """Audio nodes, whether they share a clock, and the residual alignment uncertainty of separate streams."""
    nodes = meta.get("audio_nodes") or []
    if len(nodes) < 2:
        return "1"
    clock = "one-clock" if meta.get("nodes_share_clock") else "own-clocks"
    uncertainty = meta.get("audio_alignment_uncertainty_s")
    spread = "±?" if uncertainty is None else f"±{1e3 * float(uncertainty):.2f}ms"
    return f"{len(nodes)} {clock} {spread}"


def scan_audio(audio: AudioStream, what: str) -> None:
    """Read floating-point audio through, refusing NaN or infinite samples (integer formats cannot hold them).

    Raises:
        RecordingError: naming ``what`` and the time of the first bad sample.
    """
    if audio.sample_format not in (None, "F32LE"):
        return
    block = max(1, int(SCAN_BLOCK_SECONDS * audio.sample_rate))
    for start in range(0, audio.num_samples, block):
        samples = audio.read(start, min(start + block, audio.num_samples))
        check_finite_audio(samples, audio.t0 + start / audio.sample_rate, audio.sample_rate, f"{what} audio",
                           audio.t0)


def describe(path: Path, sample_frames: int = 5, **options: Any) -> dict[str, Any]:
    """Streams, rates, spans and counts of one recording (LiDAR point counts from a few frames).

    ``options`` go to :func:`open_recording` (e.g. ``sample_rate`` for the derived npy layout).
    """
    path = Path(path)
    recording = open_recording(path, **options)
    start, end = recording.time_span()
    row: dict[str, Any] = {
        "recording": str(path.name),
        "format": _format(path, recording.meta.get("source_format")),
        "sequence": recording.sequence_id,
        "drone": recording.drone or "-",
        "span_s": round(end - start, 2),
    }
    audio = recording.audio
    if audio is not None:
        scan_audio(audio, str(path))
    row["audio"] = (f"{audio.num_channels}ch {audio.sample_rate:g}Hz {audio.duration:.1f}s"
                    if audio is not None else "-")
    audio_gaps = recording.meta.get("audio_gaps") or recording.meta.get("audio_missing_chunks")
    if audio is not None and audio_gaps:
        row["audio"] += f" gaps:{audio_gaps}"
    row["mics"] = _mics(recording.meta) if audio is not None else "-"
    row["nodes"] = _nodes(recording.meta) if audio is not None else "-"
    for sensor in ("mid360", "avia"):
        clouds = recording.lidar.get(sensor)
        if clouds is None or len(clouds) == 0:
            row[sensor] = "-"
            continue
        picks = np.linspace(0, len(clouds) - 1, min(sample_frames, len(clouds))).astype(int)
        mean_points = float(np.mean([len(clouds[int(i)]) for i in picks]))
        gaps = _gaps(clouds.timestamps)
        row[sensor] = (f"{len(clouds)} @{_rate(clouds.timestamps):.1f}Hz ~{mean_points:.0f}pts"
                       + (f" gaps:{gaps}" if gaps else ""))
    frames = recording.frames
    row["camera"] = f"{len(frames)} @{_rate(frames.timestamps):.1f}Hz" if frames is not None and len(frames) else "-"
    for name, track in (("ground_truth", recording.ground_truth), ("pseudo_label", recording.pseudo_labels)):
        if track is None:
            row[name] = "-"
        else:
            valid = int(track.valid.sum())
            gaps = _gaps(track.timestamps[track.valid])
            row[name] = f"{valid}/{len(track)} @{_rate(track.timestamps):.1f}Hz gaps:{gaps}"
    audio_meta = recording.meta.get("audio")
    snr = audio_meta.get("snr_db_mean") if isinstance(audio_meta, dict) else None
    row["snr_db"] = "-" if snr is None else f"{snr:.1f}"
    row["MB"] = f"{path.stat().st_size / 1e6:.1f}" if path.is_file() else "-"
    return row


def clock_line(path: Path, **options: Any) -> str | None:
    """The nodes' clock offsets estimated from the audio (with their uncertainty), or why there are none, for a
    recording whose nodes do not share a clock (None for one that says they do). Reads the whole audio."""
    from datamodules.features.clock_calibration import ClockCalibrationError, estimate_clock_offsets

    recording = open_recording(Path(path), **options)
    if recording.audio is None or recording.meta.get("nodes_share_clock", True) is not False:
        return None
    try:
        return estimate_clock_offsets(recording.audio).summary()
    except ClockCalibrationError as error:
        return f"clock offsets not estimated: {error}"


def format_table(rows: list[dict[str, Any]]) -> str:
    """A plain-text table (one row per recording), aligned for terminals."""
    if not rows:
        return "(no recordings)"
    columns = list(rows[0])
    cells = [[str(row.get(c, "")) for c in columns] for row in rows]
    widths = [max(len(c), *(len(r[i]) for r in cells)) for i, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths, strict=True))]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(v.ljust(w) for v, w in zip(r, widths, strict=True)) for r in cells]
    return "\n".join(lines)
