"""Converters from the original authors' layouts, on synthetic state dicts with the original names and shapes."""

from __future__ import annotations

import hashlib

import pytest
import torch
from torch.nn import functional as F

from tests.zoo import original_layouts as originals
from zoo.checkpoints import CheckpointError, WeightsMismatchError
from zoo.cli import main
from zoo.converters import FORMATS, UnknownLayoutError, convert_state, to_original
from zoo.registry import get_model
from zoo.weights import load_pretrained
from zoo.weights_cli import FORMATS as CLI_FORMATS

CASES = [
    ("aaute", originals.aaute_student, "student"),
    ("avfdti-comparison", originals.comparison_audionet, "audionet"),
    ("avfdti-comparison", originals.comparison_visualnet, "visualnet"),
    ("avfdti-comparison", originals.comparison_avped, "avped"),
    ("avfdti-comparison", originals.comparison_voranet, "voranet"),
    ("avfdti-comparison", originals.comparison_darknet, "darknet"),
    ("avfdti", originals.avfdti, "avfdti"),
    ("avped", originals.avpedaware, "avped"),
]


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("AAUTE_CACHE", str(tmp_path / "cache"))


def _net(conversion):
    """A fresh zoo net with the converted state dict loaded strictly (no missing or unexpected keys)."""
    net = get_model(conversion.layout.model, **conversion.net_kwargs).eval()
    net.load_state_dict(conversion.state_dict, strict=True)
    return net


AUDIO_ONLY = {"student", "audionet", "voranet"}


def test_the_command_line_knows_every_format():
    assert CLI_FORMATS == FORMATS


@pytest.mark.parametrize(("fmt", "build", "model"), CASES, ids=[case[1].__name__ for case in CASES])
def test_conversion_is_complete_and_deterministic(fmt, build, model):
    original = build()
    first, second = convert_state(original, fmt), convert_state(dict(reversed(original.items())), fmt)
    assert first.layout.model == model
    assert list(first.state_dict) == list(second.state_dict)  # the file's key order does not matter
    assert all(torch.equal(first.state_dict[key], second.state_dict[key]) for key in first.state_dict)
    net = first.net  # loaded strictly: no missing or unexpected keys
    mapped = set(first.renamed.values())
    assert mapped.isdisjoint(first.dropped) and mapped | set(first.dropped) == set(original)
    for ours, theirs in first.renamed.items():
        if ours not in ("head.position.4.weight", "head.position.4.bias"):  # AV-PedAware's box head is cut to 3
            assert torch.equal(net.state_dict()[ours], original[theirs])
    if model in AUDIO_ONLY:  # the image nets' forwards are checked by the visualnet test below
        with torch.no_grad():
            outputs = net(net.example_inputs(1))
        assert torch.isfinite(outputs["position"]).all()


def test_dead_parameters_are_the_documented_ones():
    assert {key.split(".")[0] for key in convert_state(originals.aaute_student(), "aaute").dropped} == {
        "bn1", "bn2", "bn3", "bn4"}
    dropped = convert_state(originals.avfdti(), "avfdti").dropped
    assert {key for key in dropped if not key.startswith("visualnet.resnet_feature.")} == {
        f"audionet.{name}.{p}" for name in ("convt3", "convf3") for p in ("weight", "bias")} | {
        f"audionet.bn{i}.{p}" for i in range(1, 5) for p in
        ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")} | {
        f"detection.position_est{i}.{p}" for i in range(1, 4) for p in ("weight", "bias")}
    conversion = convert_state(originals.avfdti(decoder_convs=1), "avfdti")
    assert conversion.net_kwargs["decoder_convs"] == 1 and conversion.net.heatmap.size == 512


def _aaute_forward(state: dict[str, torch.Tensor], mel: torch.Tensor) -> torch.Tensor:
    """The AAUTE student's forward in eval mode, computed directly from the original tensors."""
    branches = [F.relu(F.conv2d(mel, state[f"{name}.weight"], state[f"{name}.bias"])).flatten(1)
                for name in ("convt1", "convt2", "convf1", "convf2")]
    x = F.relu(F.linear(torch.cat(branches, dim=1), state["fc_audio.weight"], state["fc_audio.bias"]))
    x = F.relu(F.linear(x, state["position_est1.weight"], state["position_est1.bias"]))
    x = F.relu(F.linear(x, state["position_est2.weight"], state["position_est2.bias"]))
    return F.linear(x, state["position_est3.weight"], state["position_est3.bias"])


def test_the_converted_student_computes_what_the_original_weights_compute():
    original = originals.aaute_student(seed=3)
    net = _net(convert_state({f"module.{k}": v for k, v in original.items()}, "aaute"))  # DataParallel's prefix
    mel = net.example_inputs(4)["audio_mel"]
    with torch.no_grad():
        assert torch.allclose(net({"audio_mel": mel})["position"], _aaute_forward(original, mel), atol=1e-6)


def test_the_converted_visualnet_computes_what_the_original_weights_compute():
    from torchvision.models import resnet50

    original = originals.comparison_visualnet(seed=5)
    net = _net(convert_state({"state_dict": original}, "avfdti-comparison"))
    resnet = resnet50(weights=None).eval()
    resnet.load_state_dict({k[len("visualnet.resnet_model."):]: v for k, v in original.items()
                            if k.startswith("visualnet.resnet_model.")})
    trunk = torch.nn.Sequential(*list(resnet.children())[:-2])
    image = net.example_inputs(2)["image"]

    def mlp(x: torch.Tensor, name: str) -> torch.Tensor:
        for i in (1, 2, 3):
            x = F.linear(x, original[f"detectnet.{name}{i}.weight"], original[f"detectnet.{name}{i}.bias"])
            x = F.relu(x) if i < 3 else x
        return x

    with torch.no_grad():
        y = F.relu(F.conv2d(trunk(image), original["visualnet.convres.weight"], original["visualnet.convres.bias"],
                            padding=1))
        y = F.relu(F.conv2d(y, original["visualnet.convvis.weight"], original["visualnet.convvis.bias"], padding=1))
        feature = F.relu(F.linear(y.flatten(1), original["visualnet.fcvis.weight"], original["visualnet.fcvis.bias"]))
        outputs = net({"image": image})
    assert torch.allclose(outputs["position"], mlp(feature, "position_est"), atol=1e-5)
    assert torch.allclose(outputs["class_logits"], mlp(feature, "cls"), atol=1e-5)


def test_avpedaware_keeps_the_box_centre_of_its_seven_outputs():
    original = originals.avpedaware(seed=2)
    conversion = convert_state(original, "avped")
    assert torch.equal(conversion.state_dict["head.position.4.weight"], original["position_est3.weight"][:3])
    net = conversion.net
    assert net.in_channels == 8 and net.inputs["audio_mel"] == "aaute" and not hasattr(net.head, "classes")


def test_an_unknown_layout_lists_the_recognised_ones_and_the_keys_that_did_not_match():
    state = {"encoder.layer0.weight": torch.zeros(3, 3), "decoder.out.bias": torch.zeros(3)}
    with pytest.raises(UnknownLayoutError) as error:
        convert_state(state, "avfdti-comparison", "theirs.pth")
    message = str(error.value)
    assert "matches no avfdti-comparison layout" in message and "--format aaute: aaute (AudioNet" in message
    assert "first keys that did not match: encoder.layer0.weight, decoder.out.bias" in message
    with pytest.raises(UnknownLayoutError, match=r"it looks like --format aaute"):
        convert_state(originals.aaute_student(), "avfdti-comparison")


def test_a_shape_that_does_not_fit_names_the_parameter_and_both_shapes():
    state = originals.aaute_student()
    state["fc_audio.weight"] = torch.zeros(512, 3900)
    with pytest.raises(WeightsMismatchError, match=r"fc_audio.weight -> encoder.project.0.weight has shape 512x3900, "
                                                   r"the student net .* needs 512x3904"):
        convert_state(state, "aaute", "bad.pth")
    state = originals.aaute_student()
    state["extra.weight"] = torch.zeros(2)
    with pytest.raises(WeightsMismatchError, match=r"bad.pth: 1 key\(s\) unknown to the aaute layout .*extra.weight"):
        convert_state(state, "aaute", "bad.pth")


def test_two_views_of_a_module_must_agree():
    state = originals.comparison_darknet()
    state["classifier.0.conv.weight"] = state["classifier.0.conv.weight"] + 1
    with pytest.raises(WeightsMismatchError, match="two views of backbone.0.conv.weight"):
        convert_state(state, "avfdti-comparison")


def test_import_checkpoint_command_writes_a_self_describing_file(tmp_path, capsys):
    original = originals.aaute_student(seed=4)
    source = tmp_path / "audio_net_best.pth"
    torch.save(original, source)
    out = tmp_path / "student_aaute.pt"
    args = ["import-checkpoint", "--format", "aaute", str(source), "--out", str(out), "--register", "paper"]
    assert main(args) == 0
    first = hashlib.sha256(out.read_bytes()).hexdigest()
    assert main([*args, "--overwrite"]) == 0 and hashlib.sha256(out.read_bytes()).hexdigest() == first
    net = load_pretrained("student", "paper")
    mel = net.example_inputs(2)["audio_mel"]
    with torch.no_grad():
        assert torch.allclose(net({"audio_mel": mel})["position"], _aaute_forward(original, mel), atol=1e-6)
    assert net.pretrained["provenance"]["layout"] == "aaute"
    evil = tmp_path / "pickled_model.pth"
    torch.save(torch.nn.Linear(2, 2), evil)
    capsys.readouterr()
    assert main(["import-checkpoint", "--format", "aaute", str(evil), "--out", str(tmp_path / "x.pt")]) == 2
    assert f"{evil}: refused: its pickle needs code" in capsys.readouterr().err
    assert not (tmp_path / "x.pt").exists()
    assert main(["import-checkpoint", "--format", "aaute", str(source), "--out", str(out)]) == 2  # exists


def test_the_student_written_in_the_aaute_layout_converts_back_unchanged():
    original = originals.aaute_student(seed=6)
    net = convert_state(original, "aaute").net
    written = to_original(net, "aaute")
    assert set(written) == set(original)
    assert all(torch.equal(written[key], original[key]) for key in original if not key.startswith("bn"))
    back = convert_state(written, "aaute")
    assert all(torch.equal(back.state_dict[key], value) for key, value in net.state_dict().items())
    with pytest.raises(CheckpointError, match="only the student"):
        to_original(get_model("audionet"), "aaute")
