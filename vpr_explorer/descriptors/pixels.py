"""Patch-normalised thumbnails: the classic weight-free VPR descriptor (SeqSLAM's front end)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from vpr_explorer.descriptors.base import Extractor, open_image

WIDTH = 64
HEIGHT = 32
PATCH = 8
# Below this the patch is flat (to float precision): dividing by its std would blow
# rounding noise up to unit variance, so it contributes zeros instead. Nordland's
# tunnel frames are nearly black.
FLAT_STD = 1e-6


def patch_normalise(image: np.ndarray, patch: int = PATCH) -> np.ndarray:
    """Normalise each non-overlapping ``patch`` x ``patch`` block to zero mean, unit std.

    ``out = (x - mean_patch) / std_patch`` (population std); a patch with
    ``std_patch < 1e-6`` becomes zeros.

    Args:
        image: ``(H, W)`` greyscale, ``H`` and ``W`` multiples of ``patch``.

    Returns:
        ``(H, W)`` float32, a new array.
    """
    h, w = image.shape
    # (H, W) -> (H/p, p, W/p, p): axes 1 and 3 run inside one patch.
    blocks = image.astype(np.float64).reshape(h // patch, patch, w // patch, patch)
    mean = blocks.mean(axis=(1, 3), keepdims=True)
    std = blocks.std(axis=(1, 3), keepdims=True)
    flat = std < FLAT_STD
    out = np.where(flat, 0.0, (blocks - mean) / np.where(flat, 1.0, std))
    return out.reshape(h, w).astype(np.float32)


class PixelsExtractor(Extractor):
    """Greyscale 64x32 (W x H) thumbnail, 8x8 patch-normalised, flattened: 2048-d.

    Resizing is PIL bilinear, which widens its kernel when shrinking (an area-like
    filter), so the thumbnail does not alias.
    """

    name = "pixels"
    version = "1"
    dim = WIDTH * HEIGHT

    def load(self, path: Path) -> np.ndarray:
        """``(1, 32, 64)`` float32 patch-normalised thumbnail of grey levels in [0, 1]."""
        image = open_image(path, "L", (WIDTH, HEIGHT)).resize((WIDTH, HEIGHT), Image.BILINEAR)
        grey = np.asarray(image, dtype=np.float32) / 255.0
        return patch_normalise(grey)[None]

    def forward(self, batch: np.ndarray) -> np.ndarray:
        """``(B, 1, 32, 64)`` -> ``(B, 2048)``: the thumbnail is the descriptor."""
        return np.array(batch, dtype=np.float32).reshape(len(batch), -1)
