"""Image file -> network input: resizing rules and pixel normalisations; torch-free.

A torch extractor's input rule is one :class:`DeviceRecipe` (a resize rule and a
normalisation): its :meth:`DeviceRecipe.load` is the CPU path, run in the decoding threads
(PIL and numpy release the GIL), so whatever is done here is hidden behind the forward pass
rather than added to it; ``device_decode`` reads the same recipe to do it on the model's device.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

import numpy as np
from PIL import Image

from vpr_explorer.descriptors.base import open_image
from vpr_explorer.errors import VPRInputError

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


@dataclass(frozen=True)
class DeviceRecipe:
    """A torch extractor's preprocessing: RGB, a bilinear resize, a per-pixel normalisation.

    Exactly one of ``size`` and ``short_side`` is given.

    Attributes:
        normalisation: a :class:`Normalisation` (``preprocess.to_chw``), or a function
            ``(H, W, 3) uint8 -> (3, H, W) float32`` that treats each pixel and channel on
            its own (EfficientNet's ``x / 127.5 - 1``, which is not ``SIGNED``'s
            multiply-add to the last bit).
        size: ``(width, height)``: the whole frame squashed to it, aspect not kept.
        short_side: the shorter side resized to it, aspect kept
            (:func:`~vpr_explorer.descriptors.preprocess.short_side_size`).
    """

    normalisation: Normalisation | Callable[[np.ndarray], np.ndarray]
    size: tuple[int, int] | None = None
    short_side: int | None = None

    def __post_init__(self) -> None:
        if (self.size is None) == (self.short_side is None):
            raise VPRInputError("DeviceRecipe: give size=(width, height) or short_side, exactly one")
        if self.size is not None:
            object.__setattr__(self, "size", (int(self.size[0]), int(self.size[1])))  # hashable, as a key

    def output_size(self, width: int, height: int) -> tuple[int, int]:
        """``(width, height)`` the network is fed for a ``width`` x ``height`` image."""
        if self.size is not None:
            return self.size
        return short_side_size(width, height, self.short_side)

    def to_chw(self, rgb: np.ndarray) -> np.ndarray:
        """``(H, W, 3)`` uint8 RGB at the output size -> ``(3, H, W)`` float32 network input."""
        if isinstance(self.normalisation, Normalisation):
            return to_chw(rgb, self.normalisation)
        return self.normalisation(rgb)

    def load(self, path: Path) -> np.ndarray:
        """The CPU path: PIL decode, PIL bilinear resize (skipped at the output size), :meth:`to_chw`.

        ``(3, H, W)`` float32. PIL's bilinear widens its kernel when shrinking, as torchvision's
        ``Resize`` on a PIL image does (it calls the same function). With ``short_side``, frames
        of another aspect come out another shape; ``extract_descriptors`` batches equal shapes
        together.

        Raises:
            VPRInputError: naming ``path`` when it cannot be read as an image.
        """
        image = open_image(path, "RGB")
        size = self.output_size(image.width, image.height)
        if size != image.size:
            image = image.resize(size, Image.BILINEAR)
        return self.to_chw(np.asarray(image))
