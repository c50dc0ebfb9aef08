"""Evaluation protocols of the shared DataModule: by_sequence, time_blocks (purged), random_windows."""

from __future__ import annotations

import logging
from itertools import combinations
from pathlib import Path

import numpy as np
import pytest

from datamodules.mmaud import MMAUDDataModule
from datamodules.splits import (
    DROPPED,
    TEST,
    TRAIN,
    VAL,
    SplitConfig,
    SplitError,
    assign_sequences,
    assign_windows,
    block_counts,
)

WINDOW = 0.5  # the fixture's recordings are 4 s long: room for three blocks and their purge gaps
BLOCKS = {"protocol": "time_blocks", "seed": 0, "val": 0.3, "test": 0.3, "blocks": 3}


def _module(root, cache, split, stage: str | None = "fit", **kwargs) -> MMAUDDataModule:
    module = MMAUDDataModule(str(root), split=split, window_seconds=WINDOW, batch_size=4, cache_dir=str(cache),
                             **kwargs)
    module.prepare_data()
    module.setup(stage)
    return module


def _closest(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(np.subtract.outer(a, b)).min()) if a.size and b.size else np.inf


def _by_recording(module: MMAUDDataModule) -> dict[str, dict[str, np.ndarray]]:
    """Window times of each recording per split."""
    result: dict[str, dict[str, np.ndarray]] = {}
    for name, pieces in module.sequences.items():
        for piece in pieces:
            assert name not in result.setdefault(piece.recording_id, {}), "one piece per recording and split"
            result[piece.recording_id][name] = piece.times
    return result


# ------------------------------------------------------------------------------ window assignment


@pytest.mark.parametrize("seed", range(6))
def test_time_blocks_keep_every_split_a_window_apart(seed):
    window, rate = 2.0, 10.0
    times = np.round(np.arange(0.0, 90.0, 1 / rate), 6)
    times = times[(times < 40.0) | (times > 43.0)]  # a stretch without labels
    config = SplitConfig.from_dict({**BLOCKS, "seed": seed, "val": 0.2, "test": 0.2, "blocks": 6}, window)
    assert config.purge_seconds == window
    result = assign_windows(times, config, "flight")
    by_split = {code: times[result.split == code] for code in (TRAIN, VAL, TEST)}
    for a, b in combinations((TRAIN, VAL, TEST), 2):
        assert _closest(by_split[a], by_split[b]) >= window, (a, b)
    assert all(by_split[code].size for code in by_split)  # a 90 s flight reaches every split
    counts = block_counts(6, config.fractions)
    assert (result.blocks("test"), result.blocks("val")) == (counts["test"], counts["val"]) == (1, 1)
    # test windows are never purged; at most one purge gap (window x rate + 1 windows) per block edge
    assert result.dropped == int((result.split == DROPPED).sum()) > 0
    assert result.dropped <= 5 * (window * rate + 1)
    test_block = np.unique(result.block[result.split == TEST])[0]
    assert np.array_equal(result.split == TEST, result.block == test_block)
    again = assign_windows(times, config, "flight")
    assert np.array_equal(again.split, result.split) and np.array_equal(again.block, result.block)


def test_time_blocks_depend_on_seed_and_recording_and_honour_block_seconds():
    times = np.arange(0.0, 60.0, 0.1)
    config = SplitConfig.from_dict({**BLOCKS, "blocks": 10}, 1.0)
    splits = {(seed, key): assign_windows(times, SplitConfig.from_dict({**BLOCKS, "blocks": 10, "seed": seed}, 1.0),
                                          key).split for seed in (0, 1) for key in ("a", "b")}
    assert len({tuple(s) for s in splits.values()}) > 1
    assert np.array_equal(assign_windows(times, config, "a").split, splits[(0, "a")])
    by_length = SplitConfig.from_dict({"protocol": "time_blocks", "block_seconds": 12.0, "purge_seconds": 3.0}, 1.0)
    result = assign_windows(times, by_length, "a")
    assert np.unique(result.block).size == 5
    kept = {code: times[result.split == code] for code in (TRAIN, VAL, TEST)}
    assert _closest(kept[TRAIN], kept[TEST]) >= 3.0 and _closest(kept[TRAIN], kept[VAL]) >= 3.0
    # a recording too short for three blocks gives what it can to test, then to train
    assert block_counts(2, {"val": 0.2, "test": 0.2}) == {"val": 0, "test": 1}
    assert block_counts(1, {"val": 0.2, "test": 0.2}) == {"val": 0, "test": 0}


def test_random_windows_follow_the_fractions_and_overlap_training():
    times = np.arange(0.0, 60.0, 0.1)
    config = SplitConfig.from_dict({"protocol": "random_windows", "seed": 2, "val": 0.1, "test": 0.25}, 2.0)
    result = assign_windows(times, config, "flight")
    assert (result.split == TEST).sum() == 150 and (result.split == VAL).sum() == 60 and result.dropped == 0
    test, train = times[result.split == TEST], times[result.split == TRAIN]
    assert np.median(np.abs(np.subtract.outer(test, train)).min(axis=1)) <= 0.1 + 1e-9
    assert config.label.startswith("random_windows") and "overlap" in config.label


def test_split_settings_are_checked():
    cases = [
        ({"protocol": "kfold"}, "unknown protocol 'kfold'; known: by_sequence, time_blocks, random_windows"),
        ({"val": -0.1}, r"val must be a fraction in \[0, 1\)"),
        ({"val": 0.5, "test": 0.5}, "val \\+ test must be below 1"),
        ({"protocol": "time_blocks", "purge_seconds": 0.5}, "purge_seconds must be at least"),
        ({"protocol": "time_blocks", "blocks": 3, "block_seconds": 10}, "either blocks"),
        ({"protocol": "time_blocks", "blocks": 0}, "blocks must be a positive"),
        ({"protocol": "time_blocks", "train": ["a"], "test": ["b"]}, "explicit lists .* by_sequence"),
        ({"train": ["a"], "val": 0.2}, "must be lists"),
        ({"blocks": 4}, "time_blocks only"),
        ({"vall": 0.2}, "unknown key"),
        ({"train_flights": 0}, "train_flights must be a positive"),
        ({"protocol": "time_blocks", "train_flights": 2}, "train_flights .* under time_blocks"),
    ]
    for split, message in cases:
        with pytest.raises(SplitError, match=message):
            SplitConfig.from_dict(split, 1.0)
    with pytest.raises(SplitError, match="unknown protocol"):
        MMAUDDataModule("anywhere", split={"protocol": "kfold"})


def test_train_flights_take_nested_training_sets_drone_by_drone_and_keep_val_and_test():
    drones = ["avata", "m300", "mavic2"] * 6
    names = [(f"seq{i}", f"f{i}") for i in range(len(drones))]
    full = assign_sequences(names, drones, SplitConfig.from_dict({"val": 0.2, "test": 0.2}, 1.0))
    previous: set[int] = set()
    for flights in (1, 3, 6):
        split = assign_sequences(names, drones, SplitConfig.from_dict({"val": 0.2, "test": 0.2,
                                                                       "train_flights": flights}, 1.0))
        train = {i for i, name in enumerate(split) if name == "train"}
        assert len(train) == flights and previous <= train
        assert all(split[i] == full[i] for i in range(len(drones)) if full[i] != "train")
        assert all(full[i] == "train" for i in train) and split.count(None) == full.count("train") - flights
        previous = train
    assert {drones[i] for i in previous} == {"avata", "m300", "mavic2"}  # the drones in turn: two flights each


# ------------------------------------------------------------------------------ the DataModule


def test_time_blocks_pieces_are_disjoint_purged_and_deterministic(labelled_dir, feature_cache):
    module = _module(labelled_dir, feature_cache, BLOCKS)
    whole = _module(labelled_dir, feature_cache, {"train": [p.stem for p in sorted(labelled_dir.glob("*.mcap"))]},
                    stage=None)
    assert module.protocol == "time_blocks"
    ids = module.sequence_ids
    assert len(ids) == len(set(ids)) == 9 and all("#" in i for i in ids)
    drones = {s.sequence_id: s.drone for s in whole.sequences["train"]}
    times = _by_recording(module)
    assert set(times) == set(drones)
    for name, pieces in module.sequences.items():
        for piece in pieces:
            assert piece.sequence_id == f"{piece.recording_id}#{name}" and piece.drone == drones[piece.recording_id]
            assert np.all(np.diff(piece.times) > 0)
    for recording, splits in times.items():
        assert set(splits) == {"train", "val", "test"}  # every flight reaches every split
        for a, b in (("train", "test"), ("train", "val"), ("val", "test")):
            assert _closest(splits[a], splits[b]) >= WINDOW, (recording, a, b)
        used = np.concatenate(list(splits.values()))
        full = next(s.times for s in whole.sequences["train"] if s.sequence_id == recording)
        assert used.size == np.unique(used).size and np.isin(used, full).all()  # each window in one split at most
    summary = module.split_summary()
    total = sum(summary[name]["windows"] for name in ("train", "val", "test"))
    assert total + summary["purged_windows"] == whole.split_summary()["train"]["windows"]
    assert summary["test"] == {"sequences": 3, "pieces": 3, "blocks": 3, "windows": len(module.test_dataloader()[0]
                                                                                      .dataset),
                               "overlap_with_train": 0.0}
    assert summary["train"]["blocks"] >= 3 and summary["purge_seconds"] == WINDOW
    again = _module(labelled_dir, feature_cache, BLOCKS)
    assert again.sequence_ids == ids
    assert all(np.array_equal(a.times, b.times) for n in ("train", "val", "test")
               for a, b in zip(module.sequences[n], again.sequences[n], strict=True))
    other = _module(labelled_dir, feature_cache, {**BLOCKS, "seed": 1})
    assert any(not np.array_equal(a.times, b.times) for a, b in zip(module.sequences["test"], other.sequences["test"],
                                                                   strict=True))


def test_features_are_cached_once_per_recording_whatever_the_protocol(labelled_dir, tmp_path):
    cache = tmp_path / "cache"
    names = [p.stem for p in sorted(labelled_dir.glob("*.mcap"))]
    whole = _module(labelled_dir, cache, {"train": names}, stage=None)
    entries = sorted(cache.glob("*.npy"))
    stamps = [e.stat().st_mtime_ns for e in entries]
    assert len(entries) == 3  # one per recording and recipe
    for split in (BLOCKS, {"protocol": "random_windows", "seed": 4}):
        module = _module(labelled_dir, cache, split)
        assert sorted(cache.glob("*.npy")) == entries and [e.stat().st_mtime_ns for e in entries] == stamps
        test = module.test_dataloader()[0].dataset
        for k in (0, len(test) - 1):
            item = test[k]
            recording = module.sequences["test"][0] if k == 0 else module.sequences["test"][-1]
            full = next(s for s in whole.sequences["train"] if s.sequence_id == recording.recording_id)
            row = int(np.flatnonzero(full.times == float(item["time"]))[0])
            reference = whole.train_dataloader().dataset
            offset = int(reference.offsets[whole.sequences["train"].index(full)])
            assert np.array_equal(item["audio_mel"].numpy(), reference[offset + row]["audio_mel"].numpy())
            assert np.allclose(item["gt"].numpy(), full.gt[row])


def test_random_windows_warn_and_really_overlap(labelled_dir, feature_cache, caplog):
    split = {"protocol": "random_windows", "seed": 0, "val": 0.2, "test": 0.2}
    with caplog.at_level(logging.WARNING, logger="datamodules.mmaud"):
        module = _module(labelled_dir, feature_cache, split)
    warnings = [r.getMessage() for r in caplog.records
                if r.levelno == logging.WARNING and "random_windows" in r.getMessage()]
    assert warnings and "overlap" in warnings[0]
    assert module.protocol.startswith("random_windows") and "overlaps" in module.protocol
    times = _by_recording(module)
    near = [np.abs(np.subtract.outer(s["test"], s["train"])).min(axis=1) < WINDOW for s in times.values()]
    share = float(np.concatenate(near).mean())
    assert share > 0.9
    summary = module.split_summary()
    assert summary["test"]["overlap_with_train"] == pytest.approx(share)
    assert summary["train"]["blocks"] == summary["train"]["windows"]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="datamodules.mmaud"):
        module.setup("test")
    assert any("random_windows" in r.getMessage() for r in caplog.records)


def test_by_sequence_default_is_todays_split(labelled_dir, feature_cache):
    default = MMAUDDataModule(str(labelled_dir), window_seconds=WINDOW)
    named = MMAUDDataModule(str(labelled_dir), window_seconds=WINDOW,
                            split={"protocol": "by_sequence", "seed": 0, "val": 0.2, "test": 0.2})
    assert default.protocol == named.protocol == "by_sequence"
    assert default.split_config == named.split_config
    module = _module(labelled_dir, feature_cache, {"protocol": "by_sequence", "train": ["sim11-0000-avata"],
                                                   "val": ["sim11-0001-m300"], "test": ["sim11-0002-mavic2"]})
    assert module.sequence_ids == ["sim11-0000-avata", "sim11-0001-m300", "sim11-0002-mavic2"]
    summary = module.split_summary()
    assert summary["protocol"] == "by_sequence" and summary["purged_windows"] == 0
    assert summary["val"] == {"sequences": 1, "pieces": 1, "blocks": 1, "windows": len(module.sequences["val"][0]),
                              "overlap_with_train": 0.0}


def test_an_impossible_split_fails_at_setup_with_the_fix(labelled_dir, feature_cache):
    # three recordings of three drones: the seeded by-sequence split leaves val and test empty
    module = MMAUDDataModule(str(labelled_dir), split={"seed": 0, "val": 0.2, "test": 0.2}, window_seconds=WINDOW,
                             cache_dir=str(feature_cache))
    module.prepare_data()
    for stage, empty in (("fit", "'val'"), ("test", "'test'"), ("predict", "'test'")):
        with pytest.raises(SplitError) as error:
            module.setup(stage)
        message = str(error.value)
        assert "\n" not in message and message.startswith(f"cannot {stage}: split by_sequence")
        for part in (f"leaves {empty} empty", "train: 3 sequences", "val: 0 sequences", "test: 0 sequences",
                     "from 3 recordings", "avata 1, m300 1, mavic2 1", "time_blocks", "explicit lists"):
            assert part in message, part
    module.setup(None)  # indexing alone needs no split
    with pytest.raises(SplitError, match="cannot load test"):
        module.test_dataloader()
    # time_blocks on the same recordings works; too many blocks for 4 s flights says so
    assert _module(labelled_dir, feature_cache, BLOCKS).split_summary()["val"]["windows"] > 0
    with pytest.raises(SplitError, match="cannot fit: split time_blocks .*fewer blocks"):
        _module(labelled_dir, feature_cache, {**BLOCKS, "blocks": 40, "purge_seconds": 1.5})


def test_time_blocks_test_run_groups_predictions_per_piece(labelled_dir, feature_cache, tmp_path):
    import pandas as pd

    from zoo.cli import main

    config = str(Path(__file__).resolve().parents[2] / "configs" / "model" / "student.yaml")
    split = "{protocol: time_blocks, seed: 0, val: 0.3, test: 0.3, blocks: 3}"
    out = tmp_path / "predictions"
    args = ["test", "--config", config, "--data.root", str(labelled_dir), "--data.split", split,
            "--data.window_seconds", str(WINDOW), "--data.batch_size", "256", "--data.test_lights", "[ideal]",
            "--data.cache_dir", str(feature_cache), "--model.smooth", "true", "--model.predictions_dir", str(out),
            "--trainer.default_root_dir", str(tmp_path), "--trainer.fast_dev_run", "true",
            "--trainer.enable_progress_bar", "false"]
    assert main(args) == 0
    module = _module(labelled_dir, feature_cache, BLOCKS, stage="test")
    written = sorted(p.name for p in out.glob("*.csv"))
    assert written == sorted(f"{s.sequence_id}_ideal.csv" for s in module.sequences["test"])
    for piece in module.sequences["test"]:
        table = pd.read_csv(out / f"{piece.sequence_id}_ideal.csv")
        assert np.allclose(table["timestamp"].to_numpy(), piece.times, atol=1e-6)
