"""The phase nets' pieces on their own: steering terms, the white-noise null and the detection gate."""

from __future__ import annotations

import math

import pytest
import torch

from datamodules.features import mic_pairs, phase_recipe
from zoo.nets.phase.gate import DetectionGate
from zoo.nets.phase.null import white_noise_correlations
from zoo.nets.phase.steering import Steering, cube_grid, search_region, with_bounds

RECIPE = phase_recipe("gcc_phat")


def test_steering_terms_name_the_direct_then_the_three_ground_image_terms_of_every_pair():
    pairs = len(mic_pairs(4))
    free = Steering(RECIPE, ground_height=None).terms(4)
    assert len(free.first) == len(free.weights) == pairs and bool((free.weights == 1).all())
    terms = Steering(RECIPE, ground_height=0.0, reflection_weight=0.5).terms(4)
    assert len(terms.first) == 4 * pairs
    assert terms.rows.tolist() == list(range(pairs)) * 4  # every term reads its own pair's row
    assert terms.weights[:pairs].tolist() == [1.0] * pairs and terms.weights[pairs:].tolist() == [0.5] * 3 * pairs
    assert terms.first[pairs:2 * pairs].tolist() == (free.first + 4).tolist()  # image-direct: first mic's image
    assert terms.second[2 * pairs:3 * pairs].tolist() == (free.second + 4).tolist()  # direct-image


def test_the_region_is_checked_and_its_cube_grid_fills_it_from_the_minimum_corner():
    region = search_region((0.0, 0.0, 0.0), (2.0, 3.0, 1.0), "net")
    with pytest.raises(ValueError, match="net region must be 3 mins below 3 maxes"):
        search_region((0.0, 5.0, 0.0), (2.0, 3.0, 1.0), "net")
    points, shape = cube_grid(region, 1.0)
    assert shape == (2, 3, 1) and points[0].tolist() == [0.5, 0.5, 0.5] and points[-1].tolist() == [1.5, 2.5, 0.5]
    moved = with_bounds(region, [[-1.0, 1.0], [4.0, 6.0]])
    assert moved.tolist() == [[-1.0, 1.0], [4.0, 6.0], [0.0, 1.0]]
    with pytest.raises(ValueError, match="bounds must be"):
        with_bounds(region, [[1.0, -1.0], [4.0, 6.0]])


def test_white_noise_correlations_are_seeded_and_shaped_per_window_and_frame():
    made = white_noise_correlations(RECIPE, 3, windows=2, frames=4)
    assert made.shape == (3, 2, 4, RECIPE.num_lags()) and made.dtype == torch.float32
    assert torch.equal(made, white_noise_correlations(RECIPE, 3, windows=2, frames=4))
    assert not torch.equal(made, white_noise_correlations(RECIPE, 3, windows=2, frames=4, seed=1))
    assert float(made.abs().max()) < 0.7  # nothing coherent: a coherent source scores near 1


def test_the_gate_confirms_holds_then_falls_back_and_restarts_a_sequence_that_goes_back():
    gate = DetectionGate(hold_seconds=1.0, confirm_seconds=2.0, confirm_distance=5.0, fallback="mean")
    centre = torch.tensor([9.0, 9.0, 9.0])
    a, b = torch.tensor([1.0, 2.0, 3.0]), torch.tensor([1.0, 4.0, 3.0])
    nan = torch.full((3,), math.nan)
    positions = torch.stack([a, b, nan, nan, nan])
    detected = torch.tensor([True, True, False, False, False])
    time = torch.tensor([10.0, 11.0, 11.5, 13.0, 5.0])
    out, counted = gate.apply(positions, detected, torch.zeros(5, dtype=torch.long), time, centre)
    assert counted.tolist() == [False, True, False, False, False]  # the first is unconfirmed
    assert out[1].tolist() == b.tolist() and out[2].tolist() == b.tolist()  # held within a second
    assert out[3].tolist() == b.tolist()  # then the mean of the counted detections (only b)
    assert out[4].tolist() == centre.tolist()  # time went back: a fresh sequence, nothing detected yet
    alone, _ = DetectionGate().apply(positions[:3], detected[:3], None, None, centre)
    assert alone[2].tolist() == centre.tolist()
    with pytest.raises(ValueError, match="fallback"):
        DetectionGate(fallback="last")
