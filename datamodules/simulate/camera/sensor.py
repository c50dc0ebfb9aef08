"""Exposure and the low-light sensor: noise, ADC, ISP tone curve and encoding (Brooks et al. 2019, ELD).

Raw signal = radiance / (white-balance and brightness gains) / r, plus heteroscedastic shot and
read noise, per-row banding noise and ADC quantisation; then digital gain, white balance, gamma
1/2.2 and a smoothstep tone curve to 8-bit sRGB, and JPEG or PNG. :class:`Sensor` holds one
recording's draw of gains and noise levels; :func:`darken_image` applies the same pipeline to an
existing daylight frame.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass

import numpy as np

from datamodules.recording import EncodedImage
from datamodules.simulate.camera.optics import CameraModel

LIGHTS = ("ideal", "dark")  #: daylight, or low light at the exposure ratio r
#: Exposure ratio r of ``light='dark'`` unless told otherwise: the low-light literature (SID/ELD) uses
#: x100-x300 for "extreme low light" (simulation_sources.md 6.2 step 2) [M].
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


# ---------------------------------------------------------------------------------------- sensor
@dataclass
class Sensor:
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
    ) -> Sensor:
        """One recording's draw of the gains and noise levels (arguments as for ``render_frames``)."""
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
        """LUT entries per channel."""
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
    sensor = Sensor.sample(model, "dark", ratio, shot_noise, rng)
    linear = srgb_to_linear(np.asarray(image, dtype=np.float32) / 255.0)
    raw = linear / (sensor.wb * sensor.ratio).astype(np.float32)
    raw = np.minimum(raw, 1.0)
    noisy = raw + np.sqrt(raw * sensor.shot + sensor.read) * rng.standard_normal(raw.shape).astype(np.float32)
    dn = np.clip(np.rint(noisy * sensor.white), 0, sensor.white) / sensor.white
    return np.rint(255.0 * linear_to_srgb(dn * sensor.gain * sensor.wb)).astype(np.uint8)
