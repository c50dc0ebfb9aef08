"""The weights registry, safe loading, strict key checks, and the CLI's refusal of another model's checkpoint."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
import torch

from zoo.cli import main
from zoo.registry import get_model
from zoo.weights import (
    Weights,
    WeightsError,
    get_weights,
    list_weights,
    load_pretrained,
    load_task,
    register_weights,
    save_weights_file,
    weights_dir,
)
from zoo.weights.files import CheckpointError, UnsafeCheckpointError, WeightsMismatchError, read_checkpoint

CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "model"
SPLIT = "{train: [sim11-0000-avata], val: [sim11-0001-m300], test: [sim11-0002-mavic2]}"


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch) -> Path:
    """Every test gets its own weights cache and registry."""
    monkeypatch.setenv("AAUTE_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("AAUTE_OFFLINE", raising=False)
    return tmp_path / "cache"


def _common(model: str, labelled_dir: Path, feature_cache: Path, root: Path) -> list[str]:
    return ["--config", str(CONFIGS / f"{model}.yaml"), "--data.root", str(labelled_dir), "--data.split", SPLIT,
            "--data.window_seconds", "1.0", "--data.cache_dir", str(feature_cache),
            "--trainer.default_root_dir", str(root), "--trainer.enable_progress_bar", "false",
            "--data.test_lights", "[ideal]"]


@pytest.fixture(scope="module")
def checkpoints(labelled_dir, feature_cache, tmp_path_factory) -> dict[str, Path]:
    """Real project checkpoints of a one-batch fit: the student and AudioNet."""
    made = {}
    for model in ("student", "audionet"):
        root = tmp_path_factory.mktemp(f"fit_{model}")
        assert main(["fit", *_common(model, labelled_dir, feature_cache, root), "--trainer.max_epochs", "1",
                     "--trainer.limit_train_batches", "1", "--trainer.limit_val_batches", "1"]) == 0
        made[model] = next(root.rglob("*.ckpt"))
    return made


def _example(net) -> dict[str, torch.Tensor]:
    return net.example_inputs(2)


# ---------------------------------------------------------------------------------------------- public face


def test_the_package_exports_the_zoo_entry_points():
    import zoo
    from zoo import get_model as public_get_model
    from zoo import list_models  # noqa: F401
    from zoo import list_weights as public_list_weights
    from zoo import load_pretrained as public_load

    assert "student" in list_models() and public_get_model("student").model_name == "student"
    assert public_load is load_pretrained and public_list_weights is list_weights
    with pytest.raises(AttributeError, match="no attribute 'bogus'"):
        zoo.bogus  # noqa: B018


# ---------------------------------------------------------------------------------------------- safe reading


def test_a_pickle_needing_code_is_refused_with_the_file_and_the_reason(tmp_path):
    path = tmp_path / "model.pt"
    torch.save({"net": torch.nn.Linear(2, 2)}, path)  # a whole pickled module: needs torch.nn code to rebuild
    with pytest.raises(UnsafeCheckpointError) as error:
        read_checkpoint(path)
    message = str(error.value)
    assert str(path) in message and "needs code" in message and "torch.nn.modules.linear.Linear" in message
    assert "weights_only" not in message.replace("weights_only=True", "") and "\n" not in message


def test_a_truncated_file_is_named_as_such(tmp_path):
    good = tmp_path / "good.pt"
    torch.save(get_model("student").state_dict(), good)
    cut = tmp_path / "cut.pt"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(CheckpointError, match=rf"{cut}: truncated or corrupt weights file"):
        read_checkpoint(cut)
    with pytest.raises(FileNotFoundError, match="no such weights file"):
        read_checkpoint(tmp_path / "absent.pt")


NOT_TORCH = {
    "lfs.pt": (b"version https://git-lfs.github.com/spec/v1\noid sha256:" + b"a" * 64 + b"\nsize 4096512\n",
               "a Git LFS pointer to 4,096,512 bytes, not the weights themselves (fetch them with 'git lfs pull')"),
    "page.pt": (b"\n<!DOCTYPE html>\n<html><head><title>Sign in</title></head></html>\n", "an HTML page"),
    "notes.pt": (b"epoch 12: val_loss 0.41\n", "a text file (it starts 'epoch 12: val_loss 0.41')"),
    "noise.pt": (bytes([246, 17, 3, 200, 9, 1, 2, 3]) * 64, "not a torch file (it starts with bytes f6 11 03 c8"),
    "empty.pt": (b"", "an empty file"),
}


@pytest.mark.parametrize("name", sorted(NOT_TORCH))
def test_a_file_that_is_not_a_torch_archive_says_what_it_is(tmp_path, capsys, name):
    content, what = NOT_TORCH[name]
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(CheckpointError, match="expected weights written by torch.save") as error:
        read_checkpoint(path)
    assert str(error.value).startswith(f"{path}: {what}") and "\n" not in str(error.value)
    with pytest.raises(CheckpointError, match=f"{path}: "):
        load_pretrained("student", path)
    for argv in (["import-checkpoint", "--format", "aaute", str(path), "--out", str(tmp_path / "out.pt")],
                 ["track", "--weights", str(path), "--audio", "-", "--channels", "4", "--rate", "48000"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"aaute: error: {path}: {what}") and err.count("\n") == 1


def test_a_state_dict_that_does_not_fit_lists_names_and_shapes(tmp_path):
    state = get_model("student").state_dict()
    state["head.5.weight"] = torch.zeros(7, 128)
    state["extra.bias"] = torch.zeros(4)
    del state["encoder.project.0.bias"]
    path = tmp_path / "bad.pt"
    torch.save(state, path)
    with pytest.raises(WeightsMismatchError) as error:
        load_pretrained("student", path)
    message = str(error.value)
    assert "1 missing (encoder.project.0.bias [512])" in message
    assert "1 unexpected (extra.bias [4])" in message
    assert "head.5.weight: file 7x128, net 3x128" in message


# ---------------------------------------------------------------------------------------------- project checkpoints


def test_a_project_checkpoint_loads_into_the_task_and_into_the_bare_net(checkpoints):
    task = load_task(checkpoints["student"])
    net = load_pretrained("student", checkpoints["student"])
    assert not task.training and not net.training and task.hparams.net == "student"
    inputs = _example(net)
    with torch.no_grad():
        assert torch.equal(task.net(inputs)["position"], net(inputs)["position"])
    state = torch.load(checkpoints["student"], weights_only=True)["state_dict"]
    assert torch.equal(net.state_dict()["head.5.weight"], state["net.head.5.weight"])
    with pytest.raises(WeightsMismatchError, match=r"weights are of model 'audionet', not 'student'"):
        load_pretrained("student", checkpoints["audionet"])


def test_test_refuses_a_checkpoint_of_another_net_and_runs_it_when_asked(checkpoints, labelled_dir, feature_cache,
                                                                          tmp_path, capsys):
    common = _common("student", labelled_dir, feature_cache, tmp_path)
    capsys.readouterr()
    assert main(["test", *common, "--ckpt_path", str(checkpoints["audionet"])]) == 2
    message = capsys.readouterr().err.strip().splitlines()[-1]  # the one-line error
    assert "holds a 'audionet' net but the configured model is 'student'" in message
    assert "--use_checkpoint_model true" in message
    out = tmp_path / "own_model"
    assert main(["predict", *common, "--ckpt_path", str(checkpoints["audionet"]), "--use_checkpoint_model", "true",
                 "--model.predictions_dir", str(out)]) == 0
    assert (out / "sim11-0002-mavic2_ideal.csv").is_file()


def test_predict_with_registered_weights(checkpoints, labelled_dir, feature_cache, tmp_path):
    register_weights(Weights("student.tiny", str(checkpoints["student"]), ""))
    out = tmp_path / "predictions"
    common = _common("student", labelled_dir, feature_cache, tmp_path)
    assert main(["predict", *common, "--weights", "student.tiny", "--model.predictions_dir", str(out)]) == 0
    assert (out / "sim11-0002-mavic2_ideal.csv").is_file()
    exported = save_weights_file(load_pretrained("student", "tiny"), tmp_path / "student.pt", {})
    out2 = tmp_path / "predictions_from_file"
    assert main(["predict", *common, "--weights", str(exported), "--model.predictions_dir", str(out2)]) == 0
    assert (out2 / "sim11-0002-mavic2_ideal.csv").read_text() == (out / "sim11-0002-mavic2_ideal.csv").read_text()
    assert main(["predict", *common, "--weights", "student.bogus"]) == 2


# ---------------------------------------------------------------------------------------------- the registry


def _weights_file(tmp_path: Path, seed: int = 0) -> tuple[Path, torch.nn.Module]:
    torch.manual_seed(seed)
    net = get_model("student", kernels=8, feature_dim=64).eval()
    path = save_weights_file(net, tmp_path / f"student_{seed}.pt", {"kernels": 8, "feature_dim": 64},
                             {"data": "unit test"})
    return path, net


def test_registry_round_trip_with_hash_and_metadata(tmp_path, cache):
    path, net = _weights_file(tmp_path)
    entry = register_weights(Weights("student.unit", str(path), "", data="synthetic", protocol="by_sequence",
                                     metrics={"E_ideal": 1.5}, licence="Apache-2.0"))
    assert entry.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
    assert (cache / "weights" / "registry.json").is_file() and weights_dir() == cache / "weights"
    assert list_weights() == ["student.unit"] and list_weights("audionet") == []
    assert get_weights("unit", "student").metrics == {"E_ideal": 1.5}
    for name in ("unit", "student.unit", None):
        loaded = load_pretrained("student", weights=name)
        inputs = _example(loaded)
        with torch.no_grad():
            assert torch.equal(loaded(inputs)["position"], net(inputs)["position"])
    assert loaded.pretrained["protocol"] == "by_sequence" and not loaded.training
    with pytest.raises(WeightsError, match=r"no weights named 'student.other'; known for student: student.unit"):
        load_pretrained("student", "other")
    with pytest.raises(WeightsError, match="are of model 'student', not 'audionet'"):
        get_weights("student.unit", "audionet")


def test_a_hash_mismatch_is_refused(tmp_path):
    path, _ = _weights_file(tmp_path)
    register_weights(Weights("student.unit", str(path), ""))
    other, _ = _weights_file(tmp_path, seed=1)
    path.write_bytes(other.read_bytes())
    with pytest.raises(WeightsError, match=rf"{path}: sha256 [0-9a-f]{{64}} differs from [0-9a-f]{{64}} registered "
                                           r"for student.unit"):
        load_pretrained("student", "unit")


def test_url_weights_download_once_then_hit_the_cache_and_offline_says_where(tmp_path, cache, monkeypatch):
    path, net = _weights_file(tmp_path)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    register_weights(Weights("student.remote", path.as_uri(), digest))
    monkeypatch.setenv("AAUTE_OFFLINE", "1")
    with pytest.raises(WeightsError) as error:
        load_pretrained("student", "remote")
    cached = cache / "weights" / "files" / f"{digest[:12]}-{path.name}"
    assert f"offline mode, and {cached} is not cached; download {path.as_uri()}" in str(error.value)
    monkeypatch.delenv("AAUTE_OFFLINE")
    load_pretrained("student", "remote")
    assert cached.is_file()
    path.unlink()  # the source is gone: a second load must come from the cache alone
    monkeypatch.setenv("AAUTE_OFFLINE", "1")
    loaded = load_pretrained("student", "remote")
    inputs = _example(loaded)
    with torch.no_grad():
        assert torch.equal(loaded(inputs)["position"], net(inputs)["position"])


def test_a_download_with_the_wrong_hash_keeps_nothing(tmp_path, cache):
    path, _ = _weights_file(tmp_path)
    register_weights(Weights("student.remote", path.as_uri(), "0" * 64))
    with pytest.raises(WeightsError, match="downloaded file has sha256"):
        load_pretrained("student", "remote")
    assert not any((cache / "weights" / "files").glob("*"))
