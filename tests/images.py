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


def write_noisy_route(root: Path, names: tuple[str, ...] = ("a", "b"), frames: int = 12,
                      corrupt: str | None = None) -> Path:
    """A small traversal-folder route: frame f of every traversal is one base image plus noise.

    ``corrupt`` (e.g. ``"b/005.png"``) is overwritten with bytes that are not an image.
    """
    rng = np.random.default_rng(0)
    base = rng.integers(0, 255, size=(frames, 24, 32, 3), dtype=np.uint8)
    for name in names:
        (root / name).mkdir(parents=True)
        for f in range(frames):
            noisy = np.clip(base[f].astype(int) + rng.integers(-20, 20, base[f].shape), 0, 255).astype(np.uint8)
            Image.fromarray(noisy).save(root / name / f"{f:03d}.png")
    if corrupt:
        (root / corrupt).write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")
    return root


def write_random_route(root: Path, frames: int, size: tuple[int, int], traversals=("day", "night")) -> Path:
    """A traversal-folder route of seeded random PNGs (``frame_FF.png``), ``size`` = (width, height)."""
    for t, traversal in enumerate(traversals):
        (root / traversal).mkdir(parents=True)
        for f in range(frames):
            write_random_png(root / traversal / f"frame_{f:02d}.png", seed=100 * t + f, size=size)
    return root
