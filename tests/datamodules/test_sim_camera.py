"""Tests of the camera simulator: fisheye geometry, drone appearance, low-light physics, encoding."""

from __future__ import annotations

import math

import numpy as np
import pytest

from datamodules.recording import EncodedImage
from datamodules.simulate.camera import (
    CameraModel,
    SkyConfig,
    drone_visible,
    linear_to_srgb,
    pixel_rays,
    project,
    render_frames,
    simulate_camera,
    srgb_to_linear,
)
from datamodules.simulate.drones import drone_spec
from datamodules.simulate.trajectory import Trajectory, generate_trajectory

MAVIC2 = drone_spec("mavic2")
SMALL = CameraModel(width=320, height=180)  # quick scenes
STRIP = CameraModel(height=160)  # the default lens (same focal length) on fewer rows
HIDDEN = np.array([8.0, 25.0, 0.5])  # below the camera's horizon: not in the image


def hover(position: np.ndarray, duration: float = 10.0) -> Trajectory:
    """A drone standing still at ``position`` (its heading is then rig +x)."""
    times = np.linspace(0.0, duration, 11)
    return Trajectory(times, np.tile(np.asarray(position, dtype=np.float64), (len(times), 1)))


def frames(model: CameraModel, position: np.ndarray, times=(0.0,), light="ideal", seed=0, **options) -> list:
    rng = np.random.default_rng(seed)
    return list(render_frames(model, MAVIC2, hover(position), list(times), light, rng, **options))


def linear(image: np.ndarray) -> np.ndarray:
    """Undo the output tone curve (white-balanced linear RGB)."""
    return srgb_to_linear(image / 255.0)


def above(model: CameraModel, distance: float) -> np.ndarray:
    """A point straight up the optical axis of a zenith camera."""
    return np.asarray(model.position) + [0.0, 0.0, distance]


# -------------------------------------------------------------------------------------- geometry
def test_zenith_is_the_image_centre_and_the_fov_edge_is_the_image_edge():
    model = CameraModel()
    camera = np.asarray(model.position)
    u, v, visible = project(model, above(model, 10.0))
    assert (u, v) == pytest.approx(model.centre) and visible
    # 180 deg across the width: the horizon towards +y / -y is the right / left edge, at mid height
    u, v, visible = project(model, camera + [[0.0, 10.0, 0.0], [0.0, -10.0, 0.0]])
    assert u == pytest.approx([model.width - 0.5, -0.5])
    assert v == pytest.approx([model.centre[1]] * 2)
    assert visible.all()
    assert model.deg_per_px == pytest.approx(180.0 / 1280.0)
    # just below the horizon, or 60 deg from the zenith towards +x (above the cropped top edge): not seen
    steep = [math.sin(math.radians(60.0)), 0.0, math.cos(math.radians(60.0))]
    _, v_steep, visible = project(model, camera + np.array([[0.0, 10.0, -0.1], steep]))
    assert not visible.any() and v_steep[1] < 0
    assert not drone_visible(model, HIDDEN) and drone_visible(model, above(model, 20.0))


def test_pixel_rays_project_back_to_their_pixels():
    model = CameraModel(width=320, height=180, tilt_deg=20.0, tilt_azimuth_deg=30.0, roll_deg=10.0)
    rays, circle = pixel_rays(model)
    rows, cols = np.nonzero(circle)
    pick = np.arange(0, len(rows), 997)
    u, v, visible = project(model, np.asarray(model.position) + 5.0 * rays[rows[pick], cols[pick]])
    assert visible.all()
    np.testing.assert_allclose(u, cols[pick], atol=1e-6)
    np.testing.assert_allclose(v, rows[pick], atol=1e-6)


def test_tone_curve_round_trip():
    x = np.linspace(0.0, 1.0, 101)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-6)


# ----------------------------------------------------------------------------------------- drone
def test_drone_appears_at_its_projected_pixel_darker_than_the_sky():
    position = np.array([3.0, 5.0, 12.0])
    with_drone = frames(SMALL, position)[0].astype(float)
    without = frames(SMALL, HIDDEN)[0].astype(float)
    darkening = (without - with_drone).mean(axis=-1)
    row, col = np.unravel_index(np.argmax(darkening), darkening.shape)
    u, v, visible = project(SMALL, position)
    assert visible and math.hypot(col - u, row - v) <= 1.5
    assert darkening[row, col] > 30.0  # a dark-grey drone against the bright sky
    far = np.hypot(*np.meshgrid(np.arange(SMALL.width) - u, np.arange(SMALL.height)[:, None] - v)) > 20
    assert np.array_equal(with_drone[far], without[far])  # the drone changes nothing elsewhere


def test_drone_size_falls_as_one_over_range():
    without = linear(frames(STRIP, HIDDEN)[0])
    area, rows = {}, {}
    for distance in (5.0, 10.0, 20.0):
        darkening = 1.0 - (linear(frames(STRIP, above(STRIP, distance))[0]) / without).mean(axis=-1)
        area[distance] = darkening.sum() / darkening.max()  # projected area in fully covered pixels
        rows[distance] = np.count_nonzero((darkening > 0.2 * darkening.max()).any(axis=1))
    # area ~ 1 / R^2 and length ~ 1 / R; a Mavic 2 (322 mm long, heading up the image) spans ~13 px at 10 m
    assert area[5.0] / area[10.0] == pytest.approx(4.0, rel=0.1)
    assert area[10.0] / area[20.0] == pytest.approx(4.0, rel=0.1)
    assert rows[10.0] == pytest.approx(0.322 / 10.0 * STRIP.focal_px, abs=2.0)
    assert rows[5.0] / rows[20.0] == pytest.approx(4.0, rel=0.2)


# ------------------------------------------------------------------------------------- low light
def noise_and_mean(pair: list, box: tuple[slice, slice]) -> tuple[float, float]:
    """Relative noise (std / mean, linear green) from two frames of a still scene, and the mean."""
    first, second = (linear(frame[box][..., 1]) for frame in pair)
    return float(np.std(second - first) / math.sqrt(2.0) / np.mean(first)), float(np.mean(first))


CENTRE = (slice(60, 120), slice(100, 220))
STILL = SkyConfig(cloud_wind_mps=(0.0, 0.0))


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_dark_frames_are_darker_and_noisier(seed):
    day = frames(SMALL, HIDDEN, times=(0.0, 0.1), light="ideal", seed=seed, sky=STILL)
    dark = frames(SMALL, HIDDEN, times=(0.0, 0.1), light="dark", seed=seed, sky=STILL)
    assert dark[0].mean() < 0.6 * day[0].mean()
    day_noise, _ = noise_and_mean(day, CENTRE)
    dark_noise, _ = noise_and_mean(dark, CENTRE)
    assert dark_noise > 5.0 * day_noise  # sqrt(r = 100) = 10 for shot noise, more with read noise


def test_exposure_ratio_scales_signal_and_shot_noise():
    # same scene and sensor (lambda_shot fixed), r = 1 vs 100: the mean falls to gain / r = 16 / 100 and the
    # relative shot noise grows by sqrt(r) = 10; with an unlimited gain the mean is restored
    options = {"times": (0.0, 0.1), "light": "dark", "seed": 5, "sky": STILL, "shot_noise": 1e-4}
    noise_1, mean_1 = noise_and_mean(frames(SMALL, HIDDEN, ratio=1.0, **options), CENTRE)
    noise_100, mean_100 = noise_and_mean(frames(SMALL, HIDDEN, ratio=100.0, **options), CENTRE)
    unlimited = CameraModel(width=320, height=180, max_gain=math.inf)
    _, mean_full = noise_and_mean(frames(unlimited, HIDDEN, ratio=100.0, **options), CENTRE)
    assert mean_100 / mean_1 == pytest.approx(16.0 / 100.0, rel=0.1)
    assert noise_100 / noise_1 == pytest.approx(10.0, rel=0.3)
    assert mean_full / mean_1 == pytest.approx(1.0, rel=0.1)


def test_leds_do_not_dim_with_the_exposure_ratio():
    position = above(STRIP, 14.0)
    excess = {}
    for light in ("ideal", "dark"):
        lit, unlit = (frames(STRIP, position, light=light, shot_noise=1e-3, leds=on)[0] for on in (1, 0))
        excess[light] = float((linear(lit) - linear(unlit))[..., 0].sum())  # light the LEDs add, red channel
        if light == "dark":
            assert lit[..., 0].max() >= 200 and np.median(lit[..., 0]) < 80  # bright points in a dark frame
    # the sky and the drone's body dim by gain / r = 0.16, the emissive LEDs gain the full digital gain 16
    assert excess["dark"] / excess["ideal"] == pytest.approx(16.0, rel=0.2)


def test_clouds_drift_only_with_wind():
    changed = {}
    for wind in (0.0, 5.0):
        sky = SkyConfig(cloud_cover=(0.4, 0.4), cloud_wind_mps=(wind, wind))
        start, later = frames(SMALL, HIDDEN, times=(0.0, 60.0), sky=sky)
        changed[wind] = np.mean(np.abs(start.astype(int) - later.astype(int)).max(axis=-1) > 25)
    assert changed[0.0] < 0.001 and changed[5.0] > 0.02


# -------------------------------------------------------------------------------------- encoding
def test_same_rng_gives_identical_bytes():
    trajectory = generate_trajectory(2.0, np.random.default_rng(1))
    times = SMALL.frame_times(0.5)
    first, again, other = (
        simulate_camera(SMALL, MAVIC2, trajectory, times, "dark", np.random.default_rng(seed))
        for seed in (7, 7, 8)
    )
    assert len(first) == len(times) and all(isinstance(image, EncodedImage) for image in first)
    assert [image.data for image in first] == [image.data for image in again]
    assert [image.data for image in first] != [image.data for image in other]
    assert first[0].format == "jpeg"


def test_png_decodes_to_exactly_the_rendered_frames():
    model = CameraModel(width=320, height=180, encoding="png")
    trajectory = hover(np.array([2.0, 3.0, 8.0]))
    rendered = list(render_frames(model, MAVIC2, trajectory, [0.0, 0.1], "dark", np.random.default_rng(3)))
    encoded = simulate_camera(model, MAVIC2, trajectory, [0.0, 0.1], "dark", np.random.default_rng(3))
    for image, frame in zip(encoded, rendered, strict=True):
        assert image.format == "png"
        assert np.array_equal(image.decode(), frame)


@pytest.fixture(scope="module")
def default_day_jpegs() -> list[EncodedImage]:
    model = CameraModel()
    trajectory = generate_trajectory(3.0, np.random.default_rng(4))
    times = model.frame_times(1.0)
    return simulate_camera(model, MAVIC2, trajectory, times, "ideal", np.random.default_rng(4))


def test_default_day_jpeg_size_is_stable(default_day_jpegs):
    # regression guard at 1280 x 720, quality 70 (measured ~35-45 KB): a realistic sky, neither empty
    # nor noise-dominated (day noise adds only ~5 %)
    mean_bytes = np.mean([len(image.data) for image in default_day_jpegs])
    assert 15_000 < mean_bytes < 55_000

