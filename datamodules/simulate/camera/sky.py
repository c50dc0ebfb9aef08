"""The scene behind the drone in camera-linear radiance: clear sky with the sun, drifting clouds, buildings.

A CIE clear sky (Perez form) coloured from the blue zenith to the hazy tropical horizon, the sun's
glare, a periodic fractal cumulus layer that drifts with the wind (one keyframe every few
seconds), building facades around the horizon and the roof below it; one auto-exposure factor
per recording.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import map_coordinates

from datamodules.simulate.camera.optics import CameraModel, pixel_rays

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


class Sky:
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
