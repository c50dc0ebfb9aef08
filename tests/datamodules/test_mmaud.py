"""The shared DataModule: samples, splits, targets, darkness, cache, configuration from YAML."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from datamodules.formats import open_recording
from datamodules.mmaud import MMAUDDataModule
from datamodules.recording import Recording, RecordingError, Track
from tests.helpers.layouts import CHUNK, make_derived, make_ug2_sequence
from tests.helpers.real_data import shared_data_dir


def _module(root, tmp_path, stage: str = "fit", **kwargs) -> MMAUDDataModule:
    defaults = dict(split={"train": ["sim11-0000-avata"], "val": ["sim11-0001-m300"], "test": ["sim11-0002-mavic2"]},
                    window_seconds=1.0, batch_size=4, cache_dir=str(tmp_path / "cache"))
    module = MMAUDDataModule(str(root), **{**defaults, **kwargs})
    module.prepare_data()
    module.setup(stage)
    return module


def test_windows_end_at_label_times_and_carry_every_target(labelled_dir, tmp_path):
    module = _module(labelled_dir, tmp_path)
    batch = next(iter(module.train_dataloader()))
    assert tuple(batch["audio_mel"].shape) == (4, 4, 64, 64)
    for key in ("gt", "pseudo"):
        assert tuple(batch[key].shape) == (4, 3)
    recording = open_recording(next(labelled_dir.glob("*0000.mcap")))
    samples = module.sequences["train"][0]
    # label times are the ground-truth times whose 1 s window lies inside the audio
    gt_times = recording.ground_truth.timestamps
    assert np.array_equal(samples.times, gt_times[gt_times - 1.0 >= recording.audio.t0 - 1e-9])
    assert np.allclose(samples.pseudo[samples.pseudo_valid], samples.gt[samples.pseudo_valid] + 0.25)
    gap = (samples.times >= gt_times[25]) & (samples.times <= gt_times[31])
    assert gap.any() and not samples.pseudo_valid[gap].any() and samples.pseudo_valid[~gap].all()
    assert samples.class_id == 3  # avata
    assert sum(module.skipped.values()) > 0  # the first second of each recording has no full window


def test_target_modes_hide_what_the_loss_must_not_see(labelled_dir, tmp_path):
    pseudo_only = _module(labelled_dir, tmp_path, targets="pseudo")
    assert not pseudo_only.sequences["train"][0].gt_valid.any()
    gt_only = _module(labelled_dir, tmp_path, targets="ground_truth")
    assert not gt_only.sequences["train"][0].pseudo_valid.any()


def test_darkness_changes_the_image_not_the_audio(simulated_dir, tmp_path):
    only_test = {"test": ["sim11-0002-mavic2"]}
    module = _module(simulated_dir, tmp_path, "test", inputs={"audio_mel": "avfdti", "image": "resnet256"},
                     split=only_test)
    ideal, dark = (next(iter(loader)) for loader in module.test_dataloader())
    assert torch.equal(ideal["audio_mel"], dark["audio_mel"])
    assert not torch.equal(ideal["image"], dark["image"])
    assert torch.allclose(dark["image"], torch.full_like(dark["image"], 3 / 127.5 - 1))
    assert not dark["visible"].any() and dark["dark"].all() and not ideal["dark"].any()

    physical = _module(simulated_dir, tmp_path, "test", inputs={"image": "resnet256"}, dark_mode="physical",
                       split=only_test)
    ideal_p, dark_p = (next(iter(loader)) for loader in physical.test_dataloader())
    assert dark_p["image"].mean() < ideal_p["image"].mean() - 0.3
    assert dark_p["image"].std() > 0.01  # a noisy low-light frame, not a constant
    assert torch.equal(dark_p["visible"], ideal_p["visible"])  # geometry still decides visibility


def test_cache_is_reused_identical_and_rebuilt_for_another_recipe(simulated_dir, tmp_path):
    first = _module(simulated_dir, tmp_path)
    files = sorted((tmp_path / "cache").glob("*.npy"))
    stamps = [f.stat().st_mtime_ns for f in files]
    again = _module(simulated_dir, tmp_path)
    assert [f.stat().st_mtime_ns for f in sorted((tmp_path / "cache").glob("*.npy"))] == stamps
    a = first.train_dataloader().dataset[3]["audio_mel"]
    b = again.train_dataloader().dataset[3]["audio_mel"]
    assert torch.equal(a, b)
    from datamodules.features import audio_window, mel_features, mel_recipe

    recording = open_recording(first.sequences["train"][0].path)
    t = first.sequences["train"][0].times[3]
    direct = mel_features(audio_window(recording.audio, t, mel_recipe("aaute"), 1.0), 48000, mel_recipe("aaute"))
    assert torch.equal(a, direct)
    _module(simulated_dir, tmp_path, window_seconds=0.5)
    assert len(list((tmp_path / "cache").glob("*.npy"))) == 2 * len(files)



def test_a_second_resize_is_applied_on_reading_and_shares_the_cached_map(simulated_dir, tmp_path):
    from datamodules.features import audio_window, mel_features, mel_recipe

    base = _module(simulated_dir, tmp_path, inputs={"audio_mel": "avfdti"})
    files = sorted((tmp_path / "cache").glob("mel-*.npy"))
    resized = _module(simulated_dir, tmp_path, inputs={"audio_mel": "avfdti_224"})
    assert sorted((tmp_path / "cache").glob("mel-*.npy")) == files  # no second entry: the 64 x 64 maps are shared
    item = resized.train_dataloader().dataset[3]["audio_mel"]
    assert tuple(item.shape) == (4, 224, 224)
    assert tuple(base.train_dataloader().dataset[3]["audio_mel"].shape) == (4, 64, 64)
    recording = open_recording(resized.sequences["train"][0].path)
    t = resized.sequences["train"][0].times[3]
    recipe = mel_recipe("avfdti_224")
    direct = mel_features(audio_window(recording.audio, t, recipe, 1.0), 48000, recipe)
    assert torch.allclose(item, direct, rtol=0.0, atol=1e-6)  # the same resize, batched or not: float32 rounding

def _fake(sequence_id: str, drone: str) -> Recording:
    return Recording(sequence_id, drone, ground_truth=Track([0.0, 0.1], [[0, 0, 0], [0, 0, 1]]))


def test_seeded_split_is_by_sequence_stratified_and_stable(tmp_path):
    module = MMAUDDataModule(str(tmp_path), split={"seed": 3, "val": 0.2, "test": 0.2})
    drones = ["avata", "m300", "mavic2", "mavic3", "phantom4"]
    recordings = [(tmp_path / f"r{i}.mcap", _fake(f"r{i}", drones[i % 5])) for i in range(25)]
    assignment = module._assign_splits(recordings)
    assert assignment == module._assign_splits(recordings)
    for drone in drones:
        names = [a for (_, rec), a in zip(recordings, assignment, strict=True) if rec.drone == drone]
        assert names.count("val") == 1 and names.count("test") == 1 and names.count("train") == 3
    with pytest.raises(ValueError, match="listed in both"):
        MMAUDDataModule(str(tmp_path), split={"train": ["r1"], "test": ["r1"]})._assign_splits(recordings)
    with pytest.raises(RecordingError, match="not found"):
        MMAUDDataModule(str(tmp_path), split={"train": ["nope"]})._assign_splits(recordings)


def test_missing_inputs_and_bad_settings_are_explained(simulated_dir, tmp_path):
    with pytest.raises(ValueError, match="unknown audio recipe"):
        MMAUDDataModule(str(simulated_dir), inputs={"audio_mel": "mfcc"})
    with pytest.raises(ValueError, match="unknown input"):
        MMAUDDataModule(str(simulated_dir), inputs={"lidar": "raw"})
    with pytest.raises(RecordingError, match="no recordings found"):
        _module(tmp_path / "empty_folder_that_exists", tmp_path) if (tmp_path / "empty_folder_that_exists").mkdir() \
            is None else None


def test_datamodule_from_yaml(simulated_dir, tmp_path):
    from jsonargparse import ArgumentParser

    config = tmp_path / "data.yaml"
    config.write_text(
        f"data:\n  root: {simulated_dir}\n  split:\n    train: [sim11-0000-avata]\n    test: [sim11-0001-m300]\n"
        f"  window_seconds: 1.0\n  inputs:\n    audio_mel: avfdti_13\n  cache_dir: {tmp_path / 'cache'}\n"
    )
    parser = ArgumentParser()
    parser.add_class_arguments(MMAUDDataModule, "data")
    module = parser.instantiate_classes(parser.parse_path(str(config))).data
    module.prepare_data()
    batch = next(iter(module.test_dataloader()[0]))
    assert tuple(batch["audio_mel"].shape[1:]) == (4, 13, 13)


def test_derived_layout_with_list_file_splits_and_reader_options(tmp_path):
    root = tmp_path / "Data-M"
    truth = make_derived(root, {"0": 30, "3": 25, "7": 25}, images=False)
    lists = root / "annotation"
    lists.mkdir()
    for name, seq in (("train", "0"), ("val", "3"), ("test", "7")):
        (lists / f"{name}.txt").write_text("\n".join(f"{seq}/{i}.npy" for i in range(25)) + "\n")
    split = {name: str(lists / f"{name}.txt") for name in ("train", "val", "test")}
    modules = {}
    for rate in (46080, 48000):
        modules[rate] = _module(root, tmp_path, split=split, window_seconds=0.05, inputs={"audio_mel": "avfdti"},
                                label_rate=200.0, reader_options={"sample_rate": rate})
    module = modules[46080]
    assert [s.sequence_id for s in module.sequences["train"]] == ["0"]
    assert [s.sequence_id for s in module.sequences["test"]] == ["7"]
    test = module.sequences["test"][0]
    # labels sit at chunk ends, one chunk of CHUNK samples apart at the configured rate
    assert np.allclose(np.diff(test.times), CHUNK / 46080)
    assert np.allclose(np.diff(modules[48000].sequences["test"][0].times), CHUNK / 48000)
    assert np.allclose(test.gt, truth["7"]["gt"][-test.gt.shape[0]:])
    batch = next(iter(module.test_dataloader()[0]))
    assert tuple(batch["audio_mel"].shape[1:]) == (4, 64, 64)
    assert bool(batch["pseudo_valid"].all())
    with pytest.raises(ValueError, match="listed in both"):
        _module(root, tmp_path, split={"train": split["train"], "test": split["train"]},
                inputs={"audio_mel": "avfdti"}, window_seconds=0.05)


def test_ug2_folders_feed_an_image_model_and_refuse_an_audio_one(tmp_path):
    for k in range(3):
        make_ug2_sequence(tmp_path / "ug2" / "train" / f"seq{k}", frames=12, seed=k)
    module = _module(tmp_path / "ug2" / "train", tmp_path, inputs={"image": "resnet256"}, targets="ground_truth",
                     split={"train": ["train_seq0"], "val": ["train_seq1"], "test": ["train_seq2"]})
    samples = module.sequences["test"][0]
    assert len(samples) == 12 and samples.gt_valid.all() and samples.drone == "m300"
    batch = next(iter(module.test_dataloader()[0]))
    assert tuple(batch["image"].shape[1:]) == (3, 256, 256)
    real = shared_data_dir() / "mmaud_ug2_val_seq1"
    if real.exists():  # LiDAR only: an audio model is refused by name, not fed silence
        with pytest.raises(RecordingError, match="neither ground truth nor pseudo-labels|has none"):
            _module(real, tmp_path, split={"test": ["mmaud_ug2_val_seq1"]})
