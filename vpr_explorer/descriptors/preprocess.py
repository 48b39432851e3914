"""Image file -> network input: resizing rules and pixel normalisations; torch-free.

These run in the decoding threads (PIL and numpy release the GIL), so whatever is done
here is hidden behind the forward pass rather than added to it.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path

import numpy as np
from PIL import Image

from vpr_explorer.descriptors.base import open_image

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
#: The sides, in pixels, a user's model (``custom``) or a torch.hub model (``hub``) may be fed.
INPUT_SIDE_RANGE = (8, 4096)
#: Part of every user and hub model's cache key, bumped when the shared preprocessing changes.
#: 2: 16-bit greyscale is scaled by its bit depth (1 clipped it to a white image).
RECIPE_VERSION = "2"


class Normalisation(StrEnum):
    """How 8-bit RGB becomes the float input a network was trained on."""

    IMAGENET = "imagenet"  # (x / 255 - mean) / std, torchvision's ImageNet statistics
    UNIT = "unit"  # x / 255, in [0, 1]
    SIGNED = "signed"  # x / 127.5 - 1, in [-1, 1] (TF-style)


def _affine(mean: tuple[float, ...], std: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """``(scale, offset)`` per channel such that ``(x / 255 - mean) / std = x * scale - offset``."""
    mean_a, std_a = np.asarray(mean, dtype=np.float64), np.asarray(std, dtype=np.float64)
    return (1.0 / (255.0 * std_a)).astype(np.float32), (mean_a / std_a).astype(np.float32)


_AFFINE: dict[Normalisation, tuple[np.ndarray, np.ndarray]] = {
    Normalisation.IMAGENET: _affine(IMAGENET_MEAN, IMAGENET_STD),
    Normalisation.UNIT: _affine((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
    Normalisation.SIGNED: _affine((0.5, 0.5, 0.5), (0.5, 0.5, 0.5)),
}


def to_chw(rgb: np.ndarray, normalisation: Normalisation) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB -> ``(3, H, W)`` float32, normalised.

    ``out[c] = (rgb[..., c] / 255 - mean[c]) / std[c]``, computed as one multiply-add.
    """
    scale, offset = _AFFINE[normalisation]
    chw = np.ascontiguousarray(rgb.transpose(2, 0, 1), dtype=np.float32)
    chw *= scale[:, None, None]
    chw -= offset[:, None, None]
    return chw


def short_side_size(width: int, height: int, short: int) -> tuple[int, int]:
    """``(width, height)`` after scaling the shorter side to ``short``, keeping the aspect.

    torchvision's ``Resize(short)`` rule: the longer side becomes
    ``int(short * long / short_side)`` (truncated).
    """
    if width <= height:
        return short, int(short * height / width)
    return int(short * width / height), short


def load_squashed(path: Path, size: tuple[int, int], normalisation: Normalisation) -> np.ndarray:
    """``(3, H, W)``: the whole frame resized (bilinear, aspect not kept) to ``size = (W, H)``."""
    image = open_image(path, "RGB").resize(size, Image.BILINEAR)
    return to_chw(np.asarray(image), normalisation)


def load_short_side(path: Path, short: int, normalisation: Normalisation) -> np.ndarray:
    """``(3, H, W)``: shorter side resized (bilinear) to ``short``, aspect kept, no crop.

    PIL's bilinear widens its kernel when shrinking, as torchvision's ``Resize`` on a PIL
    image does (it calls the same function). Frames of another aspect come out another
    shape; ``extract_descriptors`` batches equal shapes together.
    """
    image = open_image(path, "RGB")
    size = short_side_size(image.width, image.height, short)
    if size != image.size:
        image = image.resize(size, Image.BILINEAR)
    return to_chw(np.asarray(image), normalisation)
