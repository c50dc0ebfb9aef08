"""``aaute label``: labels recordings of any layout in parallel, stores the track atomically, evaluates."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from datamodules.cli import main
from datamodules.formats.mcap_file import read_mcap
from datamodules.label import label_one, label_paths


@pytest.fixture
def recordings(simulated_dir, tmp_path):
    """Copies of the shared simulated recordings (labelling rewrites them)."""
    out = tmp_path / "recs"
    out.mkdir()
    for path in sorted(simulated_dir.glob("*.mcap")):
        shutil.copy(path, out / path.name)
    return out


def test_label_command_writes_pseudo_labels_in_parallel_and_evaluates(recordings, capsys):
    before = {p.name: read_mcap(p) for p in recordings.glob("*.mcap")}
    assert all(r.pseudo_labels is None for r in before.values())
    code = main(["label", str(recordings), "--workers", "2", "--evaluate"])
    assert code == 0
    out = capsys.readouterr().out
    assert "mean_m" in out and "all recordings" in out
    for path in sorted(recordings.glob("*.mcap")):
        recording = read_mcap(path)
        track = recording.pseudo_labels
        assert track is not None
        np.testing.assert_array_equal(track.timestamps, recording.ground_truth.timestamps)
        assert set(track.quality) == {"support_points", "nearest_evidence_s", "residual_m"}
        assert np.isnan(track.xyz[~track.valid]).all()
        original = before[path.name]
        assert len(recording.lidar["mid360"]) == len(original.lidar["mid360"])  # sensor data kept
        np.testing.assert_array_equal(recording.lidar["avia"][3].points, original.lidar["avia"][3].points)
    assert not [p for p in recordings.iterdir() if p.name.startswith(".")]  # no temporary files left


def test_label_skip_existing_and_dry_run(recordings):
    first = sorted(recordings.glob("*.mcap"))[0]
    done = label_one(first)
    assert done.written == first and done.error is None
    stamp = first.stat().st_mtime_ns
    again = label_paths([recordings], skip_existing=True, progress=False)
    assert [o.skipped for o in again].count(True) == 1
    assert first.stat().st_mtime_ns == stamp
    dry = label_paths([recordings], write=False, evaluate=True, progress=False)
    assert all(o.written is None and o.score is not None for o in dry)


def test_layouts_without_a_writer_are_refused_and_left_untouched(shared_data, tmp_path):
    source = shared_data / "mmaud_ug2_val_seq1"
    if not source.is_dir():
        pytest.skip("real UG2 sequence absent")
    seq = tmp_path / "val" / "seq1"
    shutil.copytree(source / "lidar_360", seq / "lidar_360")
    shutil.copytree(source / "livox_avia", seq / "livox_avia")
    before = sorted(p.relative_to(seq) for p in seq.rglob("*"))
    outcome = label_one(seq)
    assert outcome.error is not None and "aaute convert" in outcome.error
    assert sorted(p.relative_to(seq) for p in seq.rglob("*")) == before
    assert main(["label", str(seq), "--no-write"]) == 0


def test_bad_recording_fails_alone(recordings, tmp_path):
    broken = recordings / "broken.mcap"
    broken.write_bytes(b"not an mcap file")
    outcomes = label_paths([recordings], progress=False)
    errors = {o.path.name: o.error for o in outcomes}
    assert errors["broken.mcap"] is not None
    assert sum(e is None for e in errors.values()) == 3
    assert broken.read_bytes() == b"not an mcap file"
    assert main(["label", str(broken)]) == 1


def test_a_write_protected_recording_is_refused_and_left_as_it_was(recordings, caplog):
    import hashlib
    import os

    protected, writable = sorted(recordings.glob("*.mcap"))[:2]
    before = hashlib.sha256(protected.read_bytes()).hexdigest()
    protected.chmod(0o444)
    writable.chmod(0o640)
    assert main(["label", str(protected), str(writable)]) == 1
    assert f"{protected}: write-protected (mode 444)" in caplog.text
    assert hashlib.sha256(protected.read_bytes()).hexdigest() == before
    assert os.stat(protected).st_mode & 0o777 == 0o444  # not replaced by a writable copy
    assert read_mcap(writable).pseudo_labels is not None  # the others are labelled
    assert os.stat(writable).st_mode & 0o777 == 0o640  # and keep their permissions
