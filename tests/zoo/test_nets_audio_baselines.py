"""AudioNet, VorasNet and ASDNet: heads, parameter counts against baselines.md section 11, learning,
state-dict round trips, input checks, and ASDNet's per-sample independence (the fixed batch mixing)."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from zoo.nets.asdnet import ASDNet
from zoo.nets.blocks import DetectNet
from zoo.registry import get_model
from zoo.task import TrajectoryTask

NAMES = ("audionet", "voranet", "asdnet")
HEADS = {
    "audionet": {"position": (3,), "class_logits": (6,), "trajectory": (10, 3)},
    "voranet": {"position": (3,), "class_logits": (6,)},
    "asdnet": {"position": (3,), "class_logits": (6,)},
}
NO_DROPOUT = {"audionet": {"dropout": 0.0}, "voranet": {}, "asdnet": {"dropout": 0.0}}


def _count(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def _batch(net: nn.Module, batch_size: int = 2) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(3)
    batch = dict(net.example_inputs(batch_size))
    batch.update(gt=torch.rand(batch_size, 3, generator=generator) * torch.tensor([8.0, 20.0, 4.0]),
                 gt_valid=torch.ones(batch_size, dtype=torch.bool), class_id=torch.arange(batch_size) % 5)
    batch["pseudo"], batch["pseudo_valid"] = batch["gt"].clone(), batch["gt_valid"].clone()
    return batch


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize("name", NAMES)
def test_forward_gives_the_declared_heads(name):
    torch.manual_seed(0)
    net = get_model(name).eval()
    assert net.category == "supervised" and net.trains_position
    with torch.no_grad():
        outputs = net(net.example_inputs(2))
    assert {key: tuple(value.shape[1:]) for key, value in outputs.items()} == HEADS[name]
    assert all(len(value) == 2 and torch.isfinite(value).all() for value in outputs.values())


def test_audionet_counts_the_used_parameters_of_section_11():
    net = get_model("audionet")
    assert _count(net) == 1_366_375 == pytest.approx(1.366e6, rel=5e-3)
    # the published total adds two wider branches (10 x 64, 64 x 10) and four BatchNorms, never called
    dead = nn.ModuleList([nn.Conv2d(4, 16, (10, 64)), nn.Conv2d(4, 16, (64, 10)),
                          *(nn.BatchNorm2d(16) for _ in range(4))])
    assert _count(net) + _count(dead) == pytest.approx(1.448e6, rel=5e-3)


def test_voranet_counts_section_11():
    assert _count(get_model("voranet")) == 213_129 == pytest.approx(0.213e6, rel=5e-3)


def test_asdnet_counts_section_11_with_the_dead_modules_and_the_attention_projections():
    net = get_model("asdnet")
    assert _count(net) == 15_820_476
    # total: the original also holds a DetectNet(256, 6) never called and layer 1's unused downsample conv
    dead = nn.ModuleList([DetectNet(256, 6), nn.Conv2d(64, 64, 1, bias=False)])
    assert _count(net) + _count(dead) == pytest.approx(16.13e6, rel=5e-3)
    # section 11's "used" misses the MHA output projections (applied functionally, used nonetheless)
    out_proj = sum(_count(m.out_proj) for m in net.modules() if isinstance(m, nn.MultiheadAttention))
    assert out_proj == 98_816 and _count(net) - out_proj == pytest.approx(15.72e6, rel=5e-3)


@pytest.mark.parametrize("name", NAMES)
def test_one_adam_step_lowers_the_training_loss(name):
    torch.manual_seed(0)
    task = TrajectoryTask(name, net_kwargs=NO_DROPOUT[name], alpha=0.0)
    task.net.train()  # batch statistics, no dropout: the same function of the weights before and after
    batch = _batch(task.net)
    optimiser = torch.optim.Adam(task.parameters(), lr=1e-4)
    before, terms = task.objective(task.net(task._inputs(batch)), batch)
    assert set(terms) == {"position_gt", "position", "class"}
    with torch.no_grad():
        expected = 0.1 * nn.functional.cross_entropy(task.net(task._inputs(batch))["class_logits"], batch["class_id"])
    assert terms["class"].item() == pytest.approx(expected.item(), rel=1e-5)
    optimiser.zero_grad()
    before.backward()
    optimiser.step()
    with torch.no_grad():
        after, _ = task.objective(task.net(task._inputs(batch)), batch)
    assert after < before


@pytest.mark.parametrize("name", NAMES)
def test_state_dict_round_trip_gives_identical_outputs(name):
    torch.manual_seed(0)
    net = get_model(name)
    net.train()
    with torch.no_grad():
        net(net.example_inputs(2))  # move the BatchNorm running statistics away from their defaults
    net.eval()
    torch.manual_seed(1)
    other = get_model(name).eval()
    other.load_state_dict(net.state_dict())
    inputs = net.example_inputs(2)
    with torch.no_grad():
        a, b = net(inputs), other(inputs)
    assert all(torch.equal(a[key], b[key]) for key in HEADS[name])


@pytest.mark.parametrize(("name", "key", "shape"), [
    ("audionet", "audio_mel", (2, 4, 32, 32)),
    ("audionet", "audio_mel", (2, 2, 64, 64)),
    ("voranet", "audio_mel", (2, 4, 64, 64)),
    ("asdnet", "audio_mel", (2, 4, 64, 64)),
    ("asdnet", "image", (2, 3, 64, 64)),
])
def test_wrong_input_shapes_raise_a_clear_error(name, key, shape):
    net = get_model(name)
    inputs = net.example_inputs(2)
    inputs[key] = torch.rand(shape)
    expected = " x ".join(map(str, net.input_shapes()[key]))
    with pytest.raises(ValueError, match=rf"{name} needs {key} of shape B x {expected} .*got \({shape[0]}, "):
        net(inputs)
    del inputs[key]
    with pytest.raises(ValueError, match=rf"{name} needs input '{key}'"):
        net(inputs)


def test_asdnet_output_of_a_sample_does_not_depend_on_its_batch_mates():
    torch.manual_seed(0)
    net = ASDNet().eval()
    mixing = ASDNet(batch_mixing=True).eval()
    mixing.load_state_dict(net.state_dict())
    first = net.example_inputs(1)
    generator = torch.Generator().manual_seed(5)
    mates = [{key: torch.rand(1, *value.shape[1:], generator=generator) * 2 - 1 for key, value in first.items()}
             for _ in range(2)]

    def batched(*parts: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {key: torch.cat([part[key] for part in parts]) for key in first}

    with torch.no_grad():
        alone = net(first)["position"][0]
        assert torch.allclose(mixing(first)["position"][0], alone, atol=1e-6)  # same function for one sample
        for inputs in (batched(first, mates[0]), batched(mates[0], first, mates[1])):
            index = 0 if len(inputs["image"]) == 2 else 1
            assert torch.allclose(net(inputs)["position"][index], alone, atol=1e-5)
        # the published frontend convolves across the batch: sample 1 of 3 changes with its neighbours
        mixed = mixing(batched(mates[0], first, mates[1]))["position"][1]
        assert not torch.allclose(mixed, alone, atol=1e-4)
