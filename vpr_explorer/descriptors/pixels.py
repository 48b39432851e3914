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

    The recipe, step by step (with numpy and PIL):

    1. decode the whole file exactly (no JPEG draft decoding), greyscale by PIL:
       ``Image.open(path).convert("L")``, ITU-R 601 luma ``L = (299 R + 587 G + 114 B) / 1000``
       of 8-bit RGB; greyscale of more than 8 bits is scaled to 8 by its bit depth first
       (16-bit: ``v / 257``, see :func:`~vpr_explorer.descriptors.base.open_image`);
    2. ``resize((64, 32), Image.BILINEAR)``: PIL's bilinear, which widens its kernel when
       shrinking (an area-like filter, so the thumbnail does not alias), rounded to 8 bits;
    3. ``x = grey / 255`` in float64;
    4. each non-overlapping 8x8 patch: ``(x - mean) / std`` with the population std
       (``ddof=0``); a patch with ``std < 1e-6`` (flat) becomes zeros
       (:func:`patch_normalise`);
    5. flatten row by row (``(32, 64)`` C order) to 2048 values; the extraction pipeline
       divides by the L2 norm.

    Version 2 decodes exactly; version 1 used JPEG draft decoding (a 1/8-scale DCT
    decode of 960x540 frames), which a plain implementation of the recipe matched only to
    cosine 0.97, and turned 16-bit images white.
    """

    name = "pixels"
    version = "2"
    dim = WIDTH * HEIGHT

    def load(self, path: Path) -> np.ndarray:
        """``(1, 32, 64)`` float32 patch-normalised thumbnail of grey levels in [0, 1]."""
        image = open_image(path, "L").resize((WIDTH, HEIGHT), Image.BILINEAR)
        grey = np.asarray(image, dtype=np.float64) / 255.0
        return patch_normalise(grey)[None]

    def forward(self, batch: np.ndarray) -> np.ndarray:
        """``(B, 1, 32, 64)`` -> ``(B, 2048)``: the thumbnail is the descriptor."""
        return np.array(batch, dtype=np.float32).reshape(len(batch), -1)
