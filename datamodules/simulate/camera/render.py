"""The renderer: one recording's frames from the sky, the drone and the sensor.

Per frame: the sky keyframe's radiance, the drone drawn over it, the sensor's noise (a pool drawn
once per recording, used at a random shift, row order and sign, plus fresh row noise) and the
ISP's look-up table; :func:`simulate_camera` encodes the frames.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence

import numpy as np

from datamodules.recording import EncodedImage
from datamodules.simulate.camera.drone import (
    LED_PEAK_AT_10M,
    PROP_BRIGHTNESS,
    UNDERSIDE_FACTOR,
    DroneShape,
    draw_drone,
    headings,
)
from datamodules.simulate.camera.optics import CameraModel
from datamodules.simulate.camera.sensor import ROW_NOISE_FRACTION, Sensor, encode_image
from datamodules.simulate.camera.sky import Sky, SkyConfig
from datamodules.simulate.drones import DroneSpec
from datamodules.simulate.trajectory import Trajectory


def render_frames(
    model: CameraModel,
    drone: DroneSpec,
    trajectory: Trajectory,
    frame_times: Sequence[float] | np.ndarray,
    light: str = "ideal",
    rng: np.random.Generator | None = None,
    *,
    ratio: float | None = None,
    shot_noise: float | None = None,
    sky: SkyConfig | None = None,
    leds: bool = True,
) -> Iterator[np.ndarray]:
    """Render the frames of one recording (H x W x 3 uint8 RGB), one at a time.

    Args:
        model: camera, sensor and encoder.
        drone: the drone type (size, reflectivity, propeller diameter).
        trajectory: the flight; its heading follows the horizontal velocity.
        frame_times: frame times (s since start), increasing.
        light: 'ideal' (daylight: r = 1, base-ISO noise) or 'dark' (r = ``ratio``, Brooks noise sampled).
        rng: source of all randomness; the same generator state gives the same frames.
        ratio: exposure ratio r (default 1 for 'ideal', ``DARK_RATIO`` for 'dark').
        shot_noise: fixes lambda_shot (lambda_read follows Brooks' regression line) instead of sampling it
            ('dark') or using ``DAY_SHOT_LAMBDA`` ('ideal').
        sky: ranges of the random scene.
        leds: draw the navigation LEDs.
    """
    rng = np.random.default_rng() if rng is None else rng
    times = np.asarray(frame_times, dtype=np.float64)
    scene = Sky(model, sky or SkyConfig(), rng)
    sensor = Sensor.sample(model, light, ratio, shot_noise, rng)
    lut = sensor.lut()
    pad = 64
    pool = rng.standard_normal((model.height + pad, model.width + pad, 3), dtype=np.float32)
    np.clip(pool, -6.0, 6.0, out=pool)  # 6 sigma of the largest Brooks level < 0.7 white: inside the guard
    row_std = ROW_NOISE_FRACTION * math.sqrt(sensor.read) * sensor.white
    scale = sensor.raw_scale(scene.vignette)

    shape = DroneShape.of(drone)
    positions = np.asarray(trajectory.position(times)).reshape(-1, 3)
    yaws = headings(trajectory, times)
    body = np.float32(drone.reflectivity * UNDERSIDE_FACTOR * scene.exposure)
    led_peak = LED_PEAK_AT_10M * scene.exposure if leds else 0.0

    key_time, radiance, mean, std = None, None, None, None
    for i, t in enumerate(times):
        if scene.keyframe_time(float(t)) != key_time:
            key_time = scene.keyframe_time(float(t))
            radiance = scene.radiance(key_time)
            mean, std = sensor.expected(radiance * scale)
        # this frame's noise: the pool at a random shift, row order and sign, plus fresh row noise
        dy, dx = rng.integers(0, pad, size=2)
        flip, sign = rng.integers(0, 2, size=2)
        noise = (pool[::-1] if flip else pool)[dy : dy + model.height, dx : dx + model.width]
        combine = np.add if sign else np.subtract
        rows = (rng.standard_normal(model.height) * row_std).astype(np.float32)[:, None, None]
        frame = std * noise
        combine(mean, frame, out=frame)
        frame += rows
        drawn = draw_drone(model, shape, positions[i], float(yaws[i]), led_peak)
        if drawn is not None:
            box, opaque, props, light_px = drawn
            opaque, props = opaque[..., None], props[..., None]
            patch = radiance[box] * (1.0 - opaque - props) + body * (opaque + PROP_BRIGHTNESS * props)
            emitted = light_px * np.float32(sensor.ratio)  # LEDs do not dim with 1/r
            patch_mean, patch_std = sensor.expected((patch + emitted) * scale[box])
            frame[box] = combine(patch_mean, patch_std * noise[box]) + rows[box[0]]
        yield lut.take(frame.astype(np.uint16))


def simulate_camera(
    model: CameraModel,
    drone: DroneSpec,
    trajectory: Trajectory,
    frame_times: Sequence[float] | np.ndarray,
    light: str = "ideal",
    rng: np.random.Generator | None = None,
    *,
    ratio: float | None = None,
    shot_noise: float | None = None,
    sky: SkyConfig | None = None,
    leds: bool = True,
) -> list[EncodedImage]:
    """Render (:func:`render_frames`, same arguments) and encode the frames of one recording."""
    options = {"ratio": ratio, "shot_noise": shot_noise, "sky": sky, "leds": leds}
    frames = render_frames(model, drone, trajectory, frame_times, light, rng, **options)
    return [encode_image(model, frame) for frame in frames]
