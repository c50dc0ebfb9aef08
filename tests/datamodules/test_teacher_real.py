"""The teacher end to end on the real UG2 validation sequence (real Livox Mid-360 and Avia frames).

There is no ground truth for this sequence; the track is compared with the output of the published
LiDAR tracker of Deng et al. (``reference_tracker_output/``, a peer's estimate). Skips when the
real samples are absent.
"""

from __future__ import annotations

import numpy as np
import pytest

from datamodules.formats import open_recording
from datamodules.formats.ug2 import list_stamped_files
from datamodules.recording import Track
from datamodules.teacher import TeacherConfig, run_teacher
from datamodules.teacher.evaluate import track_at


@pytest.fixture(scope="module")
def ug2_seq1(shared_data):
    path = shared_data / "mmaud_ug2_val_seq1"
    if not (path / "lidar_360").is_dir():
        pytest.skip(f"real UG2 sequence not found at {path}")
    return path


def reference_track(folder) -> Track:
    stamps, names = list_stamped_files(folder, (".npy",))
    return Track(stamps, np.array([np.load(folder / n).reshape(3) for n in names]))


def test_teacher_on_real_ug2_frames_matches_the_published_tracker(ug2_seq1):
    recording = open_recording(ug2_seq1)
    result = run_teacher(recording, TeacherConfig(label_times="grid"))
    track = result.track
    assert len(track) > 80 and track.valid.mean() > 0.9
    assert {"mid360", "avia"} <= set(result.evidence["sensor"].tolist())
    reference = reference_track(ug2_seq1 / "reference_tracker_output")
    xyz, valid = track_at(track, reference.timestamps, tolerance_s=0.06)
    assert valid.mean() > 0.9
    distance = np.linalg.norm(xyz[valid] - reference.xyz[valid], axis=1)
    median = float(np.median(distance))
    print(f"\nreal UG2 val/seq1: {int(track.valid.sum())}/{len(track)} labelled, {result.evidence['time'].size} "
          f"evidence frames; distance to the published tracker at its {int(valid.sum())} times: median "
          f"{median:.3f} m, mean {distance.mean():.3f} m, 95th percentile {np.percentile(distance, 95):.3f} m")
    assert median < 0.5
    # the real frames are in the Mid-360 sensor frame: the teacher did not assume the rig frame
    assert np.nanmedian(track.xyz[:, 2]) > 0.5


def test_teacher_on_real_frames_reports_padding(ug2_seq1):
    recording = open_recording(ug2_seq1)
    result = run_teacher(recording)
    avia = result.stats["avia"]
    assert avia.frames == 88 and 0 < avia.empty_frames < 88  # most Avia frames are padding only
