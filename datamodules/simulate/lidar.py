"""Livox Mid-360 and Avia scans of an MMAUD scene: scan patterns, detection, drone and false returns.

Every pulse is fired at a time on the sensor's global pulse clock (pulse n at n / point rate, in
seconds since the recording start), so successive frames continue one non-repetitive pattern.
A pulse returns a point when it

- hits the static background (:meth:`Scene.cast`) and is detected (logistic in the received SNR),
- or hits the drone, tested against the drone at its position at that pulse's firing time,
- or is a false (solar) alarm: Bernoulli per pulse, range uniform over the range gate.

A pulse into the empty sky returns nothing. Points are written in the rig frame (z up, origin on
the roof under the rig), as the UG2 data hold LiDAR points and ground truth in one frame
(the MMAUD UG2 validation sample (``docs/simulation_sources.md`` section 5) [V]).

Sources are cited as in ``docs/simulation_sources.md``: section 5.1 specifications [V S42, S44],
section 5.2 scan patterns [E], section 5.3 points on a drone and detection [E], section 5.4 noise [V S42/E].
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import expit

from datamodules.recording import ORIGIN_BACKGROUND, ORIGIN_DRONE, ORIGIN_FALSE, PointCloud
from datamodules.simulate.drones import DroneSpec
from datamodules.simulate.scene import Scene
from datamodules.simulate.trajectory import Trajectory


def _fraction(x: np.ndarray) -> np.ndarray:
    """Fractional part in [0, 1) (phases in cycles; float64 keeps them exact at long times)."""
    return x - np.floor(x)


# ------------------------------------------------------------------------------------ scan patterns


@dataclass(frozen=True)
class Mid360Pattern:
    """Four beams sweeping azimuth while their elevations zig-zag over the vertical FOV.

    ``docs/simulation_sources.md`` section 5.2 [E]: each beam turns once per ``1 / azimuth_rate_hz``
    (10 Hz: every azimuth is passed by all four beams in each 0.1 s frame), and its elevation follows
    a triangle wave at its own, mutually incommensurate rate, so successive frames fill the gaps and
    coverage of 1 deg cells builds over 3-5 frames (SR-LIO notes [V S54]). The triangle runs in
    sin(elevation), which makes the mean density uniform per steradian, the assumption of the
    section 5.3 table (3,500 pts/sr per frame).
    """

    beams: int = 4
    azimuth_rate_hz: float = 10.0
    elevation_rates_hz: tuple[float, ...] = (211.37, 197.93, 223.71, 187.19)
    elevation_range_deg: tuple[float, float] = (-7.0, 52.0)  #: [V S42, S43]; vendor table -7.2..52.2 [S53]

    def directions(self, pulse: np.ndarray, point_rate_hz: float) -> np.ndarray:
        """Unit directions (N x 3, float32, sensor frame z up) of the pulses with these global indices."""
        beam = pulse % self.beams
        t = pulse / point_rate_hz
        azimuth = (2 * np.pi * _fraction(self.azimuth_rate_hz * t + beam / self.beams)).astype(np.float32)
        rates = np.asarray(self.elevation_rates_hz)[beam]
        phase = _fraction(rates * t + beam / self.beams).astype(np.float32)
        triangle = 1.0 - np.abs(2.0 * phase - 1.0)
        s_lo, s_hi = np.sin(np.radians(self.elevation_range_deg))
        sin_el = np.float32(s_lo) + triangle * np.float32(s_hi - s_lo)
        cos_el = np.sqrt(1.0 - sin_el * sin_el)
        return np.stack([cos_el * np.cos(azimuth), cos_el * np.sin(azimuth), sin_el], axis=1)


@dataclass(frozen=True)
class RosettePattern:
    """Risley-prism rosette of the Avia: two counter-rotating terms, six emitters side by side.

    ``docs/simulation_sources.md`` section 5.2 [V S50, M; parameters E]: the off-axis vector is
    u(t) = (e^{i 2 pi f1 t} + e^{i 2 pi f2 t}) / 2 with f2 = -f1 / phi (phi the golden ratio, so the
    pattern never repeats); its length |cos(pi (f1 - f2) t)| passes through the centre (f1 - f2) times
    a second, i.e. 10 petals per 0.1 s frame of 10 ms each, each frame rotated by 65 deg from the last.
    u is mapped onto the 70.4 x 77.2 deg ellipse [V S44] by an equidistant projection about the
    boresight. The six emitters sit 1.5 deg apart along the horizontal axis (1-2 deg [E]), with
    a 3 deg gap in the middle so that no emitter's own (singular) centre lies on the boresight;
    the centre of the FOV is then about 3-5 times denser than the mean, as section 5.3 states.
    """

    prism_rates_hz: tuple[float, float] = (61.8034, -38.1966)
    emitter_offsets_deg: tuple[float, ...] = (-4.5, -3.0, -1.5, 1.5, 3.0, 4.5)
    fov_deg: tuple[float, float] = (70.4, 77.2)  #: horizontal, vertical [V S44]

    def directions(self, pulse: np.ndarray, point_rate_hz: float) -> np.ndarray:
        """Unit directions (N x 3, float32, sensor frame, boresight +z) of these global pulse indices."""
        emitter = pulse % len(self.emitter_offsets_deg)
        t = pulse / point_rate_hz
        p1 = (2 * np.pi * _fraction(self.prism_rates_hz[0] * t)).astype(np.float32)
        p2 = (2 * np.pi * _fraction(self.prism_rates_hz[1] * t)).astype(np.float32)
        offsets = np.radians(np.asarray(self.emitter_offsets_deg, dtype=np.float32))
        half_x, half_y = np.radians(self.fov_deg[0] / 2), np.radians(self.fov_deg[1] / 2)
        # each emitter's ellipse, shifted by its offset, is the largest that stays inside the FOV ellipse
        scale_x = (half_x - np.abs(offsets)).astype(np.float32)
        scale_y = (half_y * np.sqrt(1.0 - np.abs(offsets) / half_x)).astype(np.float32)
        theta_x = 0.5 * scale_x[emitter] * (np.cos(p1) + np.cos(p2)) + offsets[emitter]
        theta_y = 0.5 * scale_y[emitter] * (np.sin(p1) + np.sin(p2))
        theta = np.hypot(theta_x, theta_y)
        sinc = np.sinc(theta / np.float32(np.pi))
        return np.stack([theta_x * sinc, theta_y * sinc, np.cos(theta)], axis=1)


# ----------------------------------------------------------------------------------------- sensors


@dataclass(frozen=True)
class LidarModel:
    """A Livox sensor: scan pattern, mount, detection and noise. Build with :meth:`mid360` or :meth:`avia`."""

    name: str
    pattern: Mid360Pattern | RosettePattern
    point_rate_hz: float  #: first-return pulses per second
    position: tuple[float, float, float]  #: sensor origin in the rig frame (m)
    detection_range_m: float  #: range at which an extended target of ``reference_reflectivity`` is detected
    blind_zone_m: float  #: returns nearer than this are dropped
    max_range_m: float  #: end of the range gate (returns beyond are dropped; false returns spread up to it)
    angle_noise_deg: float  #: 1 sigma per axis
    divergence_deg: tuple[float, float]  #: full beam divergence (vertical, horizontal)
    frame_rate_hz: float = 10.0
    tilt_deg: float = 0.0  #: tilt of the sensor's up axis (boresight) away from the rig's z axis
    tilt_azimuth_deg: float = 90.0  #: azimuth towards which it tilts (default +y, into the flight region)
    range_noise_m: float = 0.02  #: 1 sigma [V S42, S44]
    reference_reflectivity: float = 0.10  #: the spec's "@10 %" [V S42, S44]
    snr_offset_db: float = 0.0  #: SNR (dB re the spec target at the spec range) of 50 % detection [E]
    snr_slope_db: float = 1.5  #: logistic width (dB) of the detection curve [E]
    false_alarm_ratio: float = 1e-4  #: false returns per pulse, "<0.01 % @ 100 klx" [V S42; Avia M S47]
    false_intensity_max: float = 10.0  #: false returns have intensity uniform in [0, this) [E/M, section 5.4]
    intensity_scale: float = 150.0  #: Livox reflectivity value of a 100 % diffuse target (0-150 diffuse) [M]
    intensity_noise: float = 0.1  #: lognormal sigma of the reported reflectivity [E]
    #: Livox drivers report coordinates as integer millimetres and reflectivity as an integer 0-255 [M: Livox SDK]
    resolution_m: float = 0.001

    @classmethod
    def mid360(cls, **overrides: Any) -> LidarModel:
        """Livox Mid-360, ``docs/simulation_sources.md`` section 5.1 [V S42, S43] unless noted.

        200,000 pts/s at 10 Hz, 360 x (-7 ... 52) deg, 40 m @ 10 % (100 klx), blind zone 0.1 m,
        range noise 2 cm, angular noise 0.15 deg, false alarms < 0.01 %. Beam divergence is not
        published: 0.25 x 0.03 deg like other Livox sensors [E]. The range gate of 100 m is an
        estimate [E]: real UG2 Mid-360 frames hold returns out to 88 m (measured on val/seq1).
        Mounted upright at (0, 0, 1.3) m in the rig frame [E].
        """
        values: dict[str, Any] = dict(
            name="mid360",
            pattern=Mid360Pattern(),
            point_rate_hz=200_000.0,
            position=(0.0, 0.0, 1.3),
            detection_range_m=40.0,
            blind_zone_m=0.1,
            max_range_m=100.0,
            angle_noise_deg=0.15,
            divergence_deg=(0.25, 0.03),
        )
        return cls(**{**values, **overrides})

    @classmethod
    def avia(cls, **overrides: Any) -> LidarModel:
        """Livox Avia, ``docs/simulation_sources.md`` section 5.1 [V S44] unless noted.

        240,000 pts/s (first return) at 10 Hz [10 Hz: M], non-repetitive 70.4 x 77.2 deg rosette,
        190 m @ 10 % (100 klx), blind zone 1 m, range noise 2 cm, angular noise 0.05 deg, beam
        divergence 0.28 x 0.03 deg, range gate 450 m (80 % @ 0 klx; real false returns reach 434 m in
        the MMAUD UG2 validation sample, ``docs/simulation_sources.md`` section 5). Mounted at
        (0, 0, 1.35) m pointing at the
        zenith [E, the upward cone of the S1 figures]; ``tilt_deg`` tilts it.
        """
        values: dict[str, Any] = dict(
            name="avia",
            pattern=RosettePattern(),
            point_rate_hz=240_000.0,
            position=(0.0, 0.0, 1.35),
            detection_range_m=190.0,
            blind_zone_m=1.0,
            max_range_m=450.0,
            angle_noise_deg=0.05,
            divergence_deg=(0.28, 0.03),
        )
        return cls(**{**values, **overrides})

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> LidarModel:
        """The preset of a sensor by name (``"mid360"`` or ``"avia"``, as in ``recording.LIDAR_SENSORS``)."""
        presets = {"mid360": cls.mid360, "avia": cls.avia}
        if name not in presets:
            raise ValueError(f"unknown LiDAR sensor {name!r}; known: {sorted(presets)}")
        return presets[name](**overrides)

    @property
    def pulses_per_frame(self) -> int:
        return int(round(self.point_rate_hz / self.frame_rate_hz))

    def mount_rotation(self) -> np.ndarray:
        """Rotation (3 x 3) from the sensor frame to the rig frame."""
        tilt, azimuth = np.radians(self.tilt_deg), np.radians(self.tilt_azimuth_deg)
        axis = np.array([-np.sin(azimuth), np.cos(azimuth), 0.0])  # z x (tilt direction)
        return Rotation.from_rotvec(tilt * axis).as_matrix()

    def directions(self, pulse: np.ndarray) -> np.ndarray:
        """Unit beam directions (N x 3, float32) in the rig frame for global pulse indices."""
        directions = self.pattern.directions(pulse, self.point_rate_hz)
        if self.tilt_deg == 0.0:
            return directions
        return directions @ self.mount_rotation().T.astype(np.float32)

    def detection_probability(self, apparent_reflectivity: np.ndarray, ranges: np.ndarray) -> np.ndarray:
        """P_det = logistic((SNR_dB - offset) / slope) with SNR relative to the spec target at the spec range.

        Received power goes as reflectivity x incidence cosine x fill / R^2 (``docs/simulation_sources.md``
        section 5.3 [E]); ``apparent_reflectivity`` is that product's numerator. With the defaults an
        extended 10 % target facing the sensor is detected with probability 0.5 at ``detection_range_m``.
        """
        with np.errstate(divide="ignore"):
            snr_db = 10.0 * np.log10(
                apparent_reflectivity * (self.detection_range_m**2 / self.reference_reflectivity) / ranges**2
            )
        return expit((snr_db - self.snr_offset_db) / self.snr_slope_db)


# ------------------------------------------------------------------------------------------- drone


@dataclass(frozen=True)
class DroneReturnModel:
    """How a drone returns LiDAR pulses (``docs/simulation_sources.md`` section 5.3 and 7 [E]).

    The drone is a box of its spec's L x W x H, yawed by ``yaw_rad`` (L along x at 0). A pulse whose
    footprint (divergence x range) overlaps the box's silhouette returns with probability
    ``solid fraction x P_det``: the solid fraction makes the expected effective area
    ``fill_below x L x W`` seen from below (arms and body, spinning rotor disks returning with
    p ~ blade solidity ~ 0.1) and ``fill_side x`` the side area seen side-on, blended by the view
    direction; the footprint enlarges the area hit, and the fraction of the footprint on the
    silhouette (the fill) lowers the received power, so far-away drones fade out.
    """

    fill_below: float = 0.35  #: effective / planform area from below [E, section 5.3]
    fill_side: float = 0.6  #: effective / side area side-on [E, section 5.3]
    incidence_cos: float = 0.7  #: mean incidence cosine on the drone's curved surfaces [E]
    yaw_rad: float = 0.0


@dataclass(frozen=True)
class SunGlare:
    """The sun in the FOV: pulses within ``cone_deg`` of it get ``boost`` times the false-alarm ratio.

    "x5-x20 in a 5-10 deg cone around the sun direction" (``docs/simulation_sources.md`` section 5.4 [E]);
    it matters for the upward Avia around noon in Singapore.
    """

    direction: tuple[float, float, float]  #: towards the sun, rig frame
    boost: float = 10.0
    cone_deg: float = 7.5


@dataclass
class _Returns:
    """Per-pulse state of one batch (true ranges; measurement noise comes last)."""

    surface: np.ndarray  #: range to the first background surface (inf = sky)
    ranges: np.ndarray  #: range of the return (inf = none)
    apparent: np.ndarray  #: reflectivity x incidence cosine x fill of the return
    origin: np.ndarray = field(init=False)  #: ORIGIN_* per pulse

    def __post_init__(self) -> None:
        self.origin = np.full(len(self.ranges), ORIGIN_BACKGROUND, dtype=np.uint8)


def _body_frame(yaw: float) -> np.ndarray:
    """Rows: the drone's length, width and height axes in the rig frame."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def _half_width(axes_dot: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Half-extent of a box along unit vectors (support function), from |v . body axes| (N x 3)."""
    return 0.5 * np.abs(axes_dot) @ size


def _interval_overlap(offset: np.ndarray, half: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Fraction of [offset - radius, offset + radius] inside [-half, half]."""
    lo = np.maximum(offset - radius, -half)
    hi = np.minimum(offset + radius, half)
    return np.clip((hi - lo) / (2.0 * radius), 0.0, 1.0)


def _perpendicular_axes(directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors across each beam: e1 horizontal (z x d), e2 = d x e1 (up-ish)."""
    e1 = np.stack([-directions[:, 1], directions[:, 0], np.zeros(len(directions))], axis=1)
    norm = np.linalg.norm(e1, axis=1, keepdims=True)
    vertical = norm[:, 0] < 1e-9
    e1[vertical] = [1.0, 0.0, 0.0]
    norm[vertical] = 1.0
    e1 /= norm
    return e1, np.cross(directions, e1)


def drone_returns(
    model: LidarModel,
    drone: DroneSpec,
    centres: np.ndarray,
    directions: np.ndarray,
    rng: np.random.Generator,
    drone_model: DroneReturnModel | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Which beams return from the drone, and at what range.

    Args:
        model: the sensor (origin, divergence, detection curve).
        drone: its size and reflectivity.
        centres: drone centre (N x 3, rig frame) at each beam's firing time.
        directions: unit beam directions (N x 3, rig frame).
        rng: random generator (solid-or-gap and detection draws, depth on the body).
        drone_model: effective-area and incidence assumptions.

    Returns:
        Range (inf where no return) and apparent reflectivity (reflectivity x cos x fill) per beam.
    """
    drone_model = drone_model or DroneReturnModel()
    d = np.asarray(directions, dtype=np.float64)
    rel = np.asarray(centres, dtype=np.float64) - np.asarray(model.position)
    along = np.einsum("ij,ij->i", rel, d)
    offset = along[:, None] * d - rel  # from the drone centre to the beam's closest point
    e1, e2 = _perpendicular_axes(d)
    body = _body_frame(drone_model.yaw_rad)
    size = np.asarray(drone.size_m)
    d_body, e1_body, e2_body = np.abs(d @ body.T), e1 @ body.T, e2 @ body.T
    half_1, half_2 = _half_width(e1_body, size), _half_width(e2_body, size)
    depth = _half_width(d_body, size)
    length, width, height = size
    effective = drone_model.fill_below * d_body[:, 2] * length * width + drone_model.fill_side * (
        d_body[:, 0] * width * height + d_body[:, 1] * length * height
    )
    solid = effective / (4.0 * half_1 * half_2)
    beam_radius = np.maximum(along, 0.0)[:, None] * np.tan(np.radians(model.divergence_deg) / 2) + 1e-9
    fill = _interval_overlap(
        np.einsum("ij,ij->i", offset, e1), half_1, beam_radius[:, 1]
    ) * _interval_overlap(np.einsum("ij,ij->i", offset, e2), half_2, beam_radius[:, 0])
    ranges = along - depth * rng.random(len(d))  # somewhere on the visible half of the body
    apparent = drone.reflectivity * drone_model.incidence_cos * fill
    with np.errstate(divide="ignore", invalid="ignore"):
        p_return = solid * model.detection_probability(apparent, np.maximum(ranges, 1e-3))
    returned = (along > 0) & (fill > 0) & (rng.random(len(d)) < p_return)
    return np.where(returned, ranges, np.inf), apparent


def _drone_candidates(
    model: LidarModel,
    drone: DroneSpec,
    trajectory: Trajectory,
    directions: np.ndarray,
    frame_times: np.ndarray,
    offsets: np.ndarray,
) -> np.ndarray:
    """Indices of the beams that pass within the drone's angular reach during their frame.

    A cone around the drone's mean direction over the frame, wide enough for its motion within the
    frame, its size and the beam footprint; only these beams get the exact test.
    """
    origin = np.asarray(model.position)
    reach = 0.5 * float(np.linalg.norm(drone.size_m)) + 0.1  # body half-diagonal + margin (m)
    spread = np.tan(np.radians(max(model.divergence_deg)) / 2)
    found = []
    for j, t0 in enumerate(frame_times):
        rel = trajectory.position(t0 + np.linspace(0.0, 1.0 / model.frame_rate_hz, 6)) - origin
        distance = np.linalg.norm(rel, axis=1)
        radius = reach + distance.max() * spread
        start, stop = offsets[j], offsets[j + 1]
        if distance.min() <= radius:
            found.append(np.arange(start, stop))
            continue
        axis = rel.mean(axis=0)
        axis /= np.linalg.norm(axis)
        motion = np.arccos(np.clip(rel @ axis / distance, -1.0, 1.0)).max()
        half_angle = motion + np.arcsin(radius / distance.min())
        inside = directions[start:stop] @ axis.astype(np.float32) > np.cos(half_angle)
        found.append(start + np.flatnonzero(inside))
    return np.concatenate(found) if found else np.zeros(0, dtype=np.int64)


# ------------------------------------------------------------------------------------- simulation


def _frame_pulses(model: LidarModel, frame_times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Global pulse indices fired in each frame [t, t + 1 / frame rate), and per-frame offsets."""
    rate = model.point_rate_hz
    starts = np.ceil(frame_times * rate - 1e-6).astype(np.int64)
    stops = np.ceil((frame_times + 1.0 / model.frame_rate_hz) * rate - 1e-6).astype(np.int64)
    counts = stops - starts
    offsets = np.concatenate([[0], np.cumsum(counts)])
    pulses = np.repeat(starts - offsets[:-1], counts) + np.arange(offsets[-1])
    return pulses, offsets


def _detect_background(
    model: LidarModel, scene: Scene, directions: np.ndarray, rng: np.random.Generator
) -> _Returns:
    ranges, reflectivity, incidence = scene.cast(np.asarray(model.position), directions)
    returns = _Returns(ranges.copy(), ranges, reflectivity * incidence)
    hit = np.flatnonzero(np.isfinite(ranges))
    p_det = model.detection_probability(returns.apparent[hit], ranges[hit])
    returns.ranges[hit[rng.random(hit.size) >= p_det]] = np.inf
    return returns


def _add_drone(
    returns: _Returns,
    model: LidarModel,
    drone: DroneSpec,
    trajectory: Trajectory,
    directions: np.ndarray,
    times: np.ndarray,
    frame_times: np.ndarray,
    offsets: np.ndarray,
    rng: np.random.Generator,
    drone_model: DroneReturnModel | None,
) -> None:
    beams = _drone_candidates(model, drone, trajectory, directions, frame_times, offsets)
    if beams.size == 0:
        return
    ranges, apparent = drone_returns(
        model, drone, trajectory.position(times[beams]), directions[beams], rng, drone_model
    )
    nearer = ranges < returns.surface[beams]  # the drone occludes what lies behind it, and vice versa
    hit = beams[nearer]
    returns.ranges[hit] = ranges[nearer]
    returns.apparent[hit] = apparent[nearer]
    returns.origin[hit] = ORIGIN_DRONE


def _add_false(
    returns: _Returns,
    model: LidarModel,
    directions: np.ndarray,
    rng: np.random.Generator,
    sun: SunGlare | None,
) -> None:
    """Solar false alarms: isolated points, uniform range over the gate, low intensity (section 5.4)."""
    n = len(directions)
    chosen = [rng.choice(n, size=rng.binomial(n, model.false_alarm_ratio), replace=False)]
    if sun is not None and sun.boost > 1.0:
        towards = np.asarray(sun.direction, dtype=np.float64)
        towards /= np.linalg.norm(towards)
        near_sun = np.flatnonzero(directions @ towards > np.cos(np.radians(sun.cone_deg)))
        extra = rng.binomial(near_sun.size, min(1.0, model.false_alarm_ratio * (sun.boost - 1.0)))
        chosen.append(rng.choice(near_sun, size=extra, replace=False))
    pulses = np.unique(np.concatenate(chosen))
    returns.ranges[pulses] = rng.uniform(model.blind_zone_m, model.max_range_m, pulses.size)
    returns.apparent[pulses] = rng.uniform(
        0.0, model.false_intensity_max / model.intensity_scale, pulses.size
    )
    returns.origin[pulses] = ORIGIN_FALSE


def _measure(
    model: LidarModel, directions: np.ndarray, ranges: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Noisy points (rig frame, float32): range noise along the beam, angular noise across it."""
    n = len(ranges)
    measured_range = ranges + model.range_noise_m * rng.standard_normal(n)
    noisy = directions + np.radians(model.angle_noise_deg) * rng.standard_normal((n, 3))
    noisy /= np.linalg.norm(noisy, axis=1, keepdims=True)
    points = np.asarray(model.position) + measured_range[:, None] * noisy
    return (np.rint(points / model.resolution_m) * model.resolution_m).astype(np.float32)


def _intensity(
    model: LidarModel, apparent: np.ndarray, origin: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Reported reflectivity (0-150 for diffuse targets): lognormal scatter about the apparent
    reflectivity for real returns; false returns keep their uniform low values."""
    sigma = model.intensity_noise
    scatter = np.exp(sigma * rng.standard_normal(len(apparent)) - 0.5 * sigma**2)
    scatter[origin == ORIGIN_FALSE] = 1.0
    return np.rint(np.clip(model.intensity_scale * apparent * scatter, 0.0, 255.0)).astype(np.float32)


def _simulate_batch(
    model: LidarModel,
    scene: Scene,
    drone: DroneSpec | None,
    trajectory: Trajectory | None,
    frame_times: np.ndarray,
    rng: np.random.Generator,
    drone_model: DroneReturnModel | None,
    sun: SunGlare | None,
) -> list[PointCloud]:
    pulses, offsets = _frame_pulses(model, frame_times)
    directions = model.directions(pulses)
    returns = _detect_background(model, scene, directions, rng)
    if drone is not None and trajectory is not None:
        times = pulses / model.point_rate_hz
        _add_drone(
            returns, model, drone, trajectory, directions, times, frame_times, offsets, rng, drone_model
        )
    _add_false(returns, model, directions, rng, sun)
    kept = np.flatnonzero((returns.ranges >= model.blind_zone_m) & (returns.ranges <= model.max_range_m))
    ranges = returns.ranges[kept].astype(np.float64)
    points = _measure(model, directions[kept].astype(np.float64), ranges, rng)
    origin = returns.origin[kept]
    intensity = _intensity(model, returns.apparent[kept], origin, rng)
    bounds = np.searchsorted(kept, offsets)
    return [
        PointCloud(points[a:b], intensity[a:b], origin[a:b])
        for a, b in zip(bounds[:-1], bounds[1:], strict=True)
    ]


def simulate_lidar(
    model: LidarModel,
    scene: Scene,
    drone: DroneSpec | None,
    trajectory: Trajectory | None,
    frame_times: np.ndarray,
    rng: np.random.Generator,
    *,
    drone_model: DroneReturnModel | None = None,
    sun: SunGlare | None = None,
    batch_frames: int = 10,
) -> list[PointCloud]:
    """Simulate one LiDAR's frames.

    Args:
        model: the sensor (:meth:`LidarModel.mid360` or :meth:`LidarModel.avia`).
        scene: the static background.
        drone: the drone type, or None for a recording without a drone.
        trajectory: the drone's flight (positions at seconds since the recording start), or None.
        frame_times: start of each frame (s since the recording start); frame k holds the pulses
            fired in [t_k, t_k + 1 / frame rate).
        rng: the only source of randomness; the same generator state gives the same clouds.
        drone_model: effective-area assumptions (defaults of :class:`DroneReturnModel`).
        sun: extra false alarms around the sun, or None (uniform false alarms only).
        batch_frames: frames simulated together (a speed/memory knob; it changes the order of the
            random draws, so keep it fixed when comparing seeds).

    Returns:
        One :class:`PointCloud` per frame: points (float32, rig frame), intensity (float32, Livox
        reflectivity 0-150) and origin (uint8 ``ORIGIN_*``), in firing order.
    """
    frame_times = np.asarray(frame_times, dtype=np.float64).reshape(-1)
    step = max(1, int(batch_frames))
    clouds: list[PointCloud] = []
    for start in range(0, len(frame_times), step):
        batch = frame_times[start : start + step]
        clouds += _simulate_batch(model, scene, drone, trajectory, batch, rng, drone_model, sun)
    return clouds
