"""JPEGs decoded, resized and normalised on the model's device (nvJPEG through torchvision).

A torch extractor whose input is "RGB, resized bilinearly by a fixed rule, normalised per
pixel" carries that rule as a :class:`~vpr_explorer.descriptors.preprocess.DeviceRecipe`; its CPU ``load`` is the recipe's
:meth:`DeviceRecipe.load`, so both paths read the same constants. With
``extract_descriptors(..., decode="device")`` the decoding threads only read file bytes and
the calling thread, for each batch:

1. **decodes** the JPEGs with ``torchvision.io.decode_jpeg(list, mode=RGB, device=...)``
   (nvJPEG on a GPU, libjpeg-turbo on the CPU), the whole list in one call; when the call
   fails, image by image, and an image torchvision refuses goes to the CPU path;
2. **resizes** each group of equal input size as PIL's 8-bit bilinear does: horizontal pass,
   round, vertical pass, round (PIL keeps 8-bit samples between its two passes and rounds
   its fixed-point sums half up), each pass ``F.interpolate(mode="bilinear",
   antialias=True, align_corners=False)`` on float32 changing one side only, rounded as
   ``floor(x + 0.5)`` clipped to [0, 255]; a side already at its size is not resampled;
3. **normalises** through a 256-entry table per channel made by the CPU function itself
   (:meth:`DeviceRecipe.to_chw` on the 256 grey levels), so a pixel value gives bit for bit
   the float the CPU path gives it;
4. **forwards** one batch per distinct input shape (short-side recipes give one shape per
   aspect), as the CPU path does (``base.forward_by_shape``).

Steps 1 to 3 (:func:`device_inputs`) run in a thread of their own in ``extract_descriptors``,
one batch ahead of step 4 in the calling thread: while the model runs on a batch and its
descriptors come back, the next batch is decoded. On a GPU both threads issue their work on
the device's current stream, so the kernels stay in order; what overlaps is each thread's
host side (nvJPEG's Huffman decoding, kernel launches, the wait for the copy back).

Which files take the device path is decided from their bytes, not their name
(:func:`device_decodable`): a JPEG (``FF D8 FF``) that ends with its end-of-image marker
(``FF D9``: a truncated file ends elsewhere) and whose frame header is 8-bit Huffman
baseline, extended or progressive with 1 (grey) or 3 (YCbCr) components. Everything else
(PNG, CMYK or YCCK JPEG, arithmetic-coded, 12-bit, a file that cannot be read) is loaded by
``extractor.load`` in the decoding threads, as with ``decode="cpu"``, which also raises the
same :class:`~vpr_explorer.errors.VPRInputError` naming a truncated or unreadable file.

Measured on all 600 GardensPoint JPEGs (960 x 540) on a 2-core x86-64 CPU (AMD EPYC, AVX-512),
no GPU, torch 2.14, torchvision 0.29, Pillow 13.0:

* torchvision's CPU decoder vs PIL's: max abs pixel difference 0 (both are libjpeg-turbo,
  islow IDCT, fancy upsampling). nvJPEG uses its own IDCT and chroma upsampling: its
  difference is measured on a GPU by ``bench_extraction.py --decode both``;
* the resize above vs PIL's, to 224 x 224 from PIL's pixels: max abs difference 1, on
  0.17 % of the values (PIL sums with 22-bit fixed-point coefficients, torch with float32
  ones: they round apart where a sum falls next to a half). One two-sided pass rounded
  once, without PIL's intermediate rounding, differs on 12 % (every 20th frame);
* EfficientNet-Lite0 descriptors, device path on CPU tensors vs the CPU path: min cosine
  0.99997945 over the 600 images (day_left Image020.jpg; mean 0.99999681).

All three from::

    python benchmarks/bench_extraction.py --data /work/shared/datasets --device cpu --decode both --extractors efficientnet-lite0 --repeats 1

On the CPU the device path is the slower one (192 images, 2 cores: 48 img/s against 60 for
PIL in threads): decoding and resizing leave the threads for the calling thread, so
``decode="auto"`` keeps the CPU path there.

The descriptors share the extractor's cache key: within that tolerance they are the same
descriptors, as fp32 on the GPU and on the CPU are.

torchvision 0.29 deprecates its image decoders in favour of TorchCodec; where
``torchvision.io.decode_jpeg`` is gone, ``decode="auto"`` stays on the CPU and
``decode="device"`` is refused saying so.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from vpr_explorer.descriptors.base import Extractor, forward_by_shape
from vpr_explorer.descriptors.preprocess import DeviceRecipe
from vpr_explorer.errors import VPRInputError

if TYPE_CHECKING:
    import torch

    from vpr_explorer.descriptors.runtime import TorchExtractor

JPEG_MAGIC = b"\xff\xd8\xff"
JPEG_END = b"\xff\xd9"
# Frame markers nvJPEG and torchvision decode: Huffman baseline (C0), extended (C1) and
# progressive (C2). C3 (lossless), C5-C7 (hierarchical) and C9-CF (arithmetic) go to PIL.
DEVICE_FRAMES = frozenset({0xC0, 0xC1, 0xC2})
# Every start-of-frame marker: C0-CF but C4 (Huffman tables), C8 (reserved), CC (arithmetic conditioning).
FRAME_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
START_OF_SCAN = 0xDA
# Markers with no length field: TEM, RST0-7, SOI, EOI.
STANDALONE_MARKERS = frozenset({0x01, *range(0xD0, 0xDA)})
DEVICE_COMPONENTS = (1, 3)  # grey, YCbCr; CMYK/YCCK (4) differ in colour conversion between decoders
GREY_LEVELS = 256


class Decode(StrEnum):
    """Where :func:`~vpr_explorer.descriptors.extract.extract_descriptors` decodes JPEGs."""

    AUTO = "auto"  # device when the extractor has a recipe and runs on a GPU, else cpu
    CPU = "cpu"  # PIL in the decoding threads
    DEVICE = "device"  # torchvision on the extractor's device (CPU tensors included)


# ------------------------------------------------------------------ choosing the path


def decoder_missing() -> str | None:
    """Why ``torchvision.io.decode_jpeg`` cannot be used here, or ``None``."""
    try:
        import torchvision.io
    except ImportError as exc:
        return f"torchvision cannot be imported ({exc})"
    if not hasattr(torchvision.io, "decode_jpeg"):
        return f"torchvision {torchvision.__version__} has no io.decode_jpeg"
    return None


def use_device(decode: str, extractor: Extractor) -> bool:
    """Whether ``decode`` sends ``extractor``'s JPEGs to its device.

    ``"auto"`` is ``"device"`` when the extractor has a :class:`DeviceRecipe`, runs on CUDA and
    torchvision can decode JPEGs; else ``"cpu"``.

    Raises:
        VPRInputError: an unknown ``decode``; ``"device"`` for an extractor with no recipe
            (pixels, imported descriptors) or where torchvision cannot decode.
    """
    try:
        choice = Decode(decode)
    except ValueError:
        raise VPRInputError(f"decode={decode!r}: choose one of {', '.join(d.value for d in Decode)}") from None
    if choice is Decode.CPU:
        return False
    recipe = getattr(extractor, "recipe", None)
    if choice is Decode.AUTO:
        device = getattr(extractor, "device", None)
        return recipe is not None and getattr(device, "type", None) == "cuda" and decoder_missing() is None
    if recipe is None:
        raise VPRInputError(
            f"decode='device': descriptor {extractor.name!r} has no device recipe (its input is not a torch "
            "model's resized RGB image); use decode='cpu' or 'auto'"
        )
    missing = decoder_missing()
    if missing is not None:
        raise VPRInputError(f"decode='device': {missing}; use decode='cpu' or 'auto'")
    return True


def device_decodable(data: bytes) -> bool:
    """Whether ``data`` is a complete 8-bit Huffman JPEG of 1 or 3 components (see the module docstring).

    Walks the markers from start-of-image to the first frame header; a start-of-scan
    before it, a length running past the end, or any other frame type says no.
    """
    if not data.startswith(JPEG_MAGIC) or not data.endswith(JPEG_END):
        return False
    i, end = 2, len(data)
    while i + 1 < end:
        if data[i] != 0xFF:
            return False
        while i < end and data[i] == 0xFF:  # fill bytes
            i += 1
        if i >= end:
            return False
        marker = data[i]
        if marker in STANDALONE_MARKERS:
            i += 1
            continue
        if marker == START_OF_SCAN or i + 2 >= end:
            return False
        if marker in FRAME_MARKERS:
            # FF Cn | length (2) | precision (1) | height (2) | width (2) | components (1)
            if i + 8 >= end:
                return False
            height = int.from_bytes(data[i + 4 : i + 6], "big")
            return (marker in DEVICE_FRAMES and data[i + 3] == 8 and height > 0
                    and data[i + 8] in DEVICE_COMPONENTS)
        i += 1 + int.from_bytes(data[i + 1 : i + 3], "big")
    return False


def read_source(path: Path, extractor: Extractor) -> torch.Tensor | np.ndarray:
    """In a decoding thread: a device-decodable JPEG's bytes as a 1-D uint8 tensor, else ``extractor.load(path)``.

    A file that cannot be read goes to ``extractor.load`` too, which raises naming it.
    """
    import torch

    try:
        data = path.read_bytes()
    except OSError:
        return extractor.load(path)
    if not device_decodable(data):
        return extractor.load(path)
    return torch.frombuffer(bytearray(data), dtype=torch.uint8)


# ------------------------------------------------------------------ the batch step


def decode_jpegs(data: list[torch.Tensor], paths: Sequence[Path], extractor: TorchExtractor
                 ) -> list[torch.Tensor | np.ndarray]:
    """``(3, H, W)`` uint8 on ``extractor.device`` per JPEG; one torchvision refuses is ``extractor.load(path)``."""
    from torchvision.io import ImageReadMode, decode_jpeg

    try:
        return list(decode_jpeg(data, mode=ImageReadMode.RGB, device=extractor.device))
    except RuntimeError:
        pass  # one bad image fails the whole list: find it
    out: list[torch.Tensor | np.ndarray] = []
    for item, path in zip(data, paths):
        try:
            out.append(decode_jpeg(item, mode=ImageReadMode.RGB, device=extractor.device))
        except RuntimeError:
            out.append(extractor.load(path))
    return out


@functools.lru_cache(maxsize=16)
def grey_level_table(recipe: DeviceRecipe, device: torch.device) -> torch.Tensor:
    """``(3 * 256,)`` float32 on ``device``: entry ``256 c + v`` is the CPU path's value of level ``v`` in channel ``c``."""
    import torch

    levels = np.arange(GREY_LEVELS, dtype=np.uint8)
    ramp = np.repeat(levels[None, :, None], 3, axis=2)  # (1, 256, 3): every level in every channel
    table = np.asarray(recipe.to_chw(ramp), dtype=np.float32).reshape(3, GREY_LEVELS)
    return torch.from_numpy(table.copy()).reshape(-1).to(device)


def _pil_pass(x: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """One antialiased bilinear pass on float ``(N, 3, H, W)``, rounded half up to 8-bit levels."""
    import torch.nn.functional as F

    x = F.interpolate(x, size=(height, width), mode="bilinear", antialias=True, align_corners=False)
    return x.add_(0.5).floor_().clamp_(0, 255)


def resize_levels(x: torch.Tensor, recipe: DeviceRecipe) -> torch.Tensor:
    """``(N, 3, H, W)`` uint8 images of one size -> their 8-bit levels at the recipe's size, as PIL's bilinear gives them.

    Horizontal pass then vertical pass, each rounded (:func:`_pil_pass`); returned as float32
    whole numbers in [0, 255], or ``x`` itself when it is at the size already.
    """
    height, width = x.shape[2:]
    out_width, out_height = recipe.output_size(width, height)
    if (out_height, out_width) == (height, width):
        return x
    x = x.float()
    if out_width != width:
        x = _pil_pass(x, height, out_width)
    if out_height != height:
        x = _pil_pass(x, out_height, out_width)
    return x


def resize_and_normalise(images: list[torch.Tensor], recipe: DeviceRecipe) -> list[torch.Tensor]:
    """``(3, H, W)`` uint8 images -> ``(3, h, w)`` float32 network inputs, on their device.

    Images of one size are resized together (:func:`resize_levels`), then each level is
    looked up in :func:`grey_level_table`.
    """
    import torch

    out: list[torch.Tensor | None] = [None] * len(images)
    sizes = list(dict.fromkeys(tuple(image.shape[1:]) for image in images))
    for size in sizes:
        rows = [i for i, image in enumerate(images) if tuple(image.shape[1:]) == size]
        x = resize_levels(torch.stack([images[i] for i in rows]), recipe)
        table = grey_level_table(recipe, x.device)
        channel = (torch.arange(3, device=x.device) * GREY_LEVELS).view(1, 3, 1, 1)
        normalised = table.take(x.long() + channel)
        for i, image in zip(rows, normalised.unbind(0)):
            out[i] = image
    return out


def forward_tensors(images: list[torch.Tensor], extractor: TorchExtractor) -> np.ndarray:
    """``extractor.forward_tensor`` on ``(3, h, w)`` inputs, one call per distinct shape (``base.forward_by_shape``)."""
    import torch

    return forward_by_shape(images, lambda group: extractor.forward_tensor(torch.stack(group)), extractor.dim)


def device_inputs(items: list[torch.Tensor | np.ndarray], paths: Sequence[Path], extractor: TorchExtractor
                  ) -> list[torch.Tensor]:
    """One batch of :func:`read_source` results -> its ``(3, h, w)`` network inputs on ``extractor.device``, in order.

    JPEG bytes are decoded, resized and normalised there (:func:`decode_jpegs`,
    :func:`resize_and_normalise`); arrays the CPU path loaded are copied there. Runs in any
    thread (``extract_descriptors`` runs it in one of its own, a batch ahead of the model):
    the inputs are inference tensors, on the device's current stream.
    """
    import torch

    device = extractor.device
    with torch.inference_mode():
        images: list[torch.Tensor | np.ndarray] = list(items)
        jpegs = [i for i, item in enumerate(items) if isinstance(item, torch.Tensor)]
        if jpegs:
            decoded = decode_jpegs([items[i] for i in jpegs], [paths[i] for i in jpegs], extractor)
            on_device = [i for i, image in zip(jpegs, decoded) if isinstance(image, torch.Tensor)]
            for i, image in zip(jpegs, decoded):
                images[i] = image
            if on_device:
                for i, image in zip(on_device, resize_and_normalise([images[i] for i in on_device],
                                                                    extractor.recipe)):
                    images[i] = image
        return [torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).to(device)
                if isinstance(image, np.ndarray) else image for image in images]
