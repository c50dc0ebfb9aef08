"""aaute export: the self-describing checkpoint and the ONNX file, checked against PyTorch with onnxruntime."""

from __future__ import annotations

import json
import sys

import pytest
import torch

from tests.helpers.filesystem import deny_writes_under
from zoo.cli import main
from zoo.deploy.export import ExportError, export, export_onnx
from zoo.registry import get_model
from zoo.weights import load_pretrained, save_weights_file

onnx = pytest.importorskip("onnx")
onnxruntime = pytest.importorskip("onnxruntime")


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("AAUTE_CACHE", str(tmp_path / "cache"))


def test_export_writes_a_checkpoint_loadable_alone_and_an_onnx_file_equal_to_pytorch(tmp_path):
    torch.manual_seed(0)
    net = get_model("student", kernels=8, feature_dim=64).eval()
    source = save_weights_file(net, tmp_path / "trained.pt", {"kernels": 8, "feature_dim": 64}, {"data": "unit"})
    stem = tmp_path / "deploy" / "student"
    assert main(["export", "--weights", str(source), "--out", str(stem), "--original-format", "aaute"]) == 0

    loaded = load_pretrained("student", stem.with_suffix(".pt"))  # no config: the file describes the net
    mel = torch.rand(5, 4, 64, 64, generator=torch.Generator().manual_seed(7))
    with torch.no_grad():
        expected = net({"audio_mel": mel})["position"]
        assert torch.equal(loaded({"audio_mel": mel})["position"], expected)
    assert loaded.pretrained["provenance"]["source"] == str(source)

    model = onnx.load(str(stem.with_suffix(".onnx")))
    metadata = {entry.key: entry.value for entry in model.metadata_props}
    assert metadata["aaute.net"] == "student"
    assert json.loads(metadata["aaute.inputs"]) == {"audio_mel": {"recipe": "aaute", "shape": ["B", 4, 64, 64]}}
    assert json.loads(metadata["aaute.net_kwargs"]) == {"kernels": 8, "feature_dim": 64}
    session = onnxruntime.InferenceSession(str(stem.with_suffix(".onnx")), providers=["CPUExecutionProvider"])
    (position,) = session.run(["position"], {"audio_mel": mel.numpy()})
    assert float((torch.from_numpy(position) - expected).abs().max()) <= 1e-5
    assert main(["export", "--weights", str(source), "--out", str(stem)]) == 2  # never overwritten silently

    original = torch.load(stem.with_name("student_aaute.pth"), weights_only=True)  # AAUTE's AudioNet layout
    assert {"convt1.weight", "fc_audio.bias", "position_est3.weight", "bn4.running_var"} <= set(original)
    imported = tmp_path / "imported.pt"
    assert main(["import-checkpoint", "--format", "aaute", str(stem.with_name("student_aaute.pth")),
                 "--out", str(imported)]) == 0
    with torch.no_grad():
        assert torch.equal(load_pretrained("student", imported)({"audio_mel": mel})["position"], expected)


def test_an_onnx_file_that_disagrees_is_not_kept(tmp_path):
    net = get_model("student", kernels=4, feature_dim=16).eval()
    with pytest.raises(ExportError, match="onnxruntime's outputs differ from PyTorch's"):
        export_onnx(net, tmp_path / "student.onnx", {}, relative=-1.0)  # any difference is too large
    assert list(tmp_path.iterdir()) == []


def test_an_image_net_gets_the_checkpoint_and_no_onnx_by_default(tmp_path):
    net = get_model("visualnet").eval()
    done = export(net, tmp_path / "visualnet", {}, {"source": "random"})
    assert done.onnx is None and done.checkpoint.is_file() and not (tmp_path / "visualnet.onnx").exists()
    assert load_pretrained("visualnet", done.checkpoint).inputs == {"image": "resnet256"}


def test_export_without_onnx_installed_is_one_line_exit_2_and_writes_nothing(tmp_path, monkeypatch, capsys):
    net = get_model("student", kernels=4, feature_dim=16).eval()
    source = save_weights_file(net, tmp_path / "trained.pt", {"kernels": 4, "feature_dim": 16})
    for name in ("onnx", "onnxruntime"):  # None in sys.modules: ``import onnx`` raises ImportError, as if absent
        monkeypatch.setitem(sys.modules, name, None)
    out = tmp_path / "deploy"
    out.mkdir()
    assert main(["export", "--weights", str(source), "--out", str(out / "student")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("aaute: error: ONNX export needs onnx and onnxruntime")
    assert "pip install -e '.[export]'" in err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert list(out.iterdir()) == []  # neither <out>.onnx nor <out>.pt


def test_outputs_of_hundreds_of_metres_pass_within_float32_rounding_of_their_scale(tmp_path):
    torch.manual_seed(0)
    net = get_model("student").eval()
    last = [module for module in net.head.modules() if isinstance(module, torch.nn.Linear)][-1]
    with torch.no_grad():  # positions of some hundreds of metres: rounding beyond an absolute 1e-5
        last.weight.mul_(1e4)
        last.bias.mul_(1e4)
    done = export(net, tmp_path / "student", {}, {"source": "scaled"})
    assert done.onnx.is_file() and 1e-5 < done.max_difference < 1e-2


def test_a_failed_export_removes_every_file_it_wrote(tmp_path, monkeypatch, capsys):
    net = get_model("student", kernels=4, feature_dim=16).eval()
    source = save_weights_file(net, tmp_path / "trained.pt", {"kernels": 4, "feature_dim": 16})
    out = tmp_path / "deploy"
    out.mkdir()

    def refuse(*args, **kwargs):
        raise ExportError("student.onnx: onnxruntime's outputs differ")

    monkeypatch.setattr("zoo.deploy.export.export_onnx", refuse)
    argv = ["export", "--weights", str(source), "--out", str(out / "student"), "--original-format", "aaute"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("aaute: error: student.onnx") and err.count("\n") == 1
    assert list(out.iterdir()) == []
    monkeypatch.undo()

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("zoo.deploy.export.save_weights_file", full)  # the last file fails: the others go too
    with pytest.raises(OSError, match="No space left"):
        export(net, out / "student", {}, {}, original_format="aaute")
    assert list(out.iterdir()) == []
    monkeypatch.undo()
    assert main(argv) == 0  # and the next try is not refused as "already exists"
    assert sorted(p.name for p in out.iterdir()) == ["student.onnx", "student.pt", "student_aaute.pth"]


def test_export_into_a_folder_it_cannot_write_names_the_file_not_its_temporary(tmp_path, monkeypatch, capsys):
    net = get_model("student", kernels=4, feature_dim=16).eval()
    source = save_weights_file(net, tmp_path / "trained.pt", {"kernels": 4, "feature_dim": 16})
    out = tmp_path / "locked"
    out.mkdir()
    deny_writes_under(monkeypatch, out)
    assert main(["export", "--weights", str(source), "--out", str(out / "student")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"aaute: error: {out / 'student.onnx'}: cannot write into {out}")
    assert ".tmp-" not in err and err.count("\n") == 1
