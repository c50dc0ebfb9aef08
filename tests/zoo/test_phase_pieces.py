"""The phase nets' pieces on their own: steering terms, pooled correlations, the cube table, the white-noise null
and the detection gate."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from datamodules.features import GccPhat, mic_pairs, phase_recipe, split_frames
from zoo.nets.phase import null
from zoo.nets.phase.cubes import CubeColumns
from zoo.nets.phase.gate import DetectionGate
from zoo.nets.phase.null import white_noise_correlations
from zoo.nets.phase.steering import POOL_WIDTHS, Steering, cube_grid, pooled, pooled_layouts, search_region, with_bounds

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


def test_white_noise_correlations_do_not_depend_on_how_many_windows_are_transformed_at_once(monkeypatch):
    gcc = GccPhat(RECIPE, null.NULL_SAMPLE_RATE, 3)
    noise = np.random.default_rng(5).standard_normal((3, 5 * 4 * gcc.frame))  # the draws of one array
    expected = gcc.correlate(gcc.cross_spectra(split_frames(noise, gcc.frame, 20))).reshape(3, 5, 4, -1)
    monkeypatch.setattr(null, "CHUNK_WINDOWS", 2)  # chunks of 2, 2 and 1 windows
    assert torch.allclose(null.white_noise_correlations(RECIPE, 3, windows=5, frames=4, seed=5), expected, atol=1e-6)


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


def test_cube_table_gives_the_columns_computed_afresh_and_starts_afresh_when_full():
    mics = torch.tensor([[0.0, 0.0, 0.2], [3.0, 0.0, 0.7], [0.0, 3.0, 1.2], [3.0, 3.0, 1.7]], dtype=torch.float64)
    steering = Steering(phase_recipe("gcc_phat_2s_static"))
    table = CubeColumns(steering, mics, capacity=3)
    offsets = torch.cartesian_prod(*[torch.tensor([-1.0, 0.0, 1.0])] * 3)
    parents = torch.tensor([[2.0, 6.0, 4.0], [1.5, 2.0, 1.0], [5.5, 3.0, 1.0]])  # the second inside the array
    sides = torch.tensor([[0.5], [0.25], [0.125]]).expand(-1, 27)
    centres = parents[:, None, :] + offsets * sides[..., None]
    fresh = steering.columns(centres.reshape(-1, 3), mics, sides.reshape(-1, 1)).reshape(3, 27, -1)
    width = table.width
    assert bool((fresh[1] < 0).all())  # its terms read nothing (-1): the table stores the zero column's index
    expected = fresh.remainder(width)
    names = torch.tensor([7, 11, 7])  # the third is parent 7 again: read from the table, not from its cubes
    out = table.children(1, names, centres, sides)
    assert torch.equal(out[:2], expected[:2]) and torch.equal(out[2], expected[0])
    assert (table.misses, table.hits) == (2, 1)
    again = table.children(1, names[:2], torch.full_like(centres[:2], float("nan")), sides[:2])  # not read
    assert torch.equal(again, expected[:2]) and table.hits == 3
    table.children(2, torch.tensor([7, 8]), centres[1:], sides[1:])  # a level's names are its own: 3 + 2 > 3
    assert len(table.slots) == 2 and (2, 7) in table.slots and (1, 7) not in table.slots


def test_a_filled_level_reads_every_parents_columns_as_computed_afresh():
    mics = torch.tensor([[0.0, 0.0, 0.2], [3.0, 0.0, 0.7], [0.0, 3.0, 1.2], [3.0, 3.0, 1.7]], dtype=torch.float64)
    steering = Steering(phase_recipe("gcc_phat_2s_static"))
    offsets = torch.cartesian_prod(*[torch.tensor([-1.0, 0.0, 1.0])] * 3)
    parents = torch.tensor([[2.0, 6.0, 4.0], [1.5, 2.0, 1.0], [5.5, 3.0, 1.0]])
    sides = torch.tensor([[0.5], [0.25], [0.125]]).expand(-1, 27)
    centres = parents[:, None, :] + offsets * sides[..., None]
    lazy, filled = CubeColumns(steering, mics), CubeColumns(steering, mics)
    filled.fill(0, centres, sides)
    assert filled.filled(0) and not filled.filled(1) and not lazy.filled(0)
    names = torch.tensor([2, 0, 2])
    nowhere = torch.full_like(centres, float("nan"))  # a filled level never reads the cubes again
    out = filled.children(0, names, nowhere, sides)
    assert out.dtype == torch.long and torch.equal(out, lazy.children(0, names, centres[names], sides[names]))
    assert filled.misses == 0 and filled.hits == 3


def test_a_search_with_its_first_level_filled_finds_the_peaks_of_one_that_fills_its_table_as_it_goes(monkeypatch):
    from zoo.registry import get_model

    mics = torch.tensor([[0.0, 0.0, 0.2], [3.0, 0.0, 0.7], [0.0, 3.0, 1.2], [3.0, 3.0, 1.7]], dtype=torch.float64)
    torch.manual_seed(0)
    correlation = torch.rand(2, 3, 6, 697) ** 8  # a few sharp peaks per pair
    prepared = get_model("srp_phat").search
    prepared.prepare(mics)
    filled = prepared.peaks(correlation, mics)
    assert prepared.cubes(mics).filled(0)
    monkeypatch.setattr(CubeColumns, "fill", lambda *args: None)
    lazy = get_model("srp_phat").search
    assert all(torch.equal(a, b) for a, b in zip(filled, lazy.peaks(correlation, mics), strict=True))
    assert not lazy.cubes(mics).filled(0) and prepared.cubes(mics).misses < lazy.cubes(mics).misses


def test_pooled_layouts_equal_max_pools_and_each_other():
    corr = torch.randn(3, 6, 141)
    rows, columns = pooled_layouts(corr)
    reference = [corr] + [torch.nn.functional.max_pool1d(corr, 2 * w + 1, stride=1, padding=w) for w in POOL_WIDTHS[1:]]
    expected = torch.cat([torch.stack(reference, dim=1).reshape(3, -1), torch.zeros(3, 1)], dim=1)
    assert torch.equal(rows, expected) and torch.equal(columns, expected.T) and columns.is_contiguous()
    assert torch.equal(pooled(corr), expected)


def test_a_capped_delay_fit_has_its_own_threshold_key_and_the_default_keeps_the_old_one():
    from zoo.registry import get_model

    mics = torch.tensor([[0.0, 0.0, 0.2], [3.0, 0.0, 0.7], [0.0, 3.0, 1.2], [3.0, 3.0, 1.7]], dtype=torch.float64)
    settings = ({}, {"fit_steps": 30}, {"fit_steps": 10})
    default, explicit, capped = (get_model("srp_phat", **kwargs) for kwargs in settings)
    assert default.threshold_key(mics) == explicit.threshold_key(mics) != capped.threshold_key(mics)
    with pytest.raises(ValueError, match="fit_steps"):
        get_model("srp_phat", fit_steps=0)


def test_the_normal_equations_solved_by_cofactors_equal_a_damped_lu_solve():
    import numpy as np

    from zoo.nets.phase.search import FIT_DAMPING, solve_normal

    rng = np.random.default_rng(0)
    jacobian = rng.normal(size=(50, 6, 3)) * np.array([1.0, 10.0, 100.0])  # scales as far as the fit sees
    residual = rng.normal(size=(50, 6, 1))
    matrix = jacobian.transpose(0, 2, 1) @ jacobian
    normal = np.concatenate([matrix, jacobian.transpose(0, 2, 1) @ residual], axis=2)  # M x 3 x 4
    damped = matrix + np.trace(matrix, axis1=1, axis2=2)[:, None, None] * FIT_DAMPING / 3 * np.eye(3)
    expected = np.linalg.solve(damped, -normal[..., 3:])[..., 0]
    got = solve_normal(np.ascontiguousarray(normal.transpose(1, 2, 0)).astype(np.float32))  # 3 x M
    assert got.dtype == np.float32
    np.testing.assert_allclose(got.T, expected, rtol=1e-3, atol=1e-6 * np.abs(expected).max())


def test_the_delay_fit_reaches_the_source_and_equals_a_per_candidate_lu_fit():
    import numpy as np

    from datamodules.features import pair_indices
    from zoo.nets.phase.search import FIT_DAMPING, FIT_MAX_STEP, CandidateSearch

    mics = torch.tensor([[0.0, 0.0, 0.2], [3.0, 0.0, 0.7], [0.0, 3.0, 1.2], [3.0, 3.0, 1.7]], dtype=torch.float64)
    steering = Steering(phase_recipe("gcc_phat_2s_static"))
    region = torch.tensor([[-2.0, 8.0], [-5.0, 25.0], [0.5, 25.0]])
    search = CandidateSearch(steering, region)
    source = torch.tensor([4.0, 9.0, 6.0])
    start = (source + torch.randn(2, 5, 3, generator=torch.Generator().manual_seed(1))).float()  # N x K x 3
    measured = steering.lag_positions(source.expand(2, 5, 3).float(), mics, direct_only=True).numpy()
    weight = np.ones_like(measured)
    fitted = search._gauss_newton(start.numpy(), measured, weight, mics)
    np.testing.assert_allclose(fitted, source.expand(2, 5, 3).numpy(), atol=1e-2)
    # the same steps one candidate at a time with numpy's LU solve, in float64
    first, second = (index.numpy() for index in pair_indices(4))
    scale = steering.recipe.lag_rate / steering.speed_of_sound
    half = (steering.recipe.num_lags() - 1) // 2
    points = start.double().numpy().reshape(-1, 3)
    for _ in range(search.fit_steps):
        for i, point in enumerate(points):
            direction = point - mics.numpy()
            distance = np.linalg.norm(direction, axis=1)
            unit = direction / distance[:, None]
            jacobian = scale * (unit[first] - unit[second])
            residual = scale * (distance[first] - distance[second]) + half - measured.reshape(-1, 6)[i]
            matrix = jacobian.T @ jacobian
            matrix += np.trace(matrix) * FIT_DAMPING / 3 * np.eye(3)
            step = np.clip(np.linalg.solve(matrix, -jacobian.T @ residual), -FIT_MAX_STEP, FIT_MAX_STEP)
            points[i] = np.clip(point + step, region[:, 0].numpy(), region[:, 1].numpy())
    np.testing.assert_allclose(fitted.reshape(-1, 3), points, atol=2e-3)


def test_term_differences_by_a_signed_matrix_equal_the_columns_differences_bit_for_bit():
    steering = Steering(phase_recipe("gcc_phat_2s_static"))
    mics = torch.tensor([[0.0, 0.0, 0.2], [3.0, 0.0, 0.7], [0.0, 3.0, 1.2], [3.0, 3.0, 1.7]], dtype=torch.float64)
    terms = steering.terms(4)
    width = steering.recipe.lag_rate / steering.recipe.f_max
    for dtype in (torch.float32, torch.float64):
        points = (torch.rand(500, 3, generator=torch.Generator().manual_seed(2)) * 20 - 5).to(dtype)
        virtual = steering.virtual_mics(mics).to(dtype)
        distance = torch.cdist(points, virtual)
        expected = ((distance[:, terms.first] - distance[:, terms.second]) / steering.speed_of_sound
                    * steering.recipe.lag_rate + (steering.recipe.num_lags() - 1) // 2)
        position = steering._lag_columns(distance, terms.first, terms.second)
        assert torch.equal(position, expected)
        grouped = position.reshape(-1, 4, 6)
        keep = [torch.ones(500, 6, dtype=torch.bool)]
        for later in range(1, 4):
            keep.append(torch.stack([(grouped[:, later] - grouped[:, e]).abs() > width for e in range(later)]).all(0))
        assert torch.equal(steering.distinct(position, 4), torch.stack(keep, dim=1).reshape(500, 24))
