"""Reduced-budget adapters of the image models: smaller image recipes and AV-FDTI's smaller heat map.

A net built with ``input_recipes`` reads a reduced recipe with the reference parameters; the default
(and ``input_recipes=None``) is the reference, op for op; wrong data or wrong recipes fail clearly.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from torch.nn import functional as F
from torch.utils.flop_counter import FlopCounterMode

from datamodules.features import IMAGE_RECIPES
from zoo.cli import main
from zoo.nets.avfdti import AVFDTI, AVFDTI_BOUNDS, HeatmapDecoder, heatmap_focal_loss, peak_focal_loss
from zoo.nets.blocks import VisualEncoder
from zoo.registry import get_model
from zoo.task import TrajectoryTask

REDUCED = {  # image net -> constructor arguments of its reduced-budget variant
    "visualnet": {"input_recipes": {"image": "resnet64"}},
    "darknet": {"input_recipes": {"image": "resnet64"}},
    "avped": {"input_recipes": {"image": "resnet64"}},
    "asdnet": {"input_recipes": {"image": "talknet56"}},
    "avfdti": {"input_recipes": {"image": "resnet64"}, "heatmap_size": 128},
}
FIRST_IMAGE_LAYER = {
    "visualnet": "encoder.resnet.conv1.weight",
    "darknet": "backbone.0.conv.weight",
    "avped": "visual.resnet.conv1.weight",
    "asdnet": "visual_frontend.frontend3d.0.weight",
    "avfdti": "visual.resnet.conv1.weight",
}
SPLIT = "{train: [sim11-0000-avata], val: [sim11-0001-m300], test: [sim11-0002-mavic2]}"


def _build(name: str, seed: int = 0, **kwargs) -> torch.nn.Module:
    torch.manual_seed(seed)
    return get_model(name, **kwargs)


def _shapes(net: torch.nn.Module) -> dict[str, tuple[int, ...]]:
    return {key: tuple(value.shape) for key, value in net.state_dict().items()}


def test_reduced_image_recipes_keep_the_crop_and_shrink_the_size():
    assert IMAGE_RECIPES["resnet64"].size == (64, 64) and IMAGE_RECIPES["resnet128"].size == (128, 128)
    assert IMAGE_RECIPES["talknet56"].size == (56, 56)
    assert {r.crop_width for r in IMAGE_RECIPES.values()} == {1280}
    assert len({r.key() for r in IMAGE_RECIPES.values()}) == len(IMAGE_RECIPES)  # distinct feature-cache keys


@pytest.mark.parametrize("name", sorted(REDUCED))
def test_reduced_net_trains_at_the_reduced_size(name):
    net = _build(name, **REDUCED[name]).train()
    inputs = net.example_inputs(2)
    recipe = REDUCED[name]["input_recipes"]["image"]
    assert inputs["image"].shape[-2:] == IMAGE_RECIPES[recipe].size
    outputs = net(inputs)
    assert outputs["position"].shape == (2, 3) and all(torch.isfinite(v).all() for v in outputs.values())
    if name == "avfdti":
        assert outputs["heatmap"].shape == (2, 128, 128)
    sum(value.square().mean() for value in outputs.values()).backward()
    first = dict(net.named_parameters())[FIRST_IMAGE_LAYER[name]]
    assert first.grad is not None and first.grad.abs().sum() > 0  # through the adapter to the image trunk


@pytest.mark.parametrize("name", sorted(REDUCED))
def test_reduced_image_recipe_keeps_the_reference_parameters(name):
    recipes = {"input_recipes": REDUCED[name]["input_recipes"]}  # the image recipe alone (not AV-FDTI's heat map)
    reduced, reference = _build(name, **recipes), _build(name, seed=1)
    assert _shapes(reduced) == _shapes(reference)
    reduced.load_state_dict(reference.state_dict())  # a checkpoint moves between sizes (strict keys)
    assert reduced.inputs == {**type(reference).inputs, **recipes["input_recipes"]}
    assert type(reduced).inputs == reference.inputs  # the class keeps the reference recipes


def test_avfdti_smaller_heatmap_changes_only_the_decoder_layers():
    reduced, reference = AVFDTI(heatmap_size=128), AVFDTI()
    mine, theirs = _shapes(reduced), _shapes(reference)
    assert {k for k in mine.keys() ^ theirs.keys()} <= {k for k in theirs if k.startswith("heatmap.layers.")}
    assert {k: v for k, v in mine.items() if not k.startswith("heatmap.")} == \
        {k: v for k, v in theirs.items() if not k.startswith("heatmap.")}
    removed = sum(p.numel() for p in reference.parameters()) - sum(p.numel() for p in reduced.parameters())
    assert removed == 2 * (32 * 32 * 9 + 32)  # two 32 -> 32 transposed convolutions fewer
    assert reduced.reduced_settings() == {"heatmap_size": "128 (reference 512)"} and reference.reduced_settings() == {}


def test_avfdti_smaller_heatmap_costs_about_sixteen_times_less():
    features = torch.rand(1, 512)

    def flops(size: int) -> int:
        decoder = HeatmapDecoder(512, 32, 1, 16, int(math.log2(size // 16))).eval()
        with FlopCounterMode(display=False) as counter, torch.no_grad():
            decoder(features)
        return counter.get_total_flops()

    assert 14 < flops(512) / flops(128) < 18


@pytest.mark.parametrize("recipes", [None, {"image": "resnet256"}])
def test_reference_recipes_give_the_reference_net(recipes):
    reference, other = _build("visualnet").eval(), _build("visualnet", input_recipes=recipes).eval()
    inputs = reference.example_inputs(1)
    assert other.inputs == reference.inputs == {"image": "resnet256"} and other.reduced_settings() == {}
    with torch.no_grad():
        mine, theirs = reference(inputs), other(inputs)
    assert all(torch.equal(mine[key], theirs[key]) for key in mine)


def test_the_reference_grid_adds_no_op_and_reduced_grids_one(monkeypatch):
    calls: list[str] = []
    for op in ("interpolate", "adaptive_avg_pool2d"):
        original = getattr(F, op)
        monkeypatch.setattr(F, op, lambda *a, _op=op, _f=original, **k: calls.append(_op) or _f(*a, **k))
    encoder = _build("visualnet").encoder.eval()
    with torch.no_grad():
        encoder(torch.rand(1, 3, 256, 256))
        assert calls == []
        encoder(torch.rand(1, 3, 64, 64))
    assert calls == ["interpolate"]


def test_visual_encoder_grid_copies_small_maps_and_averages_large_ones():
    encoder = VisualEncoder.__new__(VisualEncoder)  # to_grid needs no weights
    small = torch.rand(2, 32, 2, 2)
    assert torch.equal(encoder.to_grid(small), small.repeat_interleave(4, dim=2).repeat_interleave(4, dim=3))
    large = torch.rand(2, 32, 16, 16)
    blocks = large.reshape(2, 32, 8, 2, 8, 2).mean(dim=(3, 5))
    assert torch.allclose(encoder.to_grid(large), blocks, atol=1e-6)
    reference = torch.rand(2, 32, 8, 8)
    assert encoder.to_grid(reference) is reference


def test_asdnet_frame_pooling_is_the_published_pool_only_at_the_reference_size():
    net = _build("asdnet").eval()
    pooled: list[tuple[int, ...]] = []
    net.visual_frontend.pool.register_forward_hook(lambda module, args, out: pooled.append(tuple(args[0].shape)))
    reduced = _build("asdnet", input_recipes={"image": "talknet56"}).eval()
    reduced.load_state_dict(net.state_dict())
    trunk: list[torch.Tensor] = []
    reduced.visual_frontend.resnet.register_forward_hook(lambda module, args, out: trunk.append(out))
    reduced.visual_frontend.pool.register_forward_hook(lambda module, args, out: pooled.append(tuple(args[0].shape)))
    with torch.no_grad():
        net(net.example_inputs(1))
        frames = reduced.visual_frontend(reduced.example_inputs(1)["image"])
    assert pooled == [(3, 512, 4, 4)]  # the reference only; T = 3 frames of the one sample
    assert trunk[0].shape == (3, 512, 2, 2) and torch.allclose(frames[0], trunk[0].mean(dim=(2, 3)), atol=1e-6)


@pytest.mark.parametrize("name", sorted(REDUCED))
def test_data_of_the_other_size_gives_the_error_naming_the_recipe(name):
    reduced, reference = _build(name, **REDUCED[name]), _build(name)
    small, big = reduced.inputs["image"], reference.inputs["image"]
    side = IMAGE_RECIPES[small].size[0]
    with pytest.raises(ValueError, match=rf"{name} needs image of shape B x 3 x {side} x {side} \(recipe '{small}'\)"):
        reduced(reference.example_inputs(1))
    with pytest.raises(ValueError, match=rf"needs image of shape B x 3 x .* \(recipe '{big}'\)"):
        reference(reduced.example_inputs(1))


def test_the_task_names_the_reduced_recipe_the_data_must_use():
    task = TrajectoryTask("visualnet", net_kwargs={"input_recipes": {"image": "resnet64"}})
    batch = dict(get_model("visualnet").example_inputs(1))
    with pytest.raises(ValueError, match=r"B x 3 x 64 x 64 \(recipe 'resnet64'\), got \(1, 3, 256, 256\)"):
        task._inputs(batch)
    del batch["image"]
    with pytest.raises(ValueError, match="needs inputs .*resnet64"):
        task._inputs(batch)


@pytest.mark.parametrize(("recipes", "message"), [
    ({"image": "resnet32"}, r"visualnet input_recipes\['image'\]: unknown image recipe 'resnet32'; known: .*resnet64"),
    ({"image": "avfdti"}, r"unknown image recipe 'avfdti'"),  # an audio recipe is not an image recipe
    ({"audio_mel": "aaute"}, r"visualnet has no input 'audio_mel' to give a recipe to; its inputs: .*image"),
    (["image", "resnet64"], r"input_recipes must map input name -> recipe name"),
])
def test_bad_input_recipes_are_refused(recipes, message):
    with pytest.raises(ValueError, match=message):
        get_model("visualnet", input_recipes=recipes)


def test_a_reduced_audio_visual_net_also_checks_its_audio_recipe():
    with pytest.raises(ValueError, match=r"avped input_recipes\['audio_mel'\]: unknown audio recipe 'resnet64'"):
        get_model("avped", input_recipes={"audio_mel": "resnet64"})


# ------------------------------------------------------------------------------ AV-FDTI at 128 x 128


def _cell_128(position: tuple[float, float]) -> tuple[int, int]:
    """(x index, y index) on a 128 x 128 grid over the AV-FDTI bounds, computed independently of the net."""
    return tuple(min(127, max(0, math.floor((v - lo) / ((hi - lo) / 128))))
                 for v, (lo, hi) in zip(position, AVFDTI_BOUNDS, strict=True))


def test_avfdti_128_targets_and_decoding_invert_each_other_within_a_cell():
    net = AVFDTI(heatmap_size=128).eval()
    assert net.heatmap.size == 128 and net.heatmap_radius == 10  # 40 px at 512 covers the same metres
    position = torch.tensor([[0.5, 2.0, 1.0], [-1.8, 18.7, 2.0], [5.86, -4.72, 3.0], [3.3, 10.0, 4.0]])
    heatmap, offset, outside = net.heatmap_target(position)
    assert heatmap.shape == (4, 128, 128) and not outside.any()
    cell = torch.tensor([(hi - lo) / 128 for lo, hi in AVFDTI_BOUNDS])
    for b in range(4):
        ix, iy = _cell_128(tuple(position[b, :2].tolist()))
        assert torch.nonzero(heatmap[b] == 1).tolist() == [[iy, ix]]
    ix, iy = _cell_128((3.3, 10.0))
    assert heatmap[3, iy, ix + 10] > 0 and heatmap[3, iy, ix + 11] == 0 and heatmap[3, iy + 11, ix] == 0
    assert ((offset >= 0) & (offset < cell * 100)).all()
    coarse = net.decode(heatmap, torch.zeros(4, 2), position[:, 2:])
    assert ((position[:, :2] - coarse[:, :2] >= 0) & (position[:, :2] - coarse[:, :2] < cell)).all()
    assert torch.allclose(net.decode(heatmap, offset, position[:, 2:]), position, atol=1e-5)
    with pytest.raises(ValueError, match=r"decodes 128 x 128 heat maps \(heatmap_size 128\), got \(512, 512\)"):
        net.decode(torch.zeros(1, 512, 512), torch.zeros(1, 2), torch.zeros(1, 1))


def test_avfdti_128_follows_new_bounds():
    net = AVFDTI(heatmap_size=128).eval()
    net.set_bounds([[-2.0, 8.0], [-5.0, 25.0]])
    heatmap = torch.zeros(1, 128, 128)
    heatmap[0, 25, 75] = 1.0  # y index 25, x index 75
    decoded = net.decode(heatmap, torch.zeros(1, 2), torch.ones(1, 1))
    assert torch.allclose(decoded[0, :2], torch.tensor([-2.0 + 75 * 10 / 128, -5.0 + 25 * 30 / 128]))


def test_avfdti_128_losses_run_and_match_the_published_focal_loss():
    torch.manual_seed(0)
    net = AVFDTI(heatmap_size=128, input_recipes={"image": "resnet64"}).train()
    inputs = net.example_inputs(2)
    outputs = net(inputs)
    target = torch.tensor([[0.5, 2.0, 1.0], [3.3, 10.0, 4.0]])
    batch = {"visible": torch.tensor([1.0, 0.0]), "class_id": torch.tensor([0, 3])}
    terms = net.auxiliary_losses(outputs, batch, target, torch.ones(2, dtype=torch.bool))
    assert set(terms) == {"heatmap", "z", "offset", "visibility", "class"}
    sum(terms.values()).backward()
    assert net.heatmap.layers[0].weight.grad.abs().sum() > 0
    generator = torch.Generator().manual_seed(0)
    logits = torch.randn(2, 128, 128, generator=generator) * 3
    cells, _, _ = net.target_cells(target)
    reference = heatmap_focal_loss(logits, net.heatmap_target(target)[0])
    assert peak_focal_loss(logits, cells, net.heatmap_radius).item() == pytest.approx(reference.item(), rel=1e-5)


@pytest.mark.parametrize("size", [16, 100, 0])
def test_avfdti_refuses_heatmap_sizes_the_decoder_cannot_make(size):
    with pytest.raises(ValueError, match=rf"heatmap_size must be 16 x 2\^k with k >= 1 .*got {size}"):
        AVFDTI(heatmap_size=size)


# ------------------------------------------------------------------------------ CLI


def test_cli_trains_a_reduced_visualnet_from_yaml_arguments(labelled_dir, feature_cache, tmp_path, capsys):
    config = Path(__file__).resolve().parents[2] / "configs" / "model" / "visualnet.yaml"
    common = ["--config", str(config), "--data.root", str(labelled_dir), "--data.split", SPLIT,
              "--data.window_seconds", "1.0", "--data.batch_size", "2", "--data.cache_dir", str(feature_cache),
              "--data.inputs", "{image: resnet64}", "--trainer.default_root_dir", str(tmp_path),
              "--trainer.fast_dev_run", "true", "--trainer.enable_progress_bar", "false"]
    assert main(["fit", *common, "--model.net_kwargs", "{input_recipes: {image: resnet64}}"]) == 0
    assert main(["fit", *common]) == 2  # the config's reference net on reduced data: one line, no traceback
    assert "visualnet needs image of shape B x 3 x 256 x 256 (recipe 'resnet256')" in capsys.readouterr().err
