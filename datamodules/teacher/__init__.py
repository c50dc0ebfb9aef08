"""The unsupervised LiDAR teacher: pseudo-label tracks from Livox Mid-360 and Avia scans.

The AAUTE paper's pipeline (``reference/mmaud_and_teacher.md`` section 3.1): Mid-360 chunks of
20 scans -> DBSCAN -> component merging -> drop largest / smallest -> UAV cluster by density;
Avia farthest point sampling; fusion by time and DBSCAN against solar returns; B-spline through
the per-frame centroids. See :mod:`datamodules.teacher.pipeline` for the stages and
:class:`TeacherConfig` for every threshold.
"""

from __future__ import annotations

from datamodules.teacher.evaluate import TeacherScore, drone_return_mask, evaluate_track, score_recording
from datamodules.teacher.pipeline import TeacherConfig, TeacherResult, label_recording, run_teacher

__all__ = [
    "TeacherConfig",
    "TeacherResult",
    "TeacherScore",
    "drone_return_mask",
    "evaluate_track",
    "label_recording",
    "run_teacher",
    "score_recording",
]
