"""The camera's optics: an upward-looking equidistant fisheye, its pose on the rig and its projection.

:class:`CameraModel` holds the whole camera's parameters (lens, pose, sensor, encoder); this module
maps rig-frame points to pixels (:func:`project`) and pixels to viewing rays (:func:`pixel_rays`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


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
