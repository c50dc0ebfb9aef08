"""Converters from the original authors' checkpoint layouts to the zoo's nets (``aaute import-checkpoint``).

The originals cannot be imported here, so each layout is described by the parameter names and
shapes of its published module (read from the code named in ``reference/baselines.md`` section 0):
which keys identify it, how each key is renamed, which dead parameters are dropped, which keyword
arguments of the zoo's net its shapes imply, and which values need reshaping. A conversion is
complete or refused: every key of the file is either mapped or a known dead parameter, and the
converted state dict fits the net key for key and shape for shape (else the error names the
parameter, its original name and both shapes). ``DataParallel``'s ``module.`` prefix and a
``{"state_dict": ...}`` / ``{"model": ...}`` wrapper are removed first.

Formats and layouts:

- ``aaute``: the AAUTE student, ``AudioNet`` of ``audio_net.py`` (AllenLei666/AAUTE @ a5809f1) -> ``student``;
  its four BatchNorms are declared but never called: dropped.
- ``avfdti``: ``AVFDTI`` of ``nets/AVFDTI.py`` (yizhuoyang/AV-FDTI @ f852ff8) -> ``avfdti`` with as many
  3 x 3 decoder convolutions as the file holds (3 at that commit); dropped: the two wider audio
  branches and four BatchNorms, the unused 3-D position MLP of the heads, the duplicate
  ``resnet_feature`` view of the ResNet (checked equal to ``resnet_model``). The bird's-eye bounds,
  which the original hard-codes, are the published ones.
- ``avfdti-comparison``: the baselines of ``nets/comparison/`` -> ``audionet`` (``AudioNet_detect``),
  ``visualnet`` (``ResNet_VisualNet``), ``avped`` (``AVPed``), ``darknet`` (``darknet53``; the
  ``classifier`` view repeats ``features``), ``voranet`` (``voranet``), ``asdnet`` (``talkNetModel`` of
  ``talkNetModel.py`` and ``talknet/``; dropped: the ``DetectNet(256, 6)`` it declares and never calls,
  and the first visual ResNet layer's 1 x 1 ``downsample``, declared but unused at stride 1; the
  V-TCN's global LayerNorm ``gamma`` / ``beta`` of shape 1 x C x 1 become GroupNorm's C-vector
  ``weight`` / ``bias``; the net keeps its per-sample visual frontend, ``batch_mixing`` off).
- ``avped``: the original AV-PedAware ``FusionNet`` of ``network/avped.py`` (yizhuoyang/AV-PedAware @
  0a96491) -> ``avped`` with 8 microphone channels, recipe B (``aaute``) audio, d = 512, the gate
  512 -> 256 -> 128 -> 2 and a position head only: its 7 box outputs are cut to the first 3 (the
  centre); the unused z MLP and the audio segmentation head (no zoo output) are dropped.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from zoo.registry import get_model
from zoo.weights.files import SHOWN, CheckpointError, WeightsMismatchError, shape_text, state_differences

RESNET_CHILDREN = {"0": "conv1", "1": "bn1", "4": "layer1", "5": "layer2", "6": "layer3", "7": "layer4"}


class UnknownLayoutError(CheckpointError):
    """A state dict that matches none of the layouts of the format asked for."""


Rule = tuple[str, str]  #: (regex on the original key, replacement)


def audio_rules(src: str, dst: str, fc: str = "fc_audio") -> list[Rule]:
    """The four-branch audio encoder (AV-FDTI ``nets/audio_net.py``, AAUTE ``audio_net.py``)."""
    return [(rf"{src}convt1\.", f"{dst}branches.0.0."), (rf"{src}convt2\.", f"{dst}branches.1.0."),
            (rf"{src}convf1\.", f"{dst}branches.2.0."), (rf"{src}convf2\.", f"{dst}branches.3.0."),
            (rf"{src}{fc}\.", f"{dst}project.0.")]


AUDIO_DEAD = [r"convt3\.", r"convf3\.", r"bn\d\.", r"bn_a\d\."]  #: declared, never called (matched at any prefix)


def visual_rules(src: str, dst: str) -> list[Rule]:
    """AV-FDTI ``nets/visual_net.py``: the ResNet-50 (also reachable as ``resnet_feature``), 2 convs and the FC."""
    children = [(rf"{src}resnet_feature\.{index}\.", f"{dst}resnet.{name}.") for index, name in RESNET_CHILDREN.items()]
    return [(rf"{src}resnet_model\.", f"{dst}resnet."), *children, (rf"{src}convres\.", f"{dst}reduce.0."),
            (rf"{src}convvis\.", f"{dst}reduce.2."), (rf"{src}fcvis\.", f"{dst}project.0.")]


def detect_rules(src: str, dst: str) -> list[Rule]:
    """AV-FDTI ``nets/comparison/detection_heads.py``: three MLPs of three Linear layers each."""
    rules = []
    for original, ours in (("position_est", "position"), ("cls", "classes"), ("traj", "trajectory")):
        rules += [(rf"{src}{original}{i + 1}\.", f"{dst}{ours}.{2 * i}.") for i in range(3)]
    return rules


def _out(state: dict[str, torch.Tensor], key: str, axis: int = 0) -> int:
    return int(state[key].shape[axis])


@dataclass
class Layout:
    """How one original module's state dict maps onto a zoo net."""

    name: str
    model: str
    original: str  #: the original module and where it is published
    signature: tuple[str, ...]  #: keys that identify the layout (all must be present)
    rules: list[Rule]
    dead: list[str] = field(default_factory=list)  #: regexes of original keys that are dropped
    net_kwargs: Callable[[dict[str, torch.Tensor]], dict[str, Any]] = lambda state: {}
    fixes: dict[str, Callable[[torch.Tensor], torch.Tensor]] = field(default_factory=dict)  #: zoo key -> reshape
    filled: tuple[str, ...] = ()  #: zoo keys the original does not store (taken from the built net)

    def target(self, key: str) -> str | None:
        """The zoo key of an original key (None: a dead parameter; '' : not this layout's)."""
        for pattern, replacement in self.rules:
            match = re.match(pattern, key)
            if match:
                return replacement + key[match.end():]
        if any(re.search(rf"(^|\.){pattern}", key) for pattern in self.dead):
            return None
        return ""


def _student_kwargs(state: dict[str, torch.Tensor]) -> dict[str, Any]:
    return {"in_channels": _out(state, "convt1.weight", 1), "kernels": _out(state, "convt1.weight"),
            "feature_dim": _out(state, "fc_audio.weight")}


def _audio_kwargs(state: dict[str, torch.Tensor], prefix: str, fc: str = "fc_audio") -> dict[str, Any]:
    return {"in_channels": _out(state, f"{prefix}convt1.weight", 1), "kernels": _out(state, f"{prefix}convt1.weight"),
            "feature_dim": _out(state, f"{prefix}{fc}.weight")}


def _avfdti_kwargs(state: dict[str, torch.Tensor]) -> dict[str, Any]:
    convs = sum(f"detection.conv{i}.weight" in state for i in (2, 3, 4))
    return {**_audio_kwargs(state, "audionet."), "decoder_convs": convs,
            "num_classes": _out(state, "detection.cls3.weight")}


def _avfdti_rules() -> list[Rule]:
    rules = [*audio_rules(r"audionet\.", "audio."), *visual_rules(r"visualnet\.", "visual."),
             (r"attention\.self_attn\.", "attention.attention."), (r"attention\.linear1\.", "attention.ffn.0."),
             (r"attention\.linear2\.", "attention.ffn.3."), (r"attention\.norm1\.", "attention.norm1."),
             (r"attention\.norm2\.", "attention.norm2."),
             (r"fc_detect\.", "gate.detect.0."), (r"fc_detect2\.", "gate.detect.2."),
             (r"fc_detect3\.", "gate.detect.4."),
             (r"detection\.fc_all\.", "heatmap.project.0."), (r"detection\.deconv0\.", "heatmap.layers.0.")]
    rules += [(rf"detection\.deconv{i}\.", f"heatmap.layers.{2 * i}.") for i in range(1, 5)]
    for name, ours in (("cls", "classes"), ("traj", "trajectory")):
        rules += [(rf"detection\.{name}{i + 1}\.", f"{ours}.{2 * i}.") for i in range(3)]
    rules += [(r"detection\.fc2\.", "z.0."), (r"detection\.fc3\.", "z.2."), (r"detection\.fc4\.", "z.4."),
              (r"detection\.offset3\.", "offset.0."), (r"detection\.offset4\.", "offset.2.")]
    return rules


def _avfdti_layout_for(state: dict[str, torch.Tensor]) -> Layout:
    """AV-FDTI with as many decoder convs as the file holds (conv2..conv4, then final_conv)."""
    convs = sum(f"detection.conv{i}.weight" in state for i in (2, 3, 4))
    rules = _avfdti_rules() + [(rf"detection\.conv{2 + i}\.", f"heatmap.layers.{10 + 2 * i}.") for i in range(convs)]
    rules.append((r"detection\.final_conv\.", f"heatmap.layers.{10 + 2 * convs}."))
    return Layout("avfdti", "avfdti", "AVFDTI (yizhuoyang/AV-FDTI nets/AVFDTI.py @ f852ff8)",
                  ("audionet.convt1.weight", "visualnet.fcvis.weight", "attention.self_attn.in_proj_weight",
                   "detection.final_conv.weight"),
                  rules, [*AUDIO_DEAD, r"detection\.position_est\d\."], _avfdti_kwargs, filled=("bev_bounds",))


def _asdnet_rules() -> list[Rule]:
    """``talkNetModel``'s names -> ASDNet's (TalkNet's own block and layer names are kept below each prefix)."""
    rules = [(r"visualFrontend\.frontend3D\.", "visual_frontend.frontend3d."),
             (r"visualFrontend\.resnet\.layer1\.(?!downsample\.)", "visual_frontend.resnet.0.")]
    rules += [(rf"visualFrontend\.resnet\.layer{n}\.", f"visual_frontend.resnet.{n - 1}.") for n in (2, 3, 4)]
    rules += [(r"visualTCN\.net\.(\d+)\.net\.4\.gamma$", "visual_tcn.{0}.net.4.weight"),
              (r"visualTCN\.net\.(\d+)\.net\.4\.beta$", "visual_tcn.{0}.net.4.bias"),
              (r"visualTCN\.net\.", "visual_tcn."), (r"visualConv1D\.net\.", "visual_conv1d."),
              (r"audioEncoder\.conv1\.", "audio_encoder.stem.0."), (r"audioEncoder\.bn1\.", "audio_encoder.stem.1.")]
    for n in range(1, 5):
        rules += [(rf"audioEncoder\.layer{n}\.(\d+)\.se\.fc\.0\.", f"audio_encoder.layers.{n - 1}.{{0}}.se.2."),
                  (rf"audioEncoder\.layer{n}\.(\d+)\.se\.fc\.2\.", f"audio_encoder.layers.{n - 1}.{{0}}.se.4."),
                  (rf"audioEncoder\.layer{n}\.", f"audio_encoder.layers.{n - 1}.")]
    return [*rules, (r"crossA2V\.", "cross_a2v."), (r"crossV2A\.", "cross_v2a."), (r"selfAV\.", "self_av."),
            (r"fc\.", "fc.0."), (r"fc_p\.", "position."), (r"fc_c\.", "classes.")]


def _global_layer_norm(value: torch.Tensor) -> torch.Tensor:
    """TalkNet's global LayerNorm ``gamma`` / ``beta`` (1 x C x 1) -> GroupNorm's C-vector (else left for the
    shape check)."""
    if value.dim() == 3 and value.shape[0] == value.shape[2] == 1:
        return value.reshape(-1).clone()
    return value.clone()


def _centre(weight: torch.Tensor) -> torch.Tensor:
    """AV-PedAware's 7 box outputs -> the first 3 (the box centre)."""
    return weight[:3].clone()


LAYOUTS: dict[str, list[Layout]] = {
    "aaute": [Layout(
        "aaute", "student", "AudioNet (AllenLei666/AAUTE audio_net.py @ a5809f1)",
        ("convt1.weight", "fc_audio.weight", "position_est3.weight"),
        [*audio_rules("", "encoder."), (r"position_est1\.", "head.0."), (r"position_est2\.", "head.2."),
         (r"position_est3\.", "head.5.")],
        AUDIO_DEAD, _student_kwargs)],
    "avfdti": [],  # built per file (the number of decoder convs): see _avfdti_layout_for
    "avfdti-comparison": [
        Layout("audionet", "audionet", "AudioNet_detect (yizhuoyang/AV-FDTI nets/comparison/audionet.py @ f852ff8)",
               ("audionet.convt1.weight", "detectnet.position_est1.weight"),
               [*audio_rules(r"audionet\.", "encoder."), *detect_rules(r"detectnet\.", "head.")], AUDIO_DEAD,
               lambda s: {**_audio_kwargs(s, "audionet."), "num_classes": _out(s, "detectnet.cls3.weight")}),
        Layout("avped-comparison", "avped", "AVPed (yizhuoyang/AV-FDTI nets/comparison/avped.py @ f852ff8)",
               ("audionet.convt1.weight", "visualnet.fcvis.weight", "fc1.weight", "detectnet.position_est1.weight"),
               [*audio_rules(r"audionet\.", "audio."), *visual_rules(r"visualnet\.", "visual."),
                (r"fc1\.", "gate.detect.0."), (r"fc2\.", "gate.detect.2."), *detect_rules(r"detectnet\.", "head.")],
               AUDIO_DEAD,
               lambda s: {**_audio_kwargs(s, "audionet."), "gate_hidden": [_out(s, "fc1.weight")],
                          "num_classes": _out(s, "detectnet.cls3.weight")}),
        Layout("visualnet", "visualnet",
               "ResNet_VisualNet (yizhuoyang/AV-FDTI nets/comparison/resnet50_visual.py @ f852ff8)",
               ("visualnet.fcvis.weight", "detectnet.position_est1.weight"),
               [*visual_rules(r"visualnet\.", "encoder."), *detect_rules(r"detectnet\.", "head.")], [],
               lambda s: {"feature_dim": _out(s, "visualnet.fcvis.weight"),
                          "num_classes": _out(s, "detectnet.cls3.weight")}),
        Layout("darknet", "darknet", "darknet53 (yizhuoyang/AV-FDTI nets/comparison/darknet.py @ f852ff8)",
               ("features.0.conv.weight", "fc_p.weight"),
               [(r"(?:features|classifier)\.(\d+)\.layer1\.", "backbone.{0}.reduce."),
                (r"(?:features|classifier)\.(\d+)\.layer2\.", "backbone.{0}.expand."),
                (r"(?:features|classifier)\.(\d+)\.", "backbone.{0}."),
                (r"fc\.", "fc.0."), (r"fc_p\.", "position."), (r"fc_c\.", "classes.")], [],
               lambda s: {"num_classes": _out(s, "fc_c.weight")}),
        Layout("voranet", "voranet", "voranet (yizhuoyang/AV-FDTI nets/comparison/voranet.py @ f852ff8)",
               ("conv1.weight", "lstm.weight_ih_l0", "fc3.weight"),
               [(r"conv1\.", "features.0.0."), (r"bn1\.", "features.0.1."), (r"conv2\.", "features.1.0."),
                (r"bn2\.", "features.1.1."), (r"conv3\.", "features.2.0."), (r"bn3\.", "features.2.1."),
                (r"lstm\.", "lstm."), (r"fc1\.", "fc.0."), (r"fc2\.", "position."), (r"fc3\.", "classes.")], [],
               lambda s: {"in_channels": _out(s, "conv1.weight", 1), "channels": _out(s, "conv1.weight"),
                          "hidden": _out(s, "lstm.weight_hh_l0", 1), "num_classes": _out(s, "fc3.weight")}),
        Layout("asdnet", "asdnet", "talkNetModel (yizhuoyang/AV-FDTI nets/comparison/talkNetModel.py @ f852ff8)",
               ("visualFrontend.frontend3D.0.weight", "audioEncoder.conv1.weight",
                "crossA2V.self_attn.in_proj_weight", "fc_p.weight"),
               _asdnet_rules(), [r"detectnet\.", r"visualFrontend\.resnet\.layer1\.downsample\."],
               lambda s: {"in_channels": _out(s, "audioEncoder.conv1.weight", 1),
                          "num_classes": _out(s, "fc_c.weight")},
               fixes={f"visual_tcn.{block}.net.4.{name}": _global_layer_norm for block in range(5)
                      for name in ("weight", "bias")}),
    ],
    "avped": [Layout(
        "avped", "avped", "FusionNet (yizhuoyang/AV-PedAware network/avped.py @ 0a96491)",
        ("convt1.weight", "fc1.weight", "resnet_model.conv1.weight", "detect.weight", "position_est3.weight"),
        [*audio_rules("", "audio.", fc="fc1"), *visual_rules("", "visual."), (r"detect\.", "gate.detect.0."),
         (r"detec2\.", "gate.detect.2."), (r"detec3\.", "gate.detect.4."), (r"position_est1\.", "head.position.0."),
         (r"position_est2\.", "head.position.2."), (r"position_est3\.", "head.position.4.")],
        [*AUDIO_DEAD, r"fc[234]\.", r"dense\.", r"conv[123]\.", r"concat\."],
        lambda s: {**_audio_kwargs(s, "", fc="fc1"), "gate_hidden": [_out(s, "detect.weight"),
                                                                      _out(s, "detec2.weight")],
                   "heads": ["position"], "input_recipes": {"audio_mel": "aaute"}},
        fixes={"head.position.4.weight": _centre, "head.position.4.bias": _centre})],
}
FORMATS = tuple(LAYOUTS)


def _unwrap(state: Any, source: str) -> dict[str, torch.Tensor]:
    """The state dict inside a training script's wrapper, without DataParallel's ``module.`` prefix."""
    if isinstance(state, dict):
        for key in ("state_dict", "model_state_dict", "model"):
            if isinstance(state.get(key), dict) and not isinstance(state.get(key), torch.Tensor):
                state = state[key]
                break
    if not isinstance(state, dict) or not state:
        raise CheckpointError(f"{source}: expected a state dict (parameter name -> tensor), got {type(state).__name__}")
    not_tensors = [key for key, value in state.items() if not isinstance(value, torch.Tensor)]
    if not_tensors:
        raise CheckpointError(f"{source}: expected a state dict of tensors; entries {not_tensors[:SHOWN]} are not")
    if all(key.startswith("module.") for key in state):
        state = {key[len("module."):]: value for key, value in state.items()}
    return dict(state)


def _is_view(key: str) -> bool:
    """Whether ``key`` reaches a module through its second attribute path (``resnet_feature``, ``classifier``)."""
    return "resnet_feature." in key or key.startswith("classifier.")


def _candidates(fmt: str, state: dict[str, torch.Tensor]) -> list[Layout]:
    if fmt not in LAYOUTS:
        raise CheckpointError(f"unknown checkpoint format {fmt!r}; known: {', '.join(FORMATS)}")
    if fmt == "avfdti":
        return [_avfdti_layout_for(state)]
    return LAYOUTS[fmt]


def _apply_rule(layout: Layout, key: str) -> str | None:
    target = layout.target(key)
    if target and "{0}" in target:  # darknet: the numbered child index carries over
        for pattern, replacement in layout.rules:
            match = re.match(pattern, key)
            if match:
                return replacement.format(*match.groups()) + key[match.end():]
    return target


def identify(fmt: str, state: dict[str, torch.Tensor], model: str | None = None, source: str = "state dict"
             ) -> Layout:
    """The layout of ``fmt`` that ``state`` has (``model`` picks one where a format has several).

    Raises:
        UnknownLayoutError: no layout's identifying keys are all present (lists the recognised layouts and
            the first keys that did not match any of them).
    """
    candidates = [layout for layout in _candidates(fmt, state) if model is None or layout.model == model]
    matching = [layout for layout in candidates if all(key in state for key in layout.signature)]
    if matching:
        # the layout that explains most keys (AV-PED's keys include AudioNet's, for one)
        return max(matching, key=lambda layout: sum(_apply_rule(layout, key) != "" for key in state))
    unmatched = [key for key in state if all(layout.target(key) == "" for layout in candidates)]
    if not unmatched:  # every key has a place, but an identifying one is absent
        unmatched = [f"(absent) {key}" for layout in candidates for key in layout.signature if key not in state]
    recognised = "; ".join(f"--format {name}: " + ", ".join(f"{layout.name} ({layout.original})" for layout in
                           (LAYOUTS[name] or [_avfdti_layout_for(state)])) for name in FORMATS)
    hint = [name for name in FORMATS if name != fmt and any(
        all(key in state for key in layout.signature) for layout in _candidates(name, state))]
    raise UnknownLayoutError(
        f"{source}: the state dict matches no {fmt} layout{f' of model {model}' if model else ''}"
        f"{f' (it looks like --format {hint[0]})' if hint else ''}; recognised layouts: {recognised}; "
        f"first keys that did not match: {', '.join(unmatched[:SHOWN])}")


@dataclass
class Conversion:
    """A converted state dict and what it took."""

    layout: Layout
    net_kwargs: dict[str, Any]
    state_dict: dict[str, torch.Tensor]
    renamed: dict[str, str]  #: zoo key -> original key
    dropped: list[str]  #: original keys of dead parameters
    net: Any = None  #: the zoo net with the converted weights loaded, in eval mode


def convert_state(state: Any, fmt: str, source: str = "state dict", model: str | None = None) -> Conversion:
    """Map an original state dict onto the zoo's net (complete, deterministic, shapes checked).

    Raises:
        UnknownLayoutError: the keys match no layout of ``fmt``.
        WeightsMismatchError: a key the layout does not know, two copies of a parameter that disagree, or a
            shape that does not fit the zoo's net (the parameter, its original name and both shapes).
    """
    state = _unwrap(state, source)
    layout = identify(fmt, state, model, source)
    converted: dict[str, torch.Tensor] = {}
    renamed: dict[str, str] = {}
    dropped: list[str] = []
    unknown: list[str] = []
    for key in sorted(state, key=lambda k: (_is_view(k), k)):  # a module's primary name before its second view
        target = _apply_rule(layout, key)
        if target is None:
            dropped.append(key)
            continue
        if target == "":
            unknown.append(key)
            continue
        value = state[key]
        if target in converted:  # the same module reachable by two paths (ResNet, Darknet): must agree
            if not torch.equal(converted[target], value):
                raise WeightsMismatchError(f"{source}: {key} and {renamed[target]} are two views of {target} but hold "
                                           f"different values")
            dropped.append(key)
            continue
        converted[target] = layout.fixes[target](value) if target in layout.fixes else value.clone()
        renamed[target] = key
    if unknown:
        raise WeightsMismatchError(f"{source}: {len(unknown)} key(s) unknown to the {layout.name} layout "
                                   f"({layout.original}): {', '.join(unknown[:SHOWN])}")
    net_kwargs = layout.net_kwargs(state)
    net = get_model(layout.model, **net_kwargs)
    expected = net.state_dict()
    for key in layout.filled:
        if key in expected and key not in converted:
            converted[key] = expected[key].clone()
    for key, value in converted.items():
        if key in expected and tuple(value.shape) != tuple(expected[key].shape):
            stored = state[renamed[key]] if key in renamed else value
            shape = shape_text(stored) + (f" ({shape_text(value)} once reshaped)" if stored.shape != value.shape
                                          else "")
            raise WeightsMismatchError(f"{source}: {renamed.get(key, key)} -> {key} has shape {shape}, the "
                                       f"{layout.model} net {net_kwargs} needs {shape_text(expected[key])}")
    differences = state_differences(expected, converted)
    if differences:
        raise WeightsMismatchError(f"{source}: conversion as {layout.name} is incomplete: {differences}")
    ordered = {key: converted[key] for key in expected}
    net.load_state_dict(ordered, strict=True)
    return Conversion(layout, net_kwargs, ordered, renamed, dropped, net.eval())


def to_original(net: Any, fmt: str) -> dict[str, torch.Tensor]:
    """The net's weights in an original layout, for the original code's ``load_state_dict`` (strict).

    Only ``aaute`` (the student as AAUTE's ``AudioNet``) is written: the inverse of its renames, plus
    the four declared-but-unused BatchNorms at their initial values so that a strict load succeeds.
    """
    if fmt != "aaute" or getattr(net, "model_name", "") != "student":
        raise CheckpointError(f"only the student can be written in an original layout (--original-format aaute); "
                              f"got {getattr(net, 'model_name', type(net).__name__)} as {fmt}")
    layout = LAYOUTS["aaute"][0]
    state: dict[str, torch.Tensor] = {}
    for key, value in net.state_dict().items():
        for pattern, replacement in layout.rules:
            if key.startswith(replacement):
                state[pattern.replace("\\.", ".") + key[len(replacement):]] = value.detach().clone()
                break
        else:
            raise CheckpointError(f"{key} has no place in the {fmt} layout ({layout.original})")
    kernels = int(state["convt1.weight"].shape[0])
    for i in range(1, 5):  # declared, never called in the original: their initial values
        state.update({f"bn{i}.{name}": value for name, value in nn.BatchNorm2d(kernels).state_dict().items()})
    return state
