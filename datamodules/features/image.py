"""Image recipes of the camera models, and the darkness protocols.

- images: the left 1280 columns, resized with antialiasing to 256 x 256 (``resnet256``; 112 x 112,
  ``talknet112``, for ASDNet), kept as uint8 and scaled to [-1, 1] (value / 127.5 - 1, no ImageNet
  statistics) at batch time.
- reduced-budget images (not the papers' recipes): ``resnet128`` and ``resnet64`` (the same crop at
  128 x 128 and 64 x 64) and ``talknet56`` (56 x 56) cut the image models' compute about 4x and 16x
  so they can train on a CPU demo budget. A net reads them only when asked
  (``TrajectoryNet(input_recipes={"image": "resnet64"})``, which keeps its parameters unchanged);
  results so obtained are reduced-budget results and are reported as such.
- darkness: ``published`` replaces the image by img * 0 + 3 (a near-black constant, -0.976 after
  scaling) and sets the visibility label to 0 (AV-FDTI ``dark_aug``); ``physical`` renders the
  frame in low light (:func:`datamodules.simulate.camera.darken_image`).
"""

from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torchvision.transforms.functional import InterpolationMode, resize

from datamodules.recording import RecordingError

DARK_MODES = ("published", "physical")
PUBLISHED_DARK_VALUE = 3  #: cv2.addWeighted(img, 0, black, 1, 3) in the AV-FDTI loaders


@dataclass(frozen=True)
class ImageRecipe:
    """An image recipe: crop the left ``crop_width`` columns, resize to ``size`` (H, W)."""

    name: str
    size: tuple[int, int]
    crop_width: int = 1280

    def key(self) -> str:
        return hashlib.sha256(repr(sorted(asdict(self).items())).encode()).hexdigest()[:12]


IMAGE_RECIPES: dict[str, ImageRecipe] = {
    r.name: r
    for r in (
        ImageRecipe("resnet256", (256, 256)),
        ImageRecipe("talknet112", (112, 112)),
        # reduced-budget variants (not the papers'): the same crop at a smaller size
        ImageRecipe("resnet128", (128, 128)),
        ImageRecipe("resnet64", (64, 64)),
        ImageRecipe("talknet56", (56, 56)),
    )
}


def image_recipe(name: str) -> ImageRecipe:
    try:
        return IMAGE_RECIPES[name]
    except KeyError:
        raise ValueError(f"unknown image recipe {name!r}; known: {sorted(IMAGE_RECIPES)}") from None


def image_features(image: np.ndarray, recipe: ImageRecipe) -> torch.Tensor:
    """Crop and resize an H x W x 3 uint8 frame -> uint8 3 x h x w (scaled at batch time)."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise RecordingError(f"expected an H x W x 3 uint8 image, got {image.shape} {image.dtype}")
    crop = torch.from_numpy(np.array(image[:, : recipe.crop_width])).permute(2, 0, 1)
    return resize(crop, list(recipe.size), interpolation=InterpolationMode.BILINEAR, antialias=True).contiguous()


def scale_image(image: torch.Tensor) -> torch.Tensor:
    """uint8 -> float32 in [-1, 1] (value / 127.5 - 1, as the AV-FDTI loaders do)."""
    return image.to(torch.float32) / 127.5 - 1.0


def published_dark(image: torch.Tensor) -> torch.Tensor:
    """The published darkness protocol: every pixel becomes the constant 3 (uint8)."""
    return torch.full_like(image, PUBLISHED_DARK_VALUE)
