"""What every descriptor extractor provides, and the image decoding they share."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
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


def forward_by_shape(images: Sequence, forward: Callable[[list], np.ndarray], dim: int) -> np.ndarray:
    """``forward`` on ``images`` (arrays or tensors with a ``shape``), one call per distinct shape.

    Extractors that keep the aspect ratio (CosPlace, EigenPlaces) load frames of another
    aspect as another shape; those cannot share a batch tensor. Usually every image has the
    same shape and this is one call.

    Args:
        forward: a list of images of one shape -> their ``(len, dim)`` descriptors.

    Returns:
        ``(len(images), dim)`` in the images' order; a call whose output is not
        ``(len, dim)`` is returned as it is, for ``normalise_rows`` to report.
    """
    shapes = list(dict.fromkeys(tuple(image.shape) for image in images))
    if len(shapes) == 1:
        return np.asarray(forward(list(images)))
    raw = np.empty((len(images), dim), dtype=np.float32)
    for shape in shapes:
        rows = [i for i, image in enumerate(images) if tuple(image.shape) == shape]
        part = np.asarray(forward([images[i] for i in rows]))
        if part.shape != (len(rows), dim):
            return part
        raw[rows] = part
    return raw


# PIL's modes for 16-bit greyscale (PNG, TIFF). Its other modes of more than 8 bits per
# sample, "I" (32-bit signed int) and "F" (32-bit float), are handled in _to_8bit too.
_SIXTEEN_BIT_MODES = ("I;16", "I;16L", "I;16B", "I;16N")
# TIFF tags that say how "I" data was stored.
_BITS_PER_SAMPLE = 258
_SAMPLE_FORMAT = 339
_SIGNED = 2


def _full_scale(image: Image.Image) -> int:
    """The largest value of ``image``'s integer samples: ``2**bits - 1``, or ``2**(bits-1) - 1`` when signed.

    Bits and signedness come from the file where it says (TIFF); otherwise 16 for
    ``I;16*`` and 32 signed for ``I``.
    """
    if image.mode in _SIXTEEN_BIT_MODES:
        return 2**16 - 1
    tags = getattr(image, "tag_v2", None) or {}
    bits, fmt = tags.get(_BITS_PER_SAMPLE, 32), tags.get(_SAMPLE_FORMAT, _SIGNED)
    bits = bits[0] if isinstance(bits, tuple) else bits
    fmt = fmt[0] if isinstance(fmt, tuple) else fmt
    if not isinstance(bits, int) or not 8 < bits <= 32:
        bits = 32
    return 2 ** (bits - 1) - 1 if fmt == _SIGNED else 2**bits - 1


def _to_8bit(image: Image.Image) -> Image.Image:
    """A greyscale image of more than 8 bits per sample as 8-bit ``"L"``, by its full range.

    Integer samples: ``round(v * 255 / full_scale)`` (:func:`_full_scale`; for 16 bits
    ``v / 257``), so 0 stays black and the largest value is white; PIL's own
    ``convert("L")`` clips at 255 instead, which turns 16-bit images white. Float
    samples (``"F"``) are taken as grey levels in [0, 1]: ``round(v * 255)``, clipped.
    Rounding is half up. Other modes are returned as they are.
    """
    if image.mode not in (*_SIXTEEN_BIT_MODES, "I", "F"):
        return image
    values = np.asarray(image, dtype=np.float64)
    scale = 255.0 if image.mode == "F" else 255.0 / _full_scale(image)
    grey = np.floor(np.clip(np.nan_to_num(values * scale), 0.0, 255.0) + 0.5)
    return Image.fromarray(grey.astype(np.uint8), mode="L")


def open_image(path: Path, mode: str, *, display_size: tuple[int, int] | None = None) -> Image.Image:
    """Decode ``path`` exactly into PIL ``mode`` (``"L"``, ``"RGB"``).

    Greyscale of more than 8 bits per sample (16-bit PNG or TIFF, 32-bit integer or
    float TIFF) is first scaled to 8 bits by its bit depth (:func:`_to_8bit`), so it
    gives what the same picture saved in 8 bits gives.

    Every extractor decodes the whole file: a JPEG decoded at a reduced DCT scale (PIL's
    draft mode) is 2-5x cheaper but gives other pixels, hence another descriptor than
    the recipe written in each extractor's docstring (cosine down to 0.972 for
    ``pixels``, 0.996 for efficientnet-lite0 on GardensPoint). Only pictures for display
    may take that shortcut: ``display_size`` = ``(width, height)`` lets a JPEG decode at the
    smallest DCT scale that still covers it.

    Raises:
        VPRInputError: naming ``path`` when PIL cannot open or decode it.
    """
    try:
        with Image.open(path) as image:
            if display_size is not None:
                image.draft(mode, display_size)
            # _to_8bit / convert() force the full decode here, inside the try, so a
            # truncated file fails with its name instead of later in a worker.
            return _to_8bit(image).convert(mode)
    except FileNotFoundError as exc:
        raise VPRInputError(f"{path}: the image file does not exist; check the dataset folder") from exc
    except (UnidentifiedImageError, Image.DecompressionBombError, OSError, ValueError, SyntaxError) as exc:
        # PIL reports damaged data as OSError ("image file is truncated"), ValueError or
        # SyntaxError depending on the codec.
        raise VPRInputError(f"{path}: cannot read the image ({exc}); replace or remove the file") from exc
