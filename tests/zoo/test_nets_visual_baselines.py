"""The image and audio-visual baselines: VisualNet, DarkNet, AV-PED, AV-FDTI (baselines.md sections 3, 4, 8, 9).

Shapes of every declared head, parameter counts against section 11, state-dict round trips, the
DarkNet residual quirk, one AV-PED training step, and AV-FDTI's heat-map targets, focal loss and
position decoding. Each network is built once per module; all forwards run at batch 1-2.
"""

from __future__ import annotations

import logging
import math

import pytest
import torch

from zoo.nets.avfdti import (
    AVFDTI,
    AVFDTI_BOUNDS,
    HeatmapDecoder,
    gaussian_profile,
    heatmap_focal_loss,
    peak_focal_loss,
)
from zoo.nets.darknet import DarkNet53, DarkResidual
from zoo.nets.visualnet import VisualNet
from zoo.registry import get_model
from zoo.task import TrajectoryTask

RESNET_FC = 2048 * 1000 + 1000  #: the unused ResNet-50 classifier, kept as published

#: section 11: (total, used) parameters; None where the table gives no number
PARAMETERS = {
    "visualnet": (31.18e6, 29.13e6),
    "darknet": (40.69e6, 40.69e6),
    "avped": (32.36e6, 30.22e6),
    "avfdti": (None, 37.0e6),  # "about 37 M used": checked to 2 % below
}

HEADS = {  # output name -> shape at batch 1
    "visualnet": {"position": (1, 3), "class_logits": (1, 6), "trajectory": (1, 10, 3)},
    "darknet": {"position": (1, 3), "class_logits": (1, 6)},
    "avped": {"position": (1, 3), "class_logits": (1, 6), "trajectory": (1, 10, 3), "visibility_logits": (1, 2)},
    "avfdti": {"position": (1, 3), "heatmap": (1, 512, 512), "heatmap_logits": (1, 512, 512), "offset": (1, 2),
               "z": (1, 1), "visibility_logits": (1, 2), "class_logits": (1, 6), "trajectory": (1, 10, 3)},
}

_NETS: dict[str, torch.nn.Module] = {}
_OUTPUTS: dict[str, dict[str, torch.Tensor]] = {}


def _net(name: str) -> torch.nn.Module:
    """One network per name for the whole module (seed 0, eval mode)."""
    if name not in _NETS:
        torch.manual_seed(0)
        _NETS[name] = get_model(name).eval()
    return _NETS[name]


def _reference(name: str) -> dict[str, torch.Tensor]:
    """The module network's outputs on its example inputs at batch 1 (no grad), computed once."""
    if name not in _OUTPUTS:
        with torch.no_grad():
            _OUTPUTS[name] = _net(name)(_net(name).example_inputs(1))
    return _OUTPUTS[name]


@pytest.mark.parametrize("name", sorted(HEADS))
def test_forward_gives_the_declared_heads_and_the_published_parameter_counts(name):
    net = _net(name)
    outputs = net(net.example_inputs(1))
    assert {key: tuple(value.shape) for key, value in outputs.items()} == HEADS[name]
    assert all(torch.isfinite(value).all() for value in outputs.values())
    sum(value.sum() for value in outputs.values()).backward()
    total = sum(p.numel() for p in net.parameters())
    used = sum(p.numel() for p in net.parameters() if p.grad is not None)  # parameters that forward reaches
    net.zero_grad(set_to_none=True)
    expected_total, expected_used = PARAMETERS[name]
    if expected_total is not None:
        assert total == pytest.approx(expected_total, rel=0.005)
    if name == "avfdti":
        assert used == pytest.approx(expected_used, rel=0.02) and total == used + RESNET_FC
    else:
        assert used == pytest.approx(expected_used, rel=0.005)


@pytest.mark.parametrize("name", sorted(HEADS))
def test_state_dict_round_trip_gives_identical_outputs(name):
    net = _net(name)
    torch.manual_seed(1)
    other = get_model(name).eval()
    other.load_state_dict(net.state_dict())
    mine = _reference(name)
    with torch.no_grad():
        theirs = other(net.example_inputs(1))
    assert all(torch.equal(mine[key], theirs[key]) for key in mine)


def test_the_networks_declare_inputs_category_and_position_training():
    assert VisualNet.inputs == DarkNet53.inputs == {"image": "resnet256"}
    assert type(_net("avped")).inputs == {"audio_mel": "avfdti", "image": "resnet256"}
    assert AVFDTI.inputs == {"audio_mel": "avfdti", "image": "resnet256"} and AVFDTI.trains_position is False
    assert all(type(_net(name)).category == "supervised" for name in HEADS)


def test_visualnet_loads_local_resnet_weights_and_never_downloads(tmp_path):
    source = _net("visualnet").encoder.resnet
    path = tmp_path / "resnet50.pth"
    torch.save(source.state_dict(), path)
    loaded = VisualNet(resnet_weights=str(path)).encoder.resnet
    assert torch.equal(loaded.conv1.weight, source.conv1.weight)
    with pytest.raises(FileNotFoundError, match="not found"):
        VisualNet(resnet_weights=str(tmp_path / "missing.pth"))


# ------------------------------------------------------------------------------ DarkNet


def test_darknet_residual_adds_the_skip_twice_when_faithful():
    torch.manual_seed(0)
    faithful = DarkResidual(8, faithful=True).eval()
    standard = DarkResidual(8, faithful=False).eval()
    standard.load_state_dict(faithful.state_dict())
    x = torch.randn(2, 8, 5, 5)
    with torch.no_grad():
        assert torch.allclose(faithful(x) - standard(x), x, atol=1e-6)


def test_darknet_faithful_and_standard_residuals_share_weights_but_differ():
    net = _net("darknet")
    standard = DarkNet53(faithful_residual=False).eval()
    standard.load_state_dict(net.state_dict())
    assert net.faithful_residual and not standard.faithful_residual
    with torch.no_grad():
        assert not torch.allclose(_reference("darknet")["position"], standard(net.example_inputs(1))["position"])


# ------------------------------------------------------------------------------ AV-PED


def test_avped_one_adam_step_lowers_the_loss():
    torch.manual_seed(0)
    task = TrajectoryTask("avped", alpha=0.0, lr=1e-4)
    task.net.eval()  # no dropout, BatchNorm running statistics: the same function before and after
    task.net.visual.resnet.requires_grad_(False)  # the frozen trunk keeps the step cheap on CPU
    batch = dict(task.net.example_inputs(2))
    batch["image"][1] = -0.976  # a darkened frame, labelled not visible
    batch.update(gt=torch.tensor([[1.0, 4.0, 2.0], [3.0, 9.0, 1.5]]), gt_valid=torch.ones(2, dtype=torch.bool),
                 pseudo=torch.zeros(2, 3), pseudo_valid=torch.zeros(2, dtype=torch.bool),
                 class_id=torch.tensor([0, -1]), visible=torch.tensor([1.0, 0.0]))
    optimiser = torch.optim.Adam(task.parameters(), lr=1e-4)
    before, terms = task.objective(task.net(task._inputs(batch)), batch)
    assert set(terms) == {"position_gt", "position", "visibility", "class"}
    optimiser.zero_grad()
    before.backward()
    optimiser.step()
    with torch.no_grad():
        after, _ = task.objective(task.net(task._inputs(batch)), batch)
    assert after < before


# ------------------------------------------------------------------------------ AV-FDTI


def _cell(position: tuple[float, float], bounds=AVFDTI_BOUNDS) -> tuple[int, int]:
    """(x index, y index) of a position, computed independently of the network."""
    return tuple(min(511, max(0, math.floor((v - lo) / ((hi - lo) / 512)))) for v, (lo, hi) in zip(position, bounds,
                                                                                                  strict=True))


def test_avfdti_decodes_a_synthetic_peak_at_the_right_metres():
    net = _net("avfdti")
    generator = torch.Generator().manual_seed(0)
    positions = [(0.5, 2.0), (-1.8, 18.7), (5.85, -4.7), (3.3, 10.0)]
    heatmap = torch.rand(len(positions), 512, 512, generator=generator) * 0.05  # background clutter
    for b, position in enumerate(positions):
        ix, iy = _cell(position)
        heatmap[b, max(iy - 3, 0):iy + 4, max(ix - 3, 0):ix + 4] += 0.5  # a blob centred on (row y, column x)
        heatmap[b, iy, ix] = 1.0
    decoded = net.decode(heatmap, torch.zeros(len(positions), 2), torch.full((len(positions), 1), 2.5))
    cell = torch.tensor([(hi - lo) / 512 for lo, hi in AVFDTI_BOUNDS])
    assert ((decoded[:, :2] - torch.tensor(positions)).abs() <= cell).all()
    assert torch.equal(decoded[:, 2], torch.full((len(positions),), 2.5))


def test_avfdti_target_and_decoding_invert_each_other():
    net = _net("avfdti")
    position = torch.tensor([[0.5, 2.0, 1.0], [-1.8, 18.7, 2.0], [5.86, -4.72, 3.0]])
    heatmap, offset, outside = net.heatmap_target(position)
    assert not outside.any()
    decoded = net.decode(heatmap, offset, position[:, 2:])
    assert torch.allclose(decoded, position, atol=1e-5)


def test_avfdti_heatmap_target_puts_the_gaussian_peak_at_the_target_cell():
    net = _net("avfdti")
    position = torch.tensor([[0.5, 2.0, 1.0], [5.86, -4.72, 1.0]])
    heatmap, offset, _ = net.heatmap_target(position)
    sigma = 81 / 6
    for b in range(2):
        ix, iy = _cell(tuple(position[b, :2].tolist()))
        assert torch.nonzero(heatmap[b] == 1).tolist() == [[iy, ix]]  # row = y index, column = x index
        assert (heatmap[b] <= 1).all()
    ix, iy = _cell((0.5, 2.0))
    assert heatmap[0, iy + 3, ix + 4].item() == pytest.approx(math.exp(-25 / (2 * sigma**2)), rel=1e-6)
    assert heatmap[0, iy, ix + 40] > 0 and heatmap[0, iy, ix + 41] == 0 and heatmap[0, iy + 41, ix] == 0
    cell_cm = torch.tensor([(hi - lo) / 512 * 100 for lo, hi in AVFDTI_BOUNDS])
    assert ((offset >= 0) & (offset < cell_cm)).all()


def test_avfdti_clips_and_counts_targets_outside_the_bounds(caplog):
    net = _net("avfdti")
    position = torch.tensor([[9.0, 2.0, 1.0], [0.0, -30.0, 1.0], [1.0, 1.0, 1.0]])
    cells, offset, outside = net.target_cells(position)
    assert outside.tolist() == [True, True, False]
    assert cells[0, 0] == 511 and cells[1, 1] == 0
    outputs = {"heatmap_logits": torch.zeros(3, 512, 512, requires_grad=True), "z": torch.zeros(3, 1),
               "offset": torch.zeros(3, 2), "visibility_logits": torch.zeros(3, 2), "class_logits": torch.zeros(3, 6)}
    batch = {"visible": torch.tensor([1.0, 0.0, 1.0]), "class_id": torch.tensor([0, 1, -1])}
    before = net.clipped_targets
    with caplog.at_level(logging.WARNING, logger="zoo.nets.avfdti"):
        terms = net.auxiliary_losses(outputs, batch, position, torch.tensor([True, True, False]))
    assert net.clipped_targets - before == 2 and "outside the bird's-eye bounds" in caplog.text
    assert set(terms) == {"heatmap", "z", "offset", "visibility", "class"}
    assert all(torch.isfinite(value) for value in terms.values())


def test_avfdti_windowed_focal_loss_equals_the_published_formula():
    net = _net("avfdti")
    generator = torch.Generator().manual_seed(0)
    position = torch.tensor([[0.5, 2.0, 1.0], [-1.8, 18.7, 1.0], [5.86, -4.72, 1.0]])  # two windows hit a border
    target, _, _ = net.heatmap_target(position)
    cells, _, _ = net.target_cells(position)
    logits = (torch.randn(3, 512, 512, generator=generator) * 3).requires_grad_()
    reference = heatmap_focal_loss(logits, target)
    windowed = peak_focal_loss(logits, cells, 40)
    assert windowed.item() == pytest.approx(reference.item(), rel=1e-5)
    (g_reference,), (g_windowed,) = torch.autograd.grad(reference, logits), torch.autograd.grad(windowed, logits)
    assert torch.allclose(g_reference, g_windowed, atol=1e-6)
    good = torch.logit(target.clamp(1e-3, 1 - 1e-3))  # a prediction that matches the target
    assert peak_focal_loss(good, cells, 40) < 0.01 * windowed
    assert gaussian_profile(torch.tensor([0.0, 40.0, 41.0]), 40)[[0, 2]].tolist() == [1.0, 0.0]


def test_avfdti_set_bounds_changes_decoding_and_travels_in_the_state_dict(caplog):
    net = _net("avfdti")
    heatmap = torch.zeros(1, 512, 512)
    heatmap[0, 100, 300] = 1.0  # y index 100, x index 300
    offset, z = torch.zeros(1, 2), torch.ones(1, 1)
    default = net.decode(heatmap, offset, z)
    bounds = [[-2.0, 8.0], [-5.0, 25.0]]
    try:
        net.set_bounds(bounds)
        moved = net.decode(heatmap, offset, z)
        assert torch.allclose(moved[0, :2], torch.tensor([-2.0 + 300 * 10 / 512, -5.0 + 100 * 30 / 512]))
        assert not torch.allclose(moved, default)
        fresh = AVFDTI().eval()
        assert torch.allclose(fresh.decode(heatmap, offset, z), default)
        fresh.load_state_dict(net.state_dict())
        assert fresh.bev_bounds.tolist() == bounds and torch.equal(fresh.decode(heatmap, offset, z), moved)
    finally:
        with caplog.at_level(logging.WARNING, logger="zoo.nets.avfdti"):
            net.set_bounds(AVFDTI_BOUNDS)  # overriding non-default bounds is worth a warning
    assert "bounds changed" in caplog.text
    assert torch.equal(net.decode(heatmap, offset, z), default)
    for bad in ([[0.0, 1.0]], [[1.0, 0.0], [0.0, 1.0]], [[0.0, float("nan")], [0.0, 1.0]]):
        with pytest.raises(ValueError, match="min < max"):
            net.set_bounds(bad)


def test_avfdti_decoder_convs_selects_the_compared_or_the_later_variant():
    compared = sum(p.numel() for p in _net("avfdti").heatmap.parameters())
    later = sum(p.numel() for p in HeatmapDecoder(512, 32, convs=3).parameters())
    assert later - compared == 2 * (32 * 32 * 9 + 32)
