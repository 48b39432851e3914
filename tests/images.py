"""Test images written on the fly (lossless PNG, so their pixels are exactly known)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image


def write_random_png(path: Path, seed: int, size: tuple[int, int]) -> Path:
    """A seeded random RGB image of ``size`` = (width, height)."""
    rng = np.random.default_rng(seed)
    Image.fromarray(rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)).save(path)
    return path
