"""Converters from the original authors' layouts, on synthetic state dicts with the original names and shapes."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from functools import lru_cache

import pytest
import torch
from torch.nn import functional as F

from tests.helpers import original_layouts as originals
from zoo.cli import main
from zoo.cli.weights import FORMATS as CLI_FORMATS
from zoo.registry import get_model
from zoo.weights import load_pretrained
from zoo.weights.converters import FORMATS, Conversion, UnknownLayoutError, convert_state, to_original
from zoo.weights.files import CheckpointError, WeightsMismatchError

CASES = [
    ("aaute", originals.aaute_student, "student"),
    ("avfdti-comparison", originals.comparison_audionet, "audionet"),
    ("avfdti-comparison", originals.comparison_visualnet, "visualnet"),
    ("avfdti-comparison", originals.comparison_avped, "avped"),
    ("avfdti-comparison", originals.comparison_voranet, "voranet"),
    ("avfdti-comparison", originals.comparison_darknet, "darknet"),
    ("avfdti-comparison", originals.comparison_asdnet, "asdnet"),
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


@lru_cache(maxsize=3)
def _converted(fmt: str, build: Callable[[], dict[str, torch.Tensor]]) -> Conversion:
    """The conversion of ``build()``, shared by the tests that only read it (the last three big nets kept)."""
    return convert_state(build(), fmt)


def test_the_command_line_knows_every_format():
    assert CLI_FORMATS == FORMATS


@pytest.mark.parametrize(("fmt", "build", "model"), CASES, ids=[case[1].__name__ for case in CASES])
def test_conversion_is_complete_and_deterministic(fmt, build, model):
    original = build()
    first, second = _converted(fmt, build), convert_state(dict(reversed(original.items())), fmt)
    assert first.layout.model == model
    assert list(first.state_dict) == list(second.state_dict)  # the file's key order does not matter
    assert all(torch.equal(first.state_dict[key], second.state_dict[key]) for key in first.state_dict)
    net = first.net  # loaded strictly: no missing or unexpected keys
    mapped = set(first.renamed.values())
    assert mapped.isdisjoint(first.dropped) and mapped | set(first.dropped) == set(original)
    loaded = net.state_dict()
    for ours, theirs in first.renamed.items():
        if ours not in ("head.position.4.weight", "head.position.4.bias"):  # AV-PedAware's box head is cut to 3
            value = original[theirs]
            if theirs.endswith((".gamma", ".beta")):  # TalkNet's global LayerNorm (1 x C x 1): a C-vector here
                value = value.flatten()
            assert torch.equal(loaded[ours], value)
    if model in AUDIO_ONLY:  # the image nets' forwards are checked by the visualnet test below
        with torch.no_grad():
            outputs = net(net.example_inputs(1))
        assert torch.isfinite(outputs["position"]).all()


def test_dead_parameters_are_the_documented_ones():
    assert {key.split(".")[0] for key in _converted("aaute", originals.aaute_student).dropped} == {
        "bn1", "bn2", "bn3", "bn4"}
    dropped = _converted("avfdti", originals.avfdti).dropped
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

    original = originals.comparison_visualnet()
    net = _net(convert_state({"state_dict": original}, "avfdti-comparison"))
    resnet = resnet50(weights=None).eval()
    resnet.load_state_dict({k[len("visualnet.resnet_model."):]: v for k, v in original.items()
                            if k.startswith("visualnet.resnet_model.")})
    trunk = torch.nn.Sequential(*list(resnet.children())[:-2])
    image = net.example_inputs(1)["image"]

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
    original = originals.avpedaware()
    conversion = _converted("avped", originals.avpedaware)
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


# ------------------------------------------------------------------------------- ASDNet (TalkNet adaptation)

#: original names and shapes that talkNetModel's state dict holds (read from its published modules)
TALKNET_KEYS = {
    "visualFrontend.frontend3D.0.weight": (64, 1, 5, 7, 7),
    "visualFrontend.frontend3D.1.running_var": (64,),
    "visualFrontend.resnet.layer1.conv1a.weight": (64, 64, 3, 3),
    "visualFrontend.resnet.layer1.downsample.weight": (64, 64, 1, 1),  # declared, unused at stride 1
    "visualFrontend.resnet.layer2.downsample.weight": (128, 64, 1, 1),
    "visualFrontend.resnet.layer4.outbnb.num_batches_tracked": (),
    "visualTCN.net.0.net.1.running_mean": (512,),
    "visualTCN.net.0.net.2.weight": (512, 1, 3),
    "visualTCN.net.2.net.3.weight": (1,),
    "visualTCN.net.4.net.4.gamma": (1, 512, 1),
    "visualTCN.net.4.net.4.beta": (1, 512, 1),
    "visualTCN.net.4.net.5.weight": (512, 512, 1),
    "visualConv1D.net.0.weight": (256, 512, 5),
    "visualConv1D.net.3.bias": (128,),
    "audioEncoder.conv1.weight": (16, 4, 8, 8),
    "audioEncoder.bn1.num_batches_tracked": (),
    "audioEncoder.layer1.2.se.fc.0.weight": (2, 16),
    "audioEncoder.layer2.0.downsample.0.weight": (32, 16, 1, 1),
    "audioEncoder.layer3.5.se.fc.2.weight": (64, 8),
    "audioEncoder.layer4.0.downsample.1.running_mean": (128,),
    "audioEncoder.layer4.2.conv2.weight": (128, 128, 3, 3),
    "crossA2V.self_attn.in_proj_weight": (384, 128),
    "crossV2A.self_attn.out_proj.bias": (128,),
    "selfAV.linear1.weight": (1024, 256),
    "selfAV.norm2.bias": (256,),
    "detectnet.position_est1.weight": (256, 256),
    "detectnet.traj3.weight": (30, 128),
    "fc.weight": (100, 768),
    "fc_p.weight": (3, 100),
    "fc_c.bias": (6,),
}
TALKNET_ABSENT = ("audioEncoder.layer1.0.downsample.0.weight", "visualFrontend.resnet.avgpool.weight")
BUFFERS = ("running_mean", "running_var", "num_batches_tracked")


@pytest.fixture(scope="module")
def asdnet_original():
    return originals.comparison_asdnet(seed=8)


@pytest.fixture(scope="module")
def asdnet_conversion(asdnet_original):
    return convert_state({f"module.{k}": v for k, v in asdnet_original.items()}, "avfdti-comparison")  # DataParallel


def test_the_synthetic_talknet_has_the_published_names_shapes_and_parameter_count(asdnet_original):
    assert {key: tuple(asdnet_original[key].shape) for key in TALKNET_KEYS} == TALKNET_KEYS
    assert not any(key in asdnet_original for key in TALKNET_ABSENT)
    parameters = sum(value.numel() for key, value in asdnet_original.items() if not key.endswith(BUFFERS))
    assert parameters == 16_125_667  # reference/baselines.md section 11: 16.13 M in total


def _talknet_name(key: str) -> str:
    """talkNetModel's name of one of our ASDNet keys (the inverse direction of the converter's renames)."""
    parts = key.split(".")
    top = {"visual_conv1d": "visualConv1D.net", "cross_a2v": "crossA2V", "cross_v2a": "crossV2A", "self_av": "selfAV",
           "position": "fc_p", "classes": "fc_c"}
    if parts[0] == "visual_frontend" and parts[1] == "frontend3d":
        return ".".join(["visualFrontend.frontend3D", *parts[2:]])
    if parts[0] == "visual_frontend":
        return ".".join([f"visualFrontend.resnet.layer{int(parts[2]) + 1}", *parts[3:]])
    if parts[0] == "visual_tcn":
        if parts[3] == "4":
            parts[4] = {"weight": "gamma", "bias": "beta"}[parts[4]]
        return ".".join(["visualTCN.net", *parts[1:]])
    if parts[0] == "audio_encoder" and parts[1] == "stem":
        return ".".join([{"0": "audioEncoder.conv1", "1": "audioEncoder.bn1"}[parts[2]], *parts[3:]])
    if parts[0] == "audio_encoder":
        if parts[4] == "se":
            parts[5] = {"2": "fc.0", "4": "fc.2"}[parts[5]]
        return ".".join([f"audioEncoder.layer{int(parts[2]) + 1}", *parts[3:]])
    if parts[0] == "fc":
        return ".".join(["fc", *parts[2:]])
    return ".".join([top[parts[0]], *parts[1:]])


def test_the_converted_asdnet_computes_what_the_net_loaded_directly_computes(asdnet_original, asdnet_conversion):
    direct = get_model("asdnet").eval()
    shapes = {key: value.shape for key, value in direct.state_dict().items()}
    direct.load_state_dict({key: asdnet_original[_talknet_name(key)].reshape(shape) for key, shape in shapes.items()},
                           strict=True)
    used = {_talknet_name(key) for key in shapes}
    assert set(asdnet_original) - used == {key for key in asdnet_original if key.startswith("detectnet.")} | {
        "visualFrontend.resnet.layer1.downsample.weight"}
    assert set(asdnet_conversion.dropped) == set(asdnet_original) - used  # named without the module. prefix
    assert asdnet_conversion.net_kwargs == {"in_channels": 4, "num_classes": 6}
    inputs = direct.example_inputs(1)
    with torch.no_grad():
        converted, expected = asdnet_conversion.net(inputs), direct(inputs)
    assert all(torch.equal(converted[name], expected[name]) for name in ("position", "class_logits"))
    assert converted["class_logits"].shape == (1, 6) and torch.isfinite(converted["position"]).all()


def test_the_global_layer_norm_becomes_an_equivalent_group_norm(asdnet_original, asdnet_conversion):
    gamma, beta = asdnet_original["visualTCN.net.3.net.4.gamma"], asdnet_original["visualTCN.net.3.net.4.beta"]
    y = torch.randn(2, 512, 3, generator=torch.Generator().manual_seed(1))
    mean = y.mean(dim=(1, 2), keepdim=True)  # TalkNet's gLN: statistics over channels and time, eps 1e-8
    global_layer_norm = gamma * (y - mean) / ((y - mean).pow(2).mean(dim=(1, 2), keepdim=True) + 1e-8).sqrt() + beta
    with torch.no_grad():
        ours = asdnet_conversion.net.visual_tcn[3].net[4](y)
    assert torch.allclose(ours, global_layer_norm, atol=1e-5)


def test_an_asdnet_file_with_a_wrong_shape_names_the_parameter_and_both_shapes(asdnet_original):
    state = dict(asdnet_original)
    state["crossV2A.linear1.weight"] = torch.zeros(512, 100)
    with pytest.raises(WeightsMismatchError, match=r"asd.pth: crossV2A.linear1.weight -> cross_v2a.linear1.weight "
                                                   r"has shape 512x100, the asdnet net .* needs 512x128"):
        convert_state(state, "avfdti-comparison", "asd.pth")
    state = dict(asdnet_original)
    state["visualTCN.net.2.net.4.gamma"] = torch.ones(1, 256, 1)
    with pytest.raises(WeightsMismatchError, match=r"visualTCN.net.2.net.4.gamma -> visual_tcn.2.net.4.weight has "
                                                   r"shape 1x256x1 \(256 once reshaped\), the asdnet net .* needs 512"):
        convert_state(state, "avfdti-comparison", "asd.pth")


def test_import_checkpoint_converts_an_asdnet_file_that_load_pretrained_reads(tmp_path, asdnet_original,
                                                                             asdnet_conversion):
    source, out = tmp_path / "asd.pth", tmp_path / "x.pt"
    torch.save({"state_dict": asdnet_original}, source)
    assert main(["import-checkpoint", "--format", "avfdti-comparison", str(source), "--out", str(out)]) == 0
    net = load_pretrained("asdnet", weights=str(out))
    assert net.pretrained["layout"] == "asdnet" and net.pretrained["format"] == "avfdti-comparison"
    converted = asdnet_conversion.state_dict
    assert all(torch.equal(value, converted[key]) for key, value in net.state_dict().items())
