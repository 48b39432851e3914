"""AlexNet conv3 with a seeded Gaussian random projection: 4096-d, as in VPR_Tutorial.

The recipe of stschubert/VPR_Tutorial ``feature_extraction/feature_extractor_holistic.py``
(``AlexNetConv3Extractor``), which the paper's AlexNet numbers use:

* torchvision AlexNet with ImageNet weights (``AlexNet_Weights.IMAGENET1K_V1``, the file
  ``alexnet-owt-7be5be79.pth``), cut after the third convolution: ``features[:7]``
  (conv1, ReLU, pool, conv2, ReLU, pool, conv3; no ReLU after conv3);
* input: the whole frame resized to 224 x 224 (bilinear, aspect not kept, no crop),
  ImageNet mean/std normalisation;
* the ``(384, 13, 13)`` map flattened in channel, row, column order: 64,896 values;
* projected to 4,096 by ``P``: ``np.random.default_rng(seed=0).standard_normal((64896,
  4096), float32)`` with each row then scaled to unit length; ``d = f @ P``.

``P`` is regenerated from the seed in each process (a few seconds, 1 GB), never stored,
and is bit-identical to VPR_Tutorial's, so the descriptors match the tutorial's. Images
are decoded exactly (no JPEG draft decoding). The extraction pipeline L2-normalises them.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np
import torch
import torchvision

from vpr_explorer.descriptors.checkpoints import ALEXNET, locate_weights
from vpr_explorer.descriptors.preprocess import DeviceRecipe, Normalisation
from vpr_explorer.descriptors.runtime import (
    TorchExtractor,
    file_identity,
    load_strict,
    prepare,
    read_checkpoint,
    resolve_device,
    resolve_precision,
    shared,
)

NAME = "alexnet-conv3"
INPUT_SIZE = 224
CONV3_END = 7  # features[:7]
CONV3_SHAPE = (384, 13, 13)
FLAT_DIM = 384 * 13 * 13  # 64,896
PROJECTION_DIM = 4096
PROJECTION_SEED = 0
# Bumped when the recipe changes; the weights' hash and the seed are in the version too.
# 2: 16-bit greyscale is scaled by its bit depth (1 clipped it to a white image).
RECIPE_VERSION = "2"
#: The input rule, read by the CPU load and by the device path alike.
RECIPE = DeviceRecipe(normalisation=Normalisation.IMAGENET, size=(INPUT_SIZE, INPUT_SIZE))


@functools.lru_cache(maxsize=1)
def random_projection(in_dim: int = FLAT_DIM, out_dim: int = PROJECTION_DIM, seed: int = PROJECTION_SEED) -> torch.Tensor:
    """VPR_Tutorial's projection matrix ``P``, ``(in_dim, out_dim)`` float32, rows of unit length.

    ``P = G / ||G||_row`` with ``G ~ N(0, 1)`` drawn by ``np.random.default_rng(seed)``
    in float32. Cached: generated once per process and shared by every AlexNet extractor
    on the CPU.
    """
    rng = np.random.default_rng(seed=seed)
    matrix = rng.standard_normal((in_dim, out_dim), dtype=np.float32)
    matrix /= np.linalg.norm(matrix, axis=1, keepdims=True)
    return torch.from_numpy(matrix)


class AlexNetConv3Projection(torch.nn.Module):
    """``(B, 3, 224, 224)`` -> conv3 map ``(B, 384, 13, 13)`` -> flat ``(B, 64896)`` -> ``(B, 4096)``."""

    def __init__(self, conv3: torch.nn.Module, projection: torch.Tensor) -> None:
        super().__init__()
        self.conv3 = conv3
        # A buffer so that .to(device) moves it; not persistent: it is not a weight.
        self.register_buffer("projection", projection, persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # flatten() follows the logical (C, H, W) order whatever the memory format.
        return self.conv3(x).flatten(1) @ self.projection


def build_conv3(path: Path) -> tuple[torch.nn.Sequential, str]:
    """torchvision AlexNet loaded strictly from ``path``, cut to ``features[:7]``; and the file's sha256.

    The whole network is built and loaded (classifier included) so that strict loading
    accounts for every tensor of the official file.

    Raises:
        VPRInputError: naming ``path`` when it is not a torchvision AlexNet state dict.
    """
    state, digest = read_checkpoint(path, f"{ALEXNET.file_name} ({ALEXNET.label})")
    net = torchvision.models.alexnet(weights=None)
    load_strict(net, state, path, "torchvision AlexNet", f"use {ALEXNET.file_name} ({ALEXNET.url})")
    return net.features[:CONV3_END], digest


def _build(path: Path, device: torch.device, precision) -> TorchExtractor:
    conv3, digest = build_conv3(path)
    model = prepare(AlexNetConv3Projection(conv3, random_projection()), device, channels_last=True)
    return TorchExtractor(
        name=NAME,
        version=f"{RECIPE_VERSION}.p{PROJECTION_SEED}.{digest[:12]}",
        dim=PROJECTION_DIM,
        model=model,
        load=RECIPE.load,
        device=device,
        precision=precision,
        recipe=RECIPE,
    )


def alexnet_conv3(
    weights: str | os.PathLike[str] | None = None,
    download: bool = False,
    device: str = "auto",
    precision: str = "fp32",
) -> TorchExtractor:
    """The AlexNet conv3 extractor (shared per weights file, device and precision).

    Args:
        weights: a torchvision AlexNet state dict (``.pth``); default: the
            ``VPR_EXPLORER_ALEXNET_WEIGHTS`` file, else torch hub's cached
            ``alexnet-owt-7be5be79.pth`` (see :mod:`~vpr_explorer.descriptors.checkpoints`).
        download: fetch the official file into torch hub's folder when it is missing.
        device: ``"auto"`` (the GPU when there is one), ``"cpu"``, ``"cuda"``, ``"cuda:N"``.
        precision: ``"fp32"``, ``"bf16"`` or ``"fp16"`` (autocast; its own cache key).

    Raises:
        VPRInputError: no weights (saying where to put them), a bad file, a bad option.
    """
    path = locate_weights(ALEXNET, weights, download)
    resolved = resolve_device(device)
    mode = resolve_precision(precision, resolved)
    key = (NAME, file_identity(path), str(resolved), mode)
    return shared(key, lambda: _build(path, resolved, mode))
