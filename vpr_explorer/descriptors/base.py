"""What every descriptor extractor provides, and the image decoding they share."""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from vpr_explorer.errors import VPRInputError


class Extractor(ABC):
    """A global image descriptor: ``load`` one image, ``forward`` a batch.

    Subclasses set the class attributes and implement the two methods. ``load`` runs in
    worker threads and must not touch shared mutable state; ``forward`` runs in the
    calling thread, one batch at a time.

    Attributes:
        name: registry name, e.g. ``"efficientnet-lite0"``.
        version: bumped whenever the descriptors change (preprocessing, weights); part
            of :attr:`cache_key`, so old cached vectors are never mixed with new ones.
        dim: descriptor length D.
    """

    name: str
    version: str
    dim: int

    @property
    def cache_key(self) -> str:
        """``"<name>-<version>"``: the descriptor cache folder for this extractor's output."""
        return f"{self.name}-{self.version}"

    @abstractmethod
    def load(self, path: Path) -> np.ndarray:
        """Decode, resize and normalise one image.

        Returns:
            ``(C, H, W)`` float32 array, the input ``forward`` expects.

        Raises:
            VPRInputError: naming ``path`` when it cannot be read as an image.
        """

    @abstractmethod
    def forward(self, batch: np.ndarray) -> np.ndarray:
        """Descriptors of a batch of loaded images.

        Args:
            batch: ``(B, C, H, W)`` float32, rows made by :meth:`load`.

        Returns:
            ``(B, dim)`` float32, not yet L2-normalised.
        """

    def __repr__(self) -> str:
        return f"{type(self).__name__}(cache_key={self.cache_key!r}, dim={self.dim})"


def open_image(path: Path, mode: str, size: tuple[int, int]) -> Image.Image:
    """Decode ``path`` into PIL ``mode``, at no less than ``size`` = ``(width, height)``.

    JPEG is decoded straight at a reduced scale (1/2, 1/4, 1/8, the DCT's free
    downscaling) when that still leaves at least ``size`` pixels: the caller resizes to
    ``size`` anyway, and it makes decoding 2-5x cheaper, which is what lets decoding
    hide behind the forward pass on a small CPU.

    Raises:
        VPRInputError: naming ``path`` when PIL cannot open or decode it.
    """
    try:
        with Image.open(path) as image:
            image.draft(mode, size)
            # convert() forces the full decode here, inside the try, so a truncated
            # JPEG fails with its file name instead of later in a worker.
            return image.convert(mode)
    except FileNotFoundError as exc:
        raise VPRInputError(f"{path}: the image file does not exist; check the dataset folder") from exc
    except (UnidentifiedImageError, Image.DecompressionBombError, OSError, ValueError, SyntaxError) as exc:
        # PIL reports damaged data as OSError ("image file is truncated"), ValueError or
        # SyntaxError depending on the codec.
        raise VPRInputError(f"{path}: cannot read the image ({exc}); replace or remove the file") from exc
