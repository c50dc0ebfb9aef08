"""Synthetic state dicts with the parameter names and shapes of the original authors' modules.

Built from the names and shapes only (the originals cannot be imported here); the values are random
and seeded, so a converted net can be checked against a direct computation with the same tensors.
"""

from __future__ import annotations

from functools import lru_cache

import torch

RESNET_CHILDREN = ("conv1", "bn1", "relu", "maxpool", "layer1", "layer2", "layer3", "layer4")


def _random(shapes: dict[str, tuple[int, ...]], seed: int) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    state = {}
    for key, shape in shapes.items():
        if key.endswith("num_batches_tracked"):
            state[key] = torch.tensor(7)
        elif key.endswith("running_var"):
            state[key] = torch.rand(shape, generator=generator) + 0.5
        else:
            state[key] = (torch.rand(shape, generator=generator) - 0.5) * 0.2
    return state


def linear(name: str, n_in: int, n_out: int) -> dict[str, tuple[int, ...]]:
    return {f"{name}.weight": (n_out, n_in), f"{name}.bias": (n_out,)}


def conv(name: str, c_in: int, c_out: int, kernel: tuple[int, int], bias: bool = True) -> dict[str, tuple[int, ...]]:
    shapes = {f"{name}.weight": (c_out, c_in, *kernel)}
    if bias:
        shapes[f"{name}.bias"] = (c_out,)
    return shapes


def batchnorm(name: str, channels: int) -> dict[str, tuple[int, ...]]:
    return {f"{name}.weight": (channels,), f"{name}.bias": (channels,), f"{name}.running_mean": (channels,),
            f"{name}.running_var": (channels,), f"{name}.num_batches_tracked": ()}


def four_branch(prefix: str, c_in: int, k: int, d: int, fc: str = "fc_audio", wide: bool = False,
                bn: str = "bn") -> dict[str, tuple[int, ...]]:
    """AV-FDTI / AAUTE audio encoder: convt1/2, convf1/2 (+ the unused convt3/convf3), fc, unused BatchNorms."""
    shapes = {**conv(f"{prefix}convt1", c_in, k, (3, 64)), **conv(f"{prefix}convt2", c_in, k, (5, 64)),
              **conv(f"{prefix}convf1", c_in, k, (64, 3)), **conv(f"{prefix}convf2", c_in, k, (64, 5)),
              **linear(f"{prefix}{fc}", 244 * k, d)}
    if wide:
        shapes.update({**conv(f"{prefix}convt3", c_in, 16, (10, 64)), **conv(f"{prefix}convf3", c_in, 16, (64, 10))})
    for i in range(1, 5):
        shapes.update(batchnorm(f"{prefix}{bn}{i}", k))
    return shapes


def resnet50_views(prefix: str, seed: int) -> dict[str, torch.Tensor]:
    """A torchvision ResNet-50 kept as ``resnet_model`` and again as ``resnet_feature`` (children 0-7), shared."""
    return dict(_resnet50_views(prefix, seed))


@lru_cache(maxsize=4)
def _resnet50_views(prefix: str, seed: int) -> dict[str, torch.Tensor]:
    from torchvision.models import resnet50

    torch.manual_seed(seed)
    model = resnet50(weights=None)
    state = {f"{prefix}resnet_model.{key}": value.clone() for key, value in model.state_dict().items()}
    for index, name in enumerate(RESNET_CHILDREN):
        for key in getattr(model, name).state_dict():
            state[f"{prefix}resnet_feature.{index}.{key}"] = state[f"{prefix}resnet_model.{name}.{key}"]
    return state


def visual(prefix: str, d: int, seed: int) -> dict[str, torch.Tensor]:
    shapes = {**conv(f"{prefix}convres", 2048, 256, (3, 3)), **conv(f"{prefix}convvis", 256, 32, (3, 3)),
              **linear(f"{prefix}fcvis", 2048, d)}
    return {**resnet50_views(prefix, seed), **_random(shapes, seed + 1)}


def detect(prefix: str, d: int, classes: int = 6, position: int = 3) -> dict[str, tuple[int, ...]]:
    shapes = {}
    for name, n_out in (("position_est", position), ("cls", classes), ("traj", 30)):
        shapes.update({**linear(f"{prefix}{name}1", d, 256), **linear(f"{prefix}{name}2", 256, 128),
                       **linear(f"{prefix}{name}3", 128, n_out)})
    return shapes


def aaute_student(seed: int = 0) -> dict[str, torch.Tensor]:
    """AAUTE ``audio_net.AudioNet``: k 16, d 512, position MLP 512-256-128-3, four unused BatchNorms."""
    shapes = {**four_branch("", 4, 16, 512), **linear("position_est1", 512, 256), **linear("position_est2", 256, 128),
              **linear("position_est3", 128, 3)}
    return _random(shapes, seed)


def comparison_audionet(seed: int = 0) -> dict[str, torch.Tensor]:
    """AV-FDTI ``AudioNet_detect`` (k 16, d 256, the baselines' setting)."""
    return _random({**four_branch("audionet.", 4, 16, 256, wide=True), **detect("detectnet.", 256)}, seed)


def comparison_visualnet(seed: int = 0) -> dict[str, torch.Tensor]:
    """AV-FDTI ``ResNet_VisualNet`` (d 256)."""
    return {**visual("visualnet.", 256, seed), **_random(detect("detectnet.", 256), seed + 2)}


def comparison_avped(seed: int = 0) -> dict[str, torch.Tensor]:
    """AV-FDTI ``AVPed`` (d 256): AudioNet + VisualNet + fc1/fc2 gate + DetectNet."""
    shapes = {**four_branch("audionet.", 4, 16, 256, wide=True), **linear("fc1", 256, 128), **linear("fc2", 128, 2),
              **detect("detectnet.", 256)}
    return {**visual("visualnet.", 256, seed), **_random(shapes, seed + 3)}


def comparison_voranet(seed: int = 0) -> dict[str, torch.Tensor]:
    """AV-FDTI ``voranet``: three conv/BN blocks, LSTM(128), fc1 128-32, fc2 32-3, fc3 32-6."""
    shapes = {}
    for i, c_in in ((1, 4), (2, 64), (3, 64)):
        shapes.update({**conv(f"conv{i}", c_in, 64, (3, 3)), **batchnorm(f"bn{i}", 64)})
    shapes.update({"lstm.weight_ih_l0": (512, 128), "lstm.weight_hh_l0": (512, 128), "lstm.bias_ih_l0": (512,),
                   "lstm.bias_hh_l0": (512,), **linear("fc1", 128, 32), **linear("fc2", 32, 3),
                   **linear("fc3", 32, 6)})
    return _random(shapes, seed)


def comparison_darknet(seed: int = 0) -> dict[str, torch.Tensor]:
    """AV-FDTI ``darknet53``: a flat ``features`` list (also reachable as ``classifier``), fc 1024-100, fc_p, fc_c."""
    shapes: dict[str, tuple[int, ...]] = {}
    index = 0

    def conv_bn(name: str, c_in: int, c_out: int, k: int) -> None:
        shapes.update({**conv(f"{name}.conv", c_in, c_out, (k, k), bias=False), **batchnorm(f"{name}.bn", c_out)})

    conv_bn("features.0", 3, 32, 3)
    channels = 32
    for c_out, blocks in ((64, 1), (128, 2), (256, 8), (512, 8), (1024, 4)):
        index += 1
        conv_bn(f"features.{index}", channels, c_out, 3)
        for _ in range(blocks):
            index += 1
            conv_bn(f"features.{index}.layer1", c_out, c_out // 2, 1)
            conv_bn(f"features.{index}.layer2", c_out // 2, c_out, 3)
        channels = c_out
    shapes.update({**linear("fc", 1024, 100), **linear("fc_p", 100, 3), **linear("fc_c", 100, 6)})
    state = _random(shapes, seed)
    state.update({key.replace("features.", "classifier.", 1): value for key, value in state.items()
                  if key.startswith("features.")})
    return state


def avfdti(seed: int = 0, decoder_convs: int = 3) -> dict[str, torch.Tensor]:
    """AV-FDTI ``AVFDTI`` (k 32, d 512) with its ``detection_heads_hm.DetectNet`` (``decoder_convs`` 3 x 3 convs)."""
    d, k = 512, 32
    shapes = {**four_branch("audionet.", 4, k, d, wide=True),
              "attention.self_attn.in_proj_weight": (3 * d, d), "attention.self_attn.in_proj_bias": (3 * d,),
              **linear("attention.self_attn.out_proj", d, d), **linear("attention.linear1", d, 4 * d),
              **linear("attention.linear2", 4 * d, d), "attention.norm1.weight": (d,), "attention.norm1.bias": (d,),
              "attention.norm2.weight": (d,), "attention.norm2.bias": (d,),
              **linear("fc_detect", d, 256), **linear("fc_detect2", 256, 128), **linear("fc_detect3", 128, 2),
              **linear("detection.fc_all", d, 256), **linear("detection.fc2", d, 256),
              **linear("detection.fc3", 256, 100), **linear("detection.fc4", 100, 1),
              **conv("detection.deconv0", k, 1, (3, 3)),  # ConvTranspose2d weights are in x out x kh x kw
              **conv("detection.final_conv", k, 1, (3, 3)),
              **linear("detection.offset3", d, 100), **linear("detection.offset4", 100, 2),
              **detect("detection.", d, position=1)}
    shapes["detection.deconv0.weight"] = (1, k, 3, 3)
    shapes["detection.deconv0.bias"] = (k,)
    for i in range(1, 5):
        shapes.update(conv(f"detection.deconv{i}", k, k, (3, 3)))
    for i in range(2, 2 + decoder_convs):
        shapes.update(conv(f"detection.conv{i}", k, k, (3, 3)))
    return {**visual("visualnet.", d, seed), **_random(shapes, seed + 4)}


def avpedaware(seed: int = 0) -> dict[str, torch.Tensor]:
    """AV-PedAware ``FusionNet``: 8-channel audio (k 16) -> fc1 512, ResNet-50 visual, gate, 7-output head,
    an unused z MLP and an audio segmentation head."""
    d = 512
    shapes = {**four_branch("", 8, 16, d, fc="fc1", bn="bn_a"), **linear("fc2", d, 256), **linear("fc3", 256, 100),
              **linear("fc4", 100, 1), **linear("detect", d, 256), **linear("detec2", 256, 128),
              **linear("detec3", 128, 2), **linear("position_est1", d, 256), **linear("position_est2", 256, 128),
              **linear("position_est3", 128, 7), **linear("dense", d, 1024), **conv("conv1", 1, 32, (3, 3)),
              **batchnorm("bn1", 32), **conv("conv2", 32, 64, (3, 3)), **batchnorm("bn2", 64),
              **conv("conv3", 64, 64, (3, 3)), **batchnorm("bn3", 64), **conv("concat", 160, 2, (1, 1))}
    visual_shapes = {**conv("convres", 2048, 256, (3, 3)), **conv("convvis", 256, 32, (3, 3)),
                     **linear("fcvis", 2048, d)}
    return {**resnet50_views("", seed), **_random(visual_shapes, seed + 1), **_random(shapes, seed + 5)}


def attention_layer(prefix: str, d: int) -> dict[str, tuple[int, ...]]:
    """TalkNet ``attentionLayer``: ``nn.MultiheadAttention`` (packed q/k/v), FFN d -> 4d -> d, two LayerNorms."""
    return {f"{prefix}self_attn.in_proj_weight": (3 * d, d), f"{prefix}self_attn.in_proj_bias": (3 * d,),
            **linear(f"{prefix}self_attn.out_proj", d, d), **linear(f"{prefix}linear1", d, 4 * d),
            **linear(f"{prefix}linear2", 4 * d, d), f"{prefix}norm1.weight": (d,), f"{prefix}norm1.bias": (d,),
            f"{prefix}norm2.weight": (d,), f"{prefix}norm2.bias": (d,)}


def _talknet_visual() -> dict[str, tuple[int, ...]]:
    """``visualFrontend`` (3-D stem, lip-reading ResNet-18 of four ``ResNetLayer``, each with a 1 x 1
    ``downsample`` declared), ``visualTCN`` (five ``DSConv1d``) and ``visualConv1D``."""
    shapes = {"visualFrontend.frontend3D.0.weight": (64, 1, 5, 7, 7), **batchnorm("visualFrontend.frontend3D.1", 64)}
    for n, (c_in, c_out) in enumerate(((64, 64), (64, 128), (128, 256), (256, 512)), start=1):
        layer = f"visualFrontend.resnet.layer{n}"
        shapes.update({**conv(f"{layer}.conv1a", c_in, c_out, (3, 3), bias=False), **batchnorm(f"{layer}.bn1a", c_out),
                       **conv(f"{layer}.conv2a", c_out, c_out, (3, 3), bias=False),
                       **conv(f"{layer}.downsample", c_in, c_out, (1, 1), bias=False),
                       **batchnorm(f"{layer}.outbna", c_out),
                       **conv(f"{layer}.conv1b", c_out, c_out, (3, 3), bias=False), **batchnorm(f"{layer}.bn1b", c_out),
                       **conv(f"{layer}.conv2b", c_out, c_out, (3, 3), bias=False),
                       **batchnorm(f"{layer}.outbnb", c_out)})
    for block in range(5):  # ReLU, BatchNorm1d, depthwise conv, PReLU, global LayerNorm, pointwise conv
        net = f"visualTCN.net.{block}.net"
        shapes.update({**batchnorm(f"{net}.1", 512), f"{net}.2.weight": (512, 1, 3), f"{net}.3.weight": (1,),
                       f"{net}.4.gamma": (1, 512, 1), f"{net}.4.beta": (1, 512, 1), f"{net}.5.weight": (512, 512, 1)})
    shapes.update({"visualConv1D.net.0.weight": (256, 512, 5), "visualConv1D.net.0.bias": (256,),
                   **batchnorm("visualConv1D.net.1", 256), "visualConv1D.net.3.weight": (128, 256, 1),
                   "visualConv1D.net.3.bias": (128,)})
    return shapes


def _talknet_audio(c_in: int) -> dict[str, tuple[int, ...]]:
    """``audioEncoder(layers=[3, 4, 6, 3], num_filters=[16, 32, 64, 128])``: SE basic blocks (reduction 8), a
    1 x 1 conv + BN ``downsample`` where the stride (a tuple from layer 2 on) or the width changes."""
    shapes = {**conv("audioEncoder.conv1", c_in, 16, (8, 8), bias=False), **batchnorm("audioEncoder.bn1", 16)}
    width = 16
    for n, (blocks, planes) in enumerate(zip((3, 4, 6, 3), (16, 32, 64, 128), strict=True), start=1):
        for block in range(blocks):
            name = f"audioEncoder.layer{n}.{block}"
            inplanes = width if block == 0 else planes
            shapes.update({**conv(f"{name}.conv1", inplanes, planes, (3, 3), bias=False),
                           **batchnorm(f"{name}.bn1", planes),
                           **conv(f"{name}.conv2", planes, planes, (3, 3), bias=False),
                           **batchnorm(f"{name}.bn2", planes), **linear(f"{name}.se.fc.0", planes, planes // 8),
                           **linear(f"{name}.se.fc.2", planes // 8, planes)})
            if block == 0 and n > 1:  # layer 1 keeps stride 1 and width 16: no downsample
                shapes.update({**conv(f"{name}.downsample.0", inplanes, planes, (1, 1), bias=False),
                               **batchnorm(f"{name}.downsample.1", planes)})
        width = planes
    return shapes


def comparison_asdnet(seed: int = 0, classes: int = 6) -> dict[str, torch.Tensor]:
    """AV-FDTI ``talkNetModel``: TalkNet's visual and audio encoders, cross- and self-attention, fc 768-100,
    fc_p 100-3, fc_c 100-``classes`` and a ``DetectNet(256, 6)`` it declares but never calls."""
    return dict(_comparison_asdnet(seed, classes))


@lru_cache(maxsize=2)
def _comparison_asdnet(seed: int, classes: int) -> dict[str, torch.Tensor]:
    shapes = {**_talknet_visual(), **_talknet_audio(4), **detect("detectnet.", 256),
              **attention_layer("crossA2V.", 128), **attention_layer("crossV2A.", 128),
              **attention_layer("selfAV.", 256), **linear("fc", 768, 100), **linear("fc_c", 100, classes),
              **linear("fc_p", 100, 3)}
    return _random(shapes, seed)
