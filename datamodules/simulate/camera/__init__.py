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

The package: :mod:`.optics` (the lens, its pose and projection), :mod:`.sky` (the scene's
radiance), :mod:`.drone` (the drone's appearance), :mod:`.sensor` (exposure, low-light noise,
ISP and encoding) and :mod:`.render` (the frames of a recording).
"""

from datamodules.simulate.camera.optics import CameraModel, drone_visible, pixel_rays, project
from datamodules.simulate.camera.render import render_frames, simulate_camera
from datamodules.simulate.camera.sensor import (
    DARK_RATIO,
    LIGHTS,
    darken_image,
    encode_image,
    linear_to_srgb,
    srgb_to_linear,
)
from datamodules.simulate.camera.sky import SkyConfig

__all__ = [
    "DARK_RATIO",
    "LIGHTS",
    "CameraModel",
    "SkyConfig",
    "darken_image",
    "drone_visible",
    "encode_image",
    "linear_to_srgb",
    "pixel_rays",
    "project",
    "render_frames",
    "simulate_camera",
    "srgb_to_linear",
]
