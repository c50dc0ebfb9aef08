"""The UG2 challenge-folder reader: the real validation sequence, synthetic train folders, bad input."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from datamodules.formats import discover_recordings, open_recording, ug2
from datamodules.formats.mcap_file import write_mcap
from datamodules.recording import RecordingError
from tests.helpers.layouts import make_ug2_sequence

REAL = "mmaud_ug2_val_seq1"


@pytest.fixture(scope="module")
def real_seq(shared_data) -> Path:
    path = shared_data / REAL
    if not path.is_dir():
        pytest.skip(f"real UG2 sequence not found at {path}")
    return path


def _nonzero_rows(path: Path) -> int:
    return int(np.any(np.load(path) != 0, axis=1).sum())


# ============================================================================================ real data


def test_real_sequence_frames_span_and_stamps(real_seq):
    rec = open_recording(real_seq)
    assert rec.meta["source_format"] == "ug2" and rec.meta["frame"] == ug2.FRAME
    assert rec.audio is None and rec.ground_truth is None and rec.frames is None and rec.drone is None
    assert {k: len(v) for k, v in rec.lidar.items()} == {"mid360": 88, "avia": 88}
    mid, avia = rec.lidar["mid360"], rec.lidar["avia"]
    assert mid.timestamps[0] == 1706255621.600227 and mid.timestamps[-1] == 1706255630.300250
    assert avia.timestamps[0] == 1706255621.614239 and avia.timestamps[-1] == 1706255630.314129
    start, end = rec.time_span()
    assert end - start == pytest.approx(8.713902, abs=1e-6)
    assert np.all(np.diff(mid.timestamps) > 0.099) and np.all(np.diff(mid.timestamps) < 0.101)
    # every name parses to the microsecond it spells
    for folder, stamps in (("lidar_360", mid.timestamps), ("livox_avia", avia.timestamps)):
        spelled = sorted(int(p.stem.replace(".", "")) for p in (real_seq / folder).glob("*.npy"))
        assert np.array_equal(np.rint(stamps * 1e6).astype(np.int64), spelled)
    # Avia frames are offset from the Mid-360 ones by about 14 ms (associated by nearest stamp)
    offsets = avia.timestamps - mid.timestamps[[mid.nearest(t) for t in avia.timestamps]]
    assert np.median(offsets) == pytest.approx(0.014, abs=0.002)


def test_real_points_per_frame_without_padding(real_seq):
    rec = open_recording(real_seq)
    mid, avia = rec.lidar["mid360"], rec.lidar["avia"]
    mid_counts = np.array([len(mid[i]) for i in range(len(mid))])
    avia_counts = np.array([len(avia[i]) for i in range(len(avia))])
    assert mid_counts.min() == 3912 and mid_counts.max() == 4406
    assert avia_counts.sum() == 1250 and avia_counts.max() == 178 and np.median(avia_counts) == 1
    # the padded files are much longer: padding was really removed, and only padding
    assert np.load(sorted((real_seq / "lidar_360").glob("*.npy"))[0]).shape[0] > 19000
    first = sorted((real_seq / "lidar_360").glob("*.npy"), key=ug2.stamp_from_name)[0]
    assert mid_counts[0] == _nonzero_rows(first)
    cloud = mid[0]
    assert cloud.points.dtype == np.float32 and not np.any(np.all(cloud.points == 0, axis=1))
    # kept in the Mid-360 frame: the roof returns lie about 1.3 m below the sensor
    z = np.concatenate([mid[i].points[:, 2] for i in range(0, 88, 11)])
    assert -1.45 < np.percentile(z, 5) < -1.15


def test_real_avia_returns_cluster_at_the_tracker_output(real_seq):
    rec = open_recording(real_seq)
    avia = rec.lidar["avia"]
    tracker = sorted((real_seq / "reference_tracker_output").glob("*.npy"), key=ug2.stamp_from_name)
    assert len(tracker) == 76
    medians, near, total = [], 0, 0
    for path in tracker:
        t, position = ug2.stamp_from_name(path), np.load(path)
        i = avia.nearest(t)
        assert abs(avia.timestamps[i] - t) < 0.015
        points = avia[i].points
        if not len(points):
            continue
        distance = np.linalg.norm(points - position, axis=1)
        medians.append(np.median(distance))
        near += int((distance < 1.0).sum())
        total += len(points)
    assert len(medians) >= 45
    assert np.median(medians) < 0.2
    assert near / total > 0.9


def test_real_sequence_converts_to_identical_mcap(real_seq, tmp_path):
    rec = open_recording(real_seq)
    back = open_recording(write_mcap(rec, tmp_path / "seq1.mcap"))
    assert back.sequence_id == rec.sequence_id and back.meta == rec.meta
    for sensor in ("mid360", "avia"):
        assert np.array_equal(back.lidar[sensor].timestamps, rec.lidar[sensor].timestamps)
        for i in (0, 40, 87):
            assert np.array_equal(back.lidar[sensor][i].points, rec.lidar[sensor][i].points)


def test_frames_are_read_on_access(real_seq, monkeypatch):
    loads = []
    original = ug2.load_npy
    monkeypatch.setattr(ug2, "load_npy", lambda path: loads.append(path) or original(path))
    rec = open_recording(real_seq)
    assert loads == []
    rec.lidar["avia"][5]
    assert len(loads) == 1 and loads[0].parent.name == "livox_avia"


# ====================================================================================== synthetic train


def test_train_sequence_with_ground_truth_class_and_images(tmp_path):
    written = make_ug2_sequence(tmp_path / "train" / "seq3")
    rec = open_recording(tmp_path / "train" / "seq3")
    assert rec.sequence_id == "train_seq3"
    assert rec.drone == "m300" and rec.meta["ug2_class"] == 2 and rec.meta["ug2_class_name"] == "M300"
    assert len(rec.lidar["mid360"]) == 12 and len(rec.frames) == 12 and len(rec.ground_truth) == 12
    for i in (0, 5, 11):
        assert np.array_equal(rec.lidar["avia"][i].points, written["avia"][i])
    assert np.allclose(rec.ground_truth.xyz, np.array(written["gt"]))
    image = rec.frames[3]
    assert image.format == "png" and image.decode().shape == (4, 8, 3)


def test_class_without_drone_type_is_kept_in_meta(tmp_path):
    make_ug2_sequence(tmp_path / "seq1", frames=4, class_id=1)
    rec = open_recording(tmp_path / "seq1")
    assert rec.drone is None and rec.meta["ug2_class_name"] == "M30"
    assert open_recording(tmp_path / "seq1", drone="mavic3").drone == "mavic3"


def test_one_hot_class_files_are_understood(tmp_path):
    make_ug2_sequence(tmp_path / "seq1", frames=3, class_id=None)
    for path in (tmp_path / "seq1" / "ground_truth").glob("*.npy"):
        np.save(tmp_path / "seq1" / "class" / path.name, np.array([0, 0, 0, 1]))
    assert open_recording(tmp_path / "seq1").drone == "phantom4"


def test_missing_frames_warn_with_a_count(tmp_path, caplog):
    make_ug2_sequence(tmp_path / "seq1", frames=20, skip=(7, 13, 14))
    with caplog.at_level(logging.WARNING, logger="datamodules.formats.ug2"):
        rec = open_recording(tmp_path / "seq1")
    assert len(rec.lidar["mid360"]) == 17
    assert rec.meta["gaps"]["lidar_360"] == 2
    assert any("2 gap(s) in lidar_360" in r.getMessage() for r in caplog.records)


def test_discover_finds_sequences_of_every_split(tmp_path):
    make_ug2_sequence(tmp_path / "Data" / "train" / "seq1", frames=3)
    make_ug2_sequence(tmp_path / "Data" / "train" / "seq2", frames=3)
    make_ug2_sequence(tmp_path / "Data" / "val" / "seq1", frames=3, class_id=None)
    found = discover_recordings(tmp_path / "Data")
    assert [p.relative_to(tmp_path / "Data").as_posix() for p in found] == ["train/seq1", "train/seq2", "val/seq1"]
    with pytest.raises(RecordingError, match=r"but a folder of 3 recordings \(train/seq1, train/seq2, val/seq1\)"):
        open_recording(tmp_path / "Data")
    ids = [open_recording(p).sequence_id for p in found]
    assert ids == ["train_seq1", "train_seq2", "val_seq1"]
    assert open_recording(found[2]).ground_truth is not None  # written above; val may also lack it
    (tmp_path / "Data" / "val" / "seq1" / "ground_truth").rename(tmp_path / "gone")
    assert open_recording(found[2]).ground_truth is None


# ============================================================================================ bad input


def test_bad_file_name_is_named(tmp_path):
    make_ug2_sequence(tmp_path / "seq1", frames=3)
    np.save(tmp_path / "seq1" / "lidar_360" / "frame_a.npy", np.zeros((3, 3)))
    with pytest.raises(RecordingError, match=r"frame_a\.npy.*<ros_time>"):
        open_recording(tmp_path / "seq1")


def test_two_files_with_one_time_are_refused(tmp_path):
    make_ug2_sequence(tmp_path / "seq1", frames=3)
    first = sorted((tmp_path / "seq1" / "livox_avia").glob("*.npy"))[0]
    np.save(first.with_name(first.stem + "0.npy"), np.zeros((3, 3)))
    with pytest.raises(RecordingError, match="livox_avia: timestamps must increase"):
        open_recording(tmp_path / "seq1")


def test_malformed_scan_and_ground_truth_are_named(tmp_path):
    make_ug2_sequence(tmp_path / "seq1", frames=3)
    scan = sorted((tmp_path / "seq1" / "lidar_360").glob("*.npy"))[1]
    np.save(scan, np.zeros((5, 2)))
    rec = open_recording(tmp_path / "seq1")
    with pytest.raises(RecordingError, match=rf"{scan.name}: expected a numeric \(points x 3\)"):
        rec.lidar["mid360"][1]
    gt = sorted((tmp_path / "seq1" / "ground_truth").glob("*.npy"))[0]
    np.save(gt, np.zeros(2))
    with pytest.raises(RecordingError, match=rf"{gt.name}: expected 3 values"):
        open_recording(tmp_path / "seq1")


def test_folder_of_no_known_layout(tmp_path):
    (tmp_path / "stuff").mkdir()
    (tmp_path / "stuff" / "notes.txt").write_text("x")
    with pytest.raises(RecordingError, match="folder is not a known recording layout; expected an .mcap"):
        open_recording(tmp_path / "stuff")
    with pytest.raises(RecordingError, match="no recordings found; expected"):
        discover_recordings(tmp_path / "stuff")
