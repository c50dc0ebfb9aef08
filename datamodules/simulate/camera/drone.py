"""The drone as the camera sees it from below: body, arms, motors, spinning propellers and navigation LEDs.

The drone is drawn at its physical angular size with the local affine map of the fisheye (weak
perspective), anti-aliased by sub-pixel sampling; it heads along its horizontal velocity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from datamodules.simulate.camera.optics import CameraModel, project
from datamodules.simulate.drones import DroneSpec
from datamodules.simulate.trajectory import Trajectory

#: Drone underside: lit from below by the roof (albedo ~0.3) under clear-sky global irradiance, its radiance
#: is about 2.7 x albedo x the zenith sky radiance [E; sunny rooftop, simulation_sources.md 0]; the albedo is the
#: DroneSpec reflectivity (dark-grey DJI plastics 0.10-0.25, white Phantom 0.7).
UNDERSIDE_FACTOR = 2.7
#: Spinning two-blade propellers cover 10-15 % of their disc (blade solidity); over a 10-30 ms exposure the
#: blades smear into a faint disc of that opacity [E]. Propellers are black: half the body radiance [E].
PROP_DISC_OPACITY = 0.12
PROP_BRIGHTNESS = 0.5
#: Navigation LEDs (~2 cd) at 10 m are about 0.4 of the daylight zenith sky radiance in one pixel
#: (2 cd / 100 m^2 / 6e-6 sr vs ~8000 cd/m^2) [E]: peak pixel value relative to the zenith sky, ~ 1/R^2.
LED_PEAK_AT_10M = 0.4
LED_PSF_SIGMA_PX = 0.7  #: optical blur of a point source (px) [E]
#: LED layout [E]: port (left) red and starboard (right) green on the front arms, white status LED at the
#: tail. Seen from below, the port side appears on the image's right of the drone's heading.
LED_COLOURS = {"red": (1.0, 0.06, 0.03), "green": (0.05, 1.0, 0.25), "white": (0.8, 0.8, 0.8)}


def headings(trajectory: Trajectory, times: np.ndarray) -> np.ndarray:
    """Yaw (rad) along the horizontal velocity, held while the drone hovers (< 0.3 m/s)."""
    velocity = np.asarray(trajectory.velocity(times)).reshape(-1, 3)
    moving = np.hypot(velocity[:, 0], velocity[:, 1]) > 0.3
    yaw = np.arctan2(velocity[:, 1], velocity[:, 0])
    last_moving = np.maximum.accumulate(np.where(moving, np.arange(len(times)), -1))
    return np.where(last_moving >= 0, yaw[np.maximum(last_moving, 0)], 0.0)


@dataclass
class DroneShape:
    """Body-frame primitives (x forward, y left, z up; metres) of a quadcopter seen from below."""

    ellipsoids: list  #: (centre, semi-axes) of the body and the motors: opaque
    arms: list  #: (start, end) of the arm capsules: opaque
    arm_radius: float
    props: list  #: (centre, semi-axes) of the spinning-propeller discs: faint
    leds: list  #: (position, colour name)

    @classmethod
    def of(cls, drone: DroneSpec) -> DroneShape:
        """X-frame with the motors at the corners of the L x W planform, body 0.5 L x 0.44 W [E].

        MMAUD's size table swaps width and height for the Mavic 3 and the Avata (simulation_sources.md section 0,
        "sic"), so the two largest dimensions are the planform and the smallest is the height.
        """
        length, width, height = sorted(drone.size_m, reverse=True)
        motor = 0.06 * length
        hubs = [(sx * (length / 2 - motor), sy * (width / 2 - motor)) for sx in (1, -1) for sy in (1, -1)]
        prop = drone.prop_diameter_m / 2.0
        (left_x, left_y), (right_x, right_y) = hubs[0], hubs[1]
        return cls(
            ellipsoids=[((0.0, 0.0, 0.0), (0.25 * length, 0.22 * width, 0.4 * height))]
            + [((x, y, 0.0), (motor, motor, 0.3 * height)) for x, y in hubs],
            arms=[((0.1 * x, 0.1 * y, 0.0), (x, y, 0.0)) for x, y in hubs],
            arm_radius=0.035 * length,
            props=[((x, y, 0.1 * height), (prop, prop, 0.005)) for x, y in hubs],
            leds=[
                ((left_x, left_y, -0.3 * height), "red"),
                ((right_x, right_y, -0.3 * height), "green"),
                ((-0.25 * length, 0.0, 0.0), "white"),
            ],
        )


def _jacobian(model: CameraModel, position: np.ndarray) -> np.ndarray:
    """d(u, v) / d(x, y, z) at a rig-frame point (2 x 3), by central differences over 1 cm."""
    step = 0.01
    u, v, _ = project(model, np.vstack([np.eye(3) * step, -np.eye(3) * step]) + position)
    return np.stack([u[:3] - u[3:], v[:3] - v[3:]]) / (2.0 * step)


def draw_drone(
    model: CameraModel, shape: DroneShape, position: np.ndarray, yaw: float, led_peak_10m: float
) -> tuple[tuple[slice, slice], np.ndarray, np.ndarray, np.ndarray] | None:
    """The drone's pixel box, opaque coverage, propeller-disc opacity and LED light (box x 3), or None.

    The drone is small against its range, so it is projected with the local affine map of the fisheye
    (weak perspective): an ellipsoid becomes an ellipse, an arm a capsule. Coverage is the fraction of
    4 x 4 sub-pixel samples inside (anti-aliasing).
    """
    u0, v0, visible = project(model, position)
    if not visible:
        return None
    jac = _jacobian(model, position)
    c, s = math.cos(yaw), math.sin(yaw)
    to_image = jac @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # body metres -> pixels
    px_per_m = float(np.linalg.det(jac @ jac.T)) ** 0.25  # geometric mean of the two image scales
    extent = max(math.hypot(x, y) + max(axes[:2]) for (x, y, _), axes in shape.props + shape.ellipsoids)
    half = px_per_m * extent + 3.0
    x0, x1 = max(math.floor(u0 - half), 0), min(math.ceil(u0 + half) + 1, model.width)
    y0, y1 = max(math.floor(v0 - half), 0), min(math.ceil(v0 + half) + 1, model.height)
    box_w, box_h = x1 - x0, y1 - y0
    sub = 4 if box_w * box_h < 40_000 else 1
    grid = (np.arange(sub) + 0.5) / sub - 0.5
    du = (np.arange(x0, x1)[:, None] + grid).reshape(-1) - u0
    dv = (np.arange(y0, y1)[:, None] + grid).reshape(-1) - v0
    du, dv = np.meshgrid(du, dv)  # sub-pixel sample offsets from the drone's centre

    def ellipse(centre: tuple, semi_axes: tuple) -> np.ndarray:
        cu, cv = to_image @ np.asarray(centre)
        inv = np.linalg.inv(to_image @ np.diag(np.square(semi_axes)) @ to_image.T + 0.01 * np.eye(2))
        qu, qv = du - cu, dv - cv
        return inv[0, 0] * qu * qu + 2.0 * inv[0, 1] * qu * qv + inv[1, 1] * qv * qv <= 1.0

    def capsule(start: tuple, end: tuple, radius: float) -> np.ndarray:
        a, b = to_image @ np.asarray(start), to_image @ np.asarray(end)
        seg = b - a
        t = np.clip(((du - a[0]) * seg[0] + (dv - a[1]) * seg[1]) / max(seg @ seg, 1e-12), 0.0, 1.0)
        return np.hypot(du - a[0] - t * seg[0], dv - a[1] - t * seg[1]) <= radius

    opaque = np.zeros(du.shape, dtype=bool)
    for centre, axes in shape.ellipsoids:
        opaque |= ellipse(centre, axes)
    for start, end in shape.arms:
        opaque |= capsule(start, end, shape.arm_radius * px_per_m)
    discs = np.zeros(du.shape, dtype=bool)
    for centre, axes in shape.props:
        discs |= ellipse(centre, axes)

    def per_pixel(mask: np.ndarray) -> np.ndarray:
        return mask.reshape(box_h, sub, box_w, sub).mean(axis=(1, 3), dtype=np.float32)

    light = np.zeros((box_h, box_w, 3), dtype=np.float32)
    if led_peak_10m > 0:
        distance = float(np.linalg.norm(position - np.asarray(model.position)))
        peak = led_peak_10m * (10.0 / max(distance, 0.5)) ** 2
        pu, pv = np.arange(x0, x1) - u0, np.arange(y0, y1)[:, None] - v0
        for offset, name in shape.leds:
            lu, lv = to_image @ np.asarray(offset)
            spot = np.exp(-((pu - lu) ** 2 + (pv - lv) ** 2) / (2.0 * LED_PSF_SIGMA_PX**2))
            light += (peak * spot[..., None] * np.asarray(LED_COLOURS[name])).astype(np.float32)
    box = (slice(y0, y1), slice(x0, x1))
    return box, per_pixel(opaque), per_pixel(discs & ~opaque) * PROP_DISC_OPACITY, light
