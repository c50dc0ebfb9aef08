"""An upward-looking fisheye camera over a tropical daytime sky, with physically based low light.

What it reproduces (``docs/simulation_sources.md``, tags as there):

- section 0: the MMAUD rig looks up at the sky through wide-angle/fisheye cameras whose frames show sky,
  clouds, building edges and the sun [V S1 figures]; the flights were recorded in tropical daytime
  (TAME ground-truth timestamps, Singapore, around 11:47-12:02) [V S2];
- section 6.2: an equidistant fisheye of about 180 deg over 1280 px (0.14 deg/px), so a Mavic 2 spans about
  13 px at 10 m [E]; the low-light pipeline of Brooks et al. 2019 [V S56] with the per-row banding noise and
  the quantisation of ELD [V S57]; navigation LEDs that are emissive and do not scale with the ratio [E].

Per frame: scene radiance in camera-linear RGB (sky keyframe with sun, clouds and buildings; the drone's
body, arms, motors and spinning-propeller discs at their physical angular size, anti-aliased) -> raw
(divide by the white-balance and brightness gains) -> x 1/r, plus the LEDs -> heteroscedastic shot + read
noise, row noise, ADC quantisation -> digital gain -> white balance, gamma 1/2.2, smoothstep tone curve,
8 bit -> JPEG or PNG. The scene is rendered directly in linear radiance, which is what Brooks'
unprocessing (inverse smoothstep, then x^2.2: :func:`srgb_to_linear`) of its clean sRGB render
(:func:`linear_to_srgb`) returns, so the round trip through sRGB is skipped.

Not modelled: the colour-correction matrix (Brooks inverts and reapplies one; it mixes and amplifies the
noise between channels), Bayer mosaic and demosaicking, Poisson shot noise and Tukey-lambda read noise
(ELD; Gaussian here), ISP noise reduction, motion blur, lens distortion beyond the equidistant model (MMAUD
calibrates an omnidirectional model with radtan distortion), drone attitude tilt, lens flare ghosts.
Pixel noise is drawn once per recording and used per frame at a random shift, row order and sign (drawing
2.8 M fresh normals costs ~35 ms, more than the frame budget); each frame's noise is still independent from
pixel to pixel, and the row noise is drawn fresh.

Frame rate: MMAUD's cameras run at 30 Hz (maintainer, MMAUD issue #42); the default is 10 Hz, aligned with
the 10 Hz labels, to keep recordings small. It is a parameter.
"""

from __future__ import annotations

import io
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import map_coordinates

from datamodules.recording import EncodedImage
from datamodules.simulate.drones import DroneSpec
from datamodules.simulate.trajectory import Trajectory

LIGHTS = ("ideal", "dark")

# ------------------------------------------------------------------------------------- constants
#: Exposure ratios r of the low-light literature (SID/ELD use x100-x300 for "extreme low light"),
#: simulation_sources.md 6.2 step 2 [M]; ``light='dark'`` uses ``DARK_RATIO`` unless told otherwise.
EXPOSURE_RATIOS = (1.0, 10.0, 30.0, 100.0, 300.0)
DARK_RATIO = 100.0
#: Brooks et al. 2019 noise levels (S56 ``random_noise_levels``; simulation_sources.md 6.2 step 3) [V]:
#: log lambda_shot ~ U(log 1e-4, log 0.012); log lambda_read = 2.18 log lambda_shot + 1.20 + N(0, 0.26).
SHOT_LAMBDA_RANGE = (1e-4, 0.012)
READ_SLOPE, READ_INTERCEPT, READ_SIGMA = 2.18, 1.20, 0.26
#: Daylight ('ideal') noise: the lowest Brooks shot level (base ISO, about 1 / full well of a small-pixel
#: sensor) with the read level on the regression line (S56) [V range, E choice].
DAY_SHOT_LAMBDA = 1e-4
#: Brooks unprocessing gains (S56; simulation_sources.md 6.2 step 1) [V]: brightness 1 / rgb_gain ~ N(0.8, 0.1),
#: red gain ~ U(1.9, 2.4), blue gain ~ U(1.5, 1.9).
BRIGHTNESS_MEAN, BRIGHTNESS_STD = 0.8, 0.1
RED_GAIN_RANGE = (1.9, 2.4)
BLUE_GAIN_RANGE = (1.5, 1.9)
GAMMA = 2.2  #: gamma of the Brooks pipeline (S56; simulation_sources.md 6.2 steps 1 and 4) [V]
#: ELD per-row banding noise (S57): in the published log-linear calibrations of public ELD
#: re-implementations (log sigma = slope log K + bias) the row-noise scale is 0.12-0.15 of the Gaussian
#: read-noise scale for system gains K = 1-3 [V numbers, E ratio]. Std of the row offset / read-noise std.
ROW_NOISE_FRACTION = 0.15
#: Sun: angular radius 0.27 deg [M]; the saturated bloom (3 radii) and the glare (e-folding 2 deg) are a
#: visual estimate of fisheye sky photos, which show a saturated blob some tens of pixels wide [E].
SUN_RADIUS_DEG = 0.27
#: CIE standard general sky type 12, "clear, low illuminance turbidity" (CIE S 011/E:2003, Perez form
#: (1 + a exp(b / cos Z)) (1 + c (exp(d chi) - exp(d pi / 2)) + e cos^2 chi)) [M]: a, b, c, d, e.
CIE_CLEAR_SKY = (-1.0, -0.32, 10.0, -3.0, 0.45)
#: Linear chroma (mean ~1) of the clear sky at the zenith and of the hazy tropical horizon [E].
SKY_ZENITH_RGB = (0.45, 0.80, 1.75)
SKY_HORIZON_RGB = (0.90, 0.98, 1.12)
#: Sunlit cumulus are 3-4x brighter than the blue zenith and brighter still towards the sun (forward
#: scattering); thick cores are darker at the base [E].
CLOUD_LUMINANCE = 3.5
CLOUD_BASE_DARKENING = 0.4
CLOUD_PERIOD_M, CLOUD_TEXELS = 6000.0, 512  #: periodic cloud texture: period (m), texels per side [E]
CLOUD_TEXEL_M = CLOUD_PERIOD_M / CLOUD_TEXELS
#: Facades: albedo 0.2-0.5 (concrete, glass, paint) [M] times their irradiance relative to the zenith sky
#: radiance, 1.0 (shaded) to 3.0 (sunlit) [E]. The roof, seen only by a tilted camera: 0.3 x 2.7 [E].
FACADE_ALBEDO = (0.2, 0.5)
FACADE_LIGHTING = (1.0, 3.0)
ROOF_LUMINANCE = 0.8
#: Auto-exposure: the median of the image circle is put at linear 0.25 (~52 % sRGB grey after the tone
#: curve), as metering on a bright sky does [E].
AUTO_EXPOSURE_MEDIAN = 0.25
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


# ----------------------------------------------------------------------------------------- model
@dataclass
class CameraModel:
    """An upward-looking equidistant fisheye camera, its sensor, ISP and encoder.

    Looking at the zenith (``tilt_deg`` 0, ``roll_deg`` 0), the image's right (u) points to rig +y and its top
    to rig +x, so the long image side covers the long side of the MMAUD flight region (y in [-5, 25] m).
    ``fov_deg`` spans the image width; the image circle (up to ``fov_deg / 2`` from the axis) is cut by the
    top and bottom edges and the corners outside it are black, as in a cropped circular fisheye.
    """

    width: int = 1280
    height: int = 720
    #: MMAUD's cameras run at 30 Hz (maintainer, MMAUD issue #42); 10 Hz matches the labels and keeps
    #: recordings small.
    frame_rate: float = 10.0  #: Hz
    fov_deg: float = 180.0  #: across the width: 180 deg / 1280 px = 0.14 deg/px (simulation_sources.md 6.2) [E]
    position: tuple[float, float, float] = (0.1, 0.0, 1.3)  #: rig frame (m)
    tilt_deg: float = 0.0  #: angle of the optical axis from the zenith
    tilt_azimuth_deg: float = 0.0  #: azimuth the axis tilts towards (from rig +x towards +y)
    roll_deg: float = 0.0  #: rotation of the image about the optical axis
    vignetting: float = 0.3  #: relative illumination lost at the edge of the image circle [E]
    adc_bits: int = 12  #: raw bit depth, i.e. the quantisation step of ELD (S57) [E: low-cost CMOS]
    #: Largest gain the auto-exposure can apply; the ISP gain is min(r, max_gain), 16 = 24 dB [E]. Use
    #: ``math.inf`` for the SID/ELD convention (gain = r: brightness restored, only the noise grows).
    max_gain: float = 16.0
    encoding: str = "jpeg"  #: 'jpeg' or 'png'
    #: Measured mean JPEG sizes per frame at 1280 x 720, quality 70: day ~41 KB (34-48 KB between
    #: recordings; ~29 KB at quality 50), dark (r = 100) ~290 KB (120-520 KB, set by the sampled noise
    #: level); at 640 x 360: day ~17 KB, dark ~62 KB. A flat grey 1280 x 720 frame already takes ~5.7 KB,
    #: so a ~7.5 KB/frame budget cannot be met at this size with a realistic sky.
    jpeg_quality: int = 70
    jpeg_optimize: bool = True  #: optimised Huffman tables: ~30 % smaller files, same pixels

    def __post_init__(self) -> None:
        if self.encoding not in ("jpeg", "png"):
            raise ValueError(f"encoding must be 'jpeg' or 'png', not {self.encoding!r}")
        if not 0.0 < self.fov_deg <= 360.0:
            raise ValueError(f"fov_deg must be in (0, 360], not {self.fov_deg}")

    @property
    def focal_px(self) -> float:
        """Equidistant focal length f (px/rad): image radius = f x angle from the optical axis."""
        return (self.width / 2.0) / math.radians(self.fov_deg / 2.0)

    @property
    def deg_per_px(self) -> float:
        return math.degrees(1.0 / self.focal_px)

    @property
    def centre(self) -> tuple[float, float]:
        """Principal point (u, v); pixel centres are at integer coordinates."""
        return (self.width - 1) / 2.0, (self.height - 1) / 2.0

    def rotation(self) -> np.ndarray:
        """Camera-to-rig rotation; its columns are the camera axes (x right, y down, z optical) in the rig."""
        roll = math.radians(self.roll_deg)
        c, s = math.cos(roll), math.sin(roll)
        zenith = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # x: rig +y, y: rig -x
        roll_m = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        tilt, az = math.radians(self.tilt_deg), math.radians(self.tilt_azimuth_deg)
        ax, ay = -math.sin(az), math.cos(az)  # rotation axis z x (cos az, sin az, 0)
        k = np.array([[0.0, 0.0, ay], [0.0, 0.0, -ax], [-ay, ax, 0.0]])
        tilt_m = np.eye(3) + math.sin(tilt) * k + (1.0 - math.cos(tilt)) * (k @ k)  # Rodrigues
        return tilt_m @ zenith @ roll_m

    def frame_times(self, duration: float) -> np.ndarray:
        """Frame times (s since start) at the frame rate over ``duration`` seconds."""
        return np.arange(0.0, duration, 1.0 / self.frame_rate)


@dataclass
class SkyConfig:
    """Ranges of the random scene around the rig, sampled once per recording [E]."""

    #: Singapore on 24 Aug at ~11:55 gives ~70 deg (TAME timestamps, S2); the range covers other hours [E].
    sun_elevation_deg: tuple[float, float] = (55.0, 80.0)
    cloud_cover: tuple[float, float] = (0.1, 0.5)  #: covered fraction of the cumulus layer [E]
    cloud_base_m: float = 1000.0  #: tropical cumulus base height [M]
    cloud_wind_mps: tuple[float, float] = (0.0, 5.0)  #: drift speed of the cloud layer [E]
    #: Clouds drift in steps, one sky keyframe every this many seconds: <= 6 px at the zenith at 5 m/s;
    #: a keyframe costs ~70 ms at 1280 x 720, i.e. ~2.5 ms per frame at 10 Hz.
    keyframe_interval_s: float = 3.0
    buildings: tuple[int, int] = (3, 8)  #: number of surrounding building facades [E]
    building_elevation_deg: tuple[float, float] = (3.0, 25.0)  #: elevation of a facade's top edge [E]


# ------------------------------------------------------------------------------------ projection
def project(model: CameraModel, points_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates (u, v) of rig-frame points (... x 3) and whether they are in the image.

    A point is visible when it is at most ``fov_deg / 2`` from the optical axis and falls on the image
    (``-0.5 <= u <= width - 0.5``, same for v): a drone below the horizon of a zenith camera, or outside the
    cropped image circle, is not in the image.
    """
    points = np.asarray(points_xyz, dtype=np.float64)
    cam = (points - np.asarray(model.position)) @ model.rotation()  # rig -> camera: R^T p
    x, y, z = cam[..., 0], cam[..., 1], cam[..., 2]
    theta = np.arctan2(np.hypot(x, y), z)
    phi = np.arctan2(y, x)
    cx, cy = model.centre
    u = cx + model.focal_px * theta * np.cos(phi)
    v = cy + model.focal_px * theta * np.sin(phi)
    in_fov = (theta <= math.radians(model.fov_deg / 2.0)) & (np.linalg.norm(cam, axis=-1) > 1e-6)
    on_image = (u >= -0.5) & (u <= model.width - 0.5) & (v >= -0.5) & (v <= model.height - 0.5)
    return u, v, in_fov & on_image


def drone_visible(model: CameraModel, position: np.ndarray) -> bool:
    """Whether a rig-frame point (the drone's centre) is in the image."""
    return bool(project(model, np.asarray(position, dtype=np.float64).reshape(3))[2])


def pixel_rays(model: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """Unit viewing directions of all pixels in the rig frame (H x W x 3) and the image-circle mask."""
    cx, cy = model.centre
    u = np.arange(model.width, dtype=np.float64) - cx
    v = np.arange(model.height, dtype=np.float64)[:, None] - cy
    theta = np.hypot(u, v) / model.focal_px
    phi = np.arctan2(v, u)
    cam = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)
    return cam @ model.rotation().T, theta <= math.radians(model.fov_deg / 2.0)


# ------------------------------------------------------------------------------------ tone curve
def srgb_to_linear(srgb: np.ndarray) -> np.ndarray:
    """Brooks unprocessing of the tone (S56): inverse smoothstep, then gamma expansion x^2.2."""
    y = np.clip(np.asarray(srgb, dtype=np.float64), 0.0, 1.0)
    x = 0.5 - np.sin(np.arcsin(1.0 - 2.0 * y) / 3.0)
    return np.maximum(x, 1e-8) ** GAMMA


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Forward tone (S56 ``process``): clip to [0, 1], gamma compression x^(1/2.2), smoothstep."""
    x = np.clip(np.asarray(linear, dtype=np.float64), 1e-8, 1.0) ** (1.0 / GAMMA)
    return 3.0 * x**2 - 2.0 * x**3


def encode_image(model: CameraModel, image: np.ndarray) -> EncodedImage:
    """Compress an H x W x 3 uint8 RGB frame as ``model`` says."""
    from PIL import Image

    buffer = io.BytesIO()
    picture = Image.fromarray(np.ascontiguousarray(image, dtype=np.uint8))
    if model.encoding == "png":
        picture.save(buffer, format="PNG", compress_level=6)
    else:
        picture.save(buffer, format="JPEG", quality=model.jpeg_quality, optimize=model.jpeg_optimize)
    return EncodedImage(buffer.getvalue(), model.encoding)


# ------------------------------------------------------------------------------------------ sky
def _cloud_texture(rng: np.random.Generator) -> np.ndarray:
    """A periodic fractal field on the cloud layer: power ~ k^-3.6 below 1.5 km scales, unit variance [E]."""
    k = np.fft.fftfreq(CLOUD_TEXELS, d=CLOUD_TEXEL_M)
    k2 = k[:, None] ** 2 + k[None, :] ** 2
    amplitude = (k2 + (1.0 / 1500.0) ** 2) ** (-3.6 / 4.0)
    shape = (CLOUD_TEXELS, CLOUD_TEXELS)
    field = np.fft.ifft2((rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) * amplitude).real
    return ((field - field.mean()) / field.std()).astype(np.float32)


def _perez(cos_zenith: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """Relative luminance of the CIE clear sky for the cosine of the zenith angle and the angle to the sun."""
    a, b, c, d, e = CIE_CLEAR_SKY
    gradation = 1.0 + a * np.exp(b / np.maximum(cos_zenith, 0.02))
    indicatrix = 1.0 + c * (np.exp(d * gamma) - np.exp(d * math.pi / 2.0)) + e * np.cos(gamma) ** 2
    return gradation * indicatrix


class _Sky:
    """The scene of one recording in camera-linear RGB: static sky, sun and buildings; drifting clouds.

    Radiances are relative to the zenith sky away from the sun (= 1), times one auto-exposure factor per
    recording that puts the median of the first keyframe at ``AUTO_EXPOSURE_MEDIAN``. Pixels are kept
    flattened; ``index`` lists the open-sky pixels, the only ones clouds and sun can change.
    """

    def __init__(self, model: CameraModel, config: SkyConfig, rng: np.random.Generator):
        self.config = config
        rays, circle = pixel_rays(model)
        self.shape = circle.shape
        rays = rays.reshape(-1, 3).astype(np.float32)
        circle = circle.reshape(-1)
        elevation = np.arcsin(np.clip(rays[:, 2], -1.0, 1.0))
        azimuth = np.arctan2(rays[:, 1], rays[:, 0])

        # buildings: a facade whose top edge is at elevation e0 straight ahead (azimuth az0) has its top at
        # atan(tan(e0) cos(az - az0)) elsewhere; the highest edge hides the ones behind
        skyline = np.zeros(azimuth.shape, dtype=np.float32)
        solid = np.zeros(rays.shape, dtype=np.float32)
        for _ in range(int(rng.integers(config.buildings[0], config.buildings[1] + 1))):
            az0 = rng.uniform(-math.pi, math.pi)
            half_width = math.radians(rng.uniform(8.0, 40.0))
            top = math.tan(math.radians(rng.uniform(*config.building_elevation_deg)))
            luminance = rng.uniform(*FACADE_ALBEDO) * rng.uniform(*FACADE_LIGHTING)
            tint = luminance * (1.0 + rng.uniform(-0.06, 0.06, size=3))
            offset = (azimuth - az0 + math.pi) % (2.0 * math.pi) - math.pi
            edge = np.where(np.abs(offset) < half_width, np.arctan(top * np.cos(offset)), 0.0)
            in_front = (edge > skyline) & (elevation < edge)
            height = np.clip(elevation / max(float(edge.max()), 1e-3), 0.0, 1.0)
            solid[in_front] = tint * (1.0 - 0.3 * height[in_front, None])  # darker up the wall
            skyline = np.maximum(skyline, edge)
        ground = elevation < 0.0
        solid[ground] = ROOF_LUMINANCE
        self.solid = solid * circle[:, None]
        self.index = np.flatnonzero(circle & ~ground & (elevation >= skyline))

        # clear sky with the sun
        sun_el = math.radians(rng.uniform(*config.sun_elevation_deg))
        sun_az = rng.uniform(-math.pi, math.pi)
        sun = np.array([math.cos(sun_az), math.sin(sun_az), math.tan(sun_el)]) * math.cos(sun_el)
        view = rays[self.index]
        cos_z = np.clip(view[:, 2], 0.0, 1.0)
        gamma = np.arccos(np.clip(view @ sun.astype(np.float32), -1.0, 1.0))
        luminance = _perez(cos_z, gamma) / _perez(np.ones(1), np.full(1, math.pi / 2.0))
        weight = ((1.0 - cos_z) ** 2)[:, None]
        colour = np.asarray(SKY_ZENITH_RGB) * (1.0 - weight) + np.asarray(SKY_HORIZON_RGB) * weight
        whiten = np.exp(-gamma / 0.3)[:, None]  # the aureole around the sun is whiter [E]
        colour = colour * (1.0 - whiten) + whiten
        self.sky = (colour * luminance[:, None]).astype(np.float32)
        glare = 4.0 * np.exp(-gamma / 0.035) + 100.0 * (gamma < math.radians(3.0 * SUN_RADIUS_DEG))
        self.glare = glare.astype(np.float32)[:, None]
        self.cloud_light = (CLOUD_LUMINANCE * (1.0 + 2.0 * np.exp(-gamma / 0.4))).astype(np.float32)[:, None]

        # cloud layer: a sky pixel looking along (x, y, z) sees the layer point (x, y) / z x base height;
        # clouds fade into the haze towards the horizon, which also hides the texture's aliasing there [E]
        self.layer_xy = view[:, :2] / np.maximum(view[:, 2:], 0.05) * config.cloud_base_m
        distance = np.hypot(self.layer_xy[:, 0], self.layer_xy[:, 1]) / (3.0 * config.cloud_base_m)
        self.haze = np.exp(-(distance**2)).astype(np.float32)[:, None]
        self.texture = _cloud_texture(rng)
        self.threshold = np.float32(np.quantile(self.texture, 1.0 - rng.uniform(*config.cloud_cover)))
        speed, direction = rng.uniform(*config.cloud_wind_mps), rng.uniform(-math.pi, math.pi)
        self.wind = speed * np.array([math.cos(direction), math.sin(direction)])

        axis = model.rotation()[:, 2].astype(np.float32)
        theta = np.arccos(np.clip(rays @ axis, -1.0, 1.0)) / math.radians(model.fov_deg / 2.0)
        vignette = (1.0 - model.vignetting * np.clip(theta, 0.0, 1.0) ** 2) * circle
        self.vignette = vignette.reshape(self.shape).astype(np.float32)
        self.exposure = 1.0
        first = self.radiance(0.0).mean(axis=-1)[circle.reshape(self.shape)]
        self.exposure = AUTO_EXPOSURE_MEDIAN / float(np.median(first))

    def keyframe_time(self, t: float) -> float:
        """Start of the keyframe interval holding time ``t`` (a still sky has a single keyframe)."""
        step = self.config.keyframe_interval_s
        if not np.any(self.wind) or step <= 0:
            return 0.0
        return math.floor(t / step) * step

    def radiance(self, t: float) -> np.ndarray:
        """Camera-linear scene radiance at time ``t`` (H x W x 3, float32), before vignetting."""
        xy = (self.layer_xy - self.wind * t) / CLOUD_TEXEL_M
        density = map_coordinates(self.texture, [xy[:, 1], xy[:, 0]], order=1, mode="grid-wrap")[:, None]
        alpha = np.clip((density - self.threshold) / 0.3, 0.0, 1.0) * self.haze  # soft cloud edges
        thickness = np.clip((density - self.threshold) / 2.0, 0.0, 1.0)
        cloud = self.cloud_light * (1.0 - CLOUD_BASE_DARKENING * thickness)
        glare = self.glare * (1.0 - 0.9 * alpha)  # the sun dims behind clouds
        sky = self.sky * (1.0 - alpha) + cloud * alpha + glare
        out = self.solid.copy()
        out[self.index] = sky
        out *= np.float32(self.exposure)
        return out.reshape(*self.shape, 3)


# ---------------------------------------------------------------------------------------- sensor
@dataclass
class _Sensor:
    """Per-recording sensor state: gains, noise levels, exposure ratio and the output look-up table.

    Raw values are normalised to white = 1 and stored in ADC units (DN). Each channel owns a LUT block of
    3 (white + 1) entries covering DN from -(white + 1) to 2 (white + 1) - 1, so that noise never reaches a
    neighbouring channel's block and the ADC clipping happens inside the LUT.
    """

    ratio: float
    gain: float
    shot: float  #: lambda_shot: noise variance per unit raw signal
    read: float  #: lambda_read: signal-independent noise variance
    wb: np.ndarray  #: raw -> white-balanced linear, per channel: [red, 1, blue] / brightness
    white: int  #: raw white level (DN)

    @classmethod
    def sample(
        cls, model: CameraModel, light: str, ratio: float | None, shot: float | None, rng: np.random.Generator
    ) -> _Sensor:
        # draw the same numbers in both modes, so that 'ideal' and 'dark' of one rng show the same scene
        brightness = float(np.clip(rng.normal(BRIGHTNESS_MEAN, BRIGHTNESS_STD), 0.5, 1.1))
        red, blue = rng.uniform(*RED_GAIN_RANGE), rng.uniform(*BLUE_GAIN_RANGE)
        log_shot = rng.uniform(math.log(SHOT_LAMBDA_RANGE[0]), math.log(SHOT_LAMBDA_RANGE[1]))
        read_residual = rng.normal(0.0, READ_SIGMA)
        if light not in LIGHTS:
            raise ValueError(f"light must be one of {LIGHTS}, not {light!r}")
        if light == "ideal":
            log_shot, read_residual = math.log(DAY_SHOT_LAMBDA), 0.0
        if shot is not None:
            log_shot, read_residual = math.log(shot), 0.0
        ratio = (1.0 if light == "ideal" else DARK_RATIO) if ratio is None else float(ratio)
        if ratio < 1.0:
            raise ValueError(f"exposure ratio must be >= 1, not {ratio}")
        return cls(
            ratio=ratio,
            gain=min(ratio, model.max_gain),
            shot=math.exp(log_shot),
            read=math.exp(READ_SLOPE * log_shot + READ_INTERCEPT + read_residual),
            wb=np.array([red, 1.0, blue]) / brightness,
            white=2**model.adc_bits - 1,
        )

    @property
    def block(self) -> int:
        return 3 * (self.white + 1)

    def lut(self) -> np.ndarray:
        """LUT index -> 8-bit sRGB: ADC clipping, digital gain, white balance, gamma and tone curve."""
        dn = np.clip(np.arange(self.block) - (self.white + 1), 0, self.white) / self.white
        blocks = [np.rint(255.0 * linear_to_srgb(dn * self.gain * g)) for g in self.wb]
        return np.concatenate(blocks).astype(np.uint8)

    def raw_scale(self, vignette: np.ndarray) -> np.ndarray:
        """Radiance -> raw signal, per pixel and channel: vignetting / white-balance gains / r."""
        return (vignette[..., None] / (self.wb * self.ratio)).astype(np.float32)

    def expected(self, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """LUT index of the mean raw signal (+0.5, so that truncation rounds) and the noise std, in DN.

        The signal is clipped at full well; the noise variance is lambda_shot raw + lambda_read (S56).
        """
        raw = np.minimum(raw, np.float32(1.0), dtype=np.float32)
        std = np.sqrt(raw * np.float32(self.shot) + np.float32(self.read))
        std *= np.float32(self.white)
        raw *= np.float32(self.white)
        raw += np.arange(3, dtype=np.float32) * self.block + (self.white + 1.5)
        return raw, std


# ----------------------------------------------------------------------------------------- drone
def _headings(trajectory: Trajectory, times: np.ndarray) -> np.ndarray:
    """Yaw (rad) along the horizontal velocity, held while the drone hovers (< 0.3 m/s)."""
    velocity = np.asarray(trajectory.velocity(times)).reshape(-1, 3)
    moving = np.hypot(velocity[:, 0], velocity[:, 1]) > 0.3
    yaw = np.arctan2(velocity[:, 1], velocity[:, 0])
    last_moving = np.maximum.accumulate(np.where(moving, np.arange(len(times)), -1))
    return np.where(last_moving >= 0, yaw[np.maximum(last_moving, 0)], 0.0)


@dataclass
class _DroneShape:
    """Body-frame primitives (x forward, y left, z up; metres) of a quadcopter seen from below."""

    ellipsoids: list  #: (centre, semi-axes) of the body and the motors: opaque
    arms: list  #: (start, end) of the arm capsules: opaque
    arm_radius: float
    props: list  #: (centre, semi-axes) of the spinning-propeller discs: faint
    leds: list  #: (position, colour name)

    @classmethod
    def of(cls, drone: DroneSpec) -> _DroneShape:
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


def _draw_drone(
    model: CameraModel, shape: _DroneShape, position: np.ndarray, yaw: float, led_peak_10m: float
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


# ------------------------------------------------------------------------------------- rendering
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
    scene = _Sky(model, sky or SkyConfig(), rng)
    sensor = _Sensor.sample(model, light, ratio, shot_noise, rng)
    lut = sensor.lut()
    pad = 64
    pool = rng.standard_normal((model.height + pad, model.width + pad, 3), dtype=np.float32)
    np.clip(pool, -6.0, 6.0, out=pool)  # 6 sigma of the largest Brooks level < 0.7 white: inside the guard
    row_std = ROW_NOISE_FRACTION * math.sqrt(sensor.read) * sensor.white
    scale = sensor.raw_scale(scene.vignette)

    shape = _DroneShape.of(drone)
    positions = np.asarray(trajectory.position(times)).reshape(-1, 3)
    yaws = _headings(trajectory, times)
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
        drawn = _draw_drone(model, shape, positions[i], float(yaws[i]), led_peak)
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


def darken_image(
    image: np.ndarray,
    rng: np.random.Generator,
    ratio: float = DARK_RATIO,
    model: CameraModel | None = None,
    shot_noise: float | None = None,
) -> np.ndarray:
    """Turn a daylight frame (H x W x 3 uint8 sRGB) into the same view in low light.

    The physical pipeline of :func:`render_frames` applied to an existing image: unprocess to
    linear raw with sampled white-balance gains, scale by 1 / ``ratio``, add Brooks shot and read
    noise, quantise with the ADC, then auto-exposure gain (capped at ``model.max_gain``) and the
    ISP. Unlike a recording simulated with ``light='dark'``, emissive LEDs dim with the rest here.
    """
    model = model or CameraModel()
    sensor = _Sensor.sample(model, "dark", ratio, shot_noise, rng)
    linear = srgb_to_linear(np.asarray(image, dtype=np.float32) / 255.0)
    raw = linear / (sensor.wb * sensor.ratio).astype(np.float32)
    raw = np.minimum(raw, 1.0)
    noisy = raw + np.sqrt(raw * sensor.shot + sensor.read) * rng.standard_normal(raw.shape).astype(np.float32)
    dn = np.clip(np.rint(noisy * sensor.white), 0, sensor.white) / sensor.white
    return np.rint(255.0 * linear_to_srgb(dn * sensor.gain * sensor.wb)).astype(np.uint8)
