"""CosPlace and EigenPlaces: a torchvision backbone, GeM pooling, a linear layer, L2.

Both methods publish the same network (gmberton/CosPlace
``cosplace_model/cosplace_network.py`` ``GeoLocalizationNet``, gmberton/EigenPlaces
``eigenplaces_model/eigenplaces_network.py`` ``GeoLocalizationNet_``); they differ in
training, i.e. in the weights. Rebuilt here with the same module tree, so the official
checkpoints load strictly by their own key names::

    backbone.0 ... backbone.7        ResNet conv1, bn1, relu, maxpool, layer1-4
                                     (VGG16: features[:-2], backbone.0 ... backbone.28)
    aggregation.0  L2Norm            over channels, at each position
    aggregation.1  GeM               p (learnt, starts at 3), eps 1e-6
    aggregation.2  Flatten
    aggregation.3  Linear            features_dim -> fc_output_dim
    aggregation.4  L2Norm

GeM: ``f_c = (mean_{h,w} max(x_chw, eps)^p)^(1/p)`` (Radenovic et al. 2018, eq. 3).

Input, as VPR_Tutorial feeds both (``transforms.Resize(480)``): the shorter side resized
to 480 pixels, aspect kept, no crop (GardensPoint's 960 x 540 -> 853 x 480), ImageNet
mean/std. ``short_side`` changes it (and the cache key).

Weights: the official release files (``ResNet50_2048_cosplace.pth``...), the ones
``torch.hub.load("gmberton/cosplace", "get_trained_model", ...)`` downloads into torch
hub's checkpoint folder; they are read from there (or from ``weights=`` / the
environment variable, see :mod:`~vpr_explorer.descriptors.checkpoints`) into this
network, so no repository code is fetched or run.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import torch
import torch.nn.functional as F
import torchvision

from vpr_explorer.descriptors.checkpoints import PUBLISHED_MODELS, WeightsSpec, locate_weights, place_weights
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
from vpr_explorer.errors import VPRInputError

METHODS = tuple(PUBLISHED_MODELS)  # ("cosplace", "eigenplaces")
# Channels of the last convolution, the GeM input (the repositories' CHANNELS_NUM_IN_LAST_CONV).
CHANNELS_IN_LAST_CONV = {"ResNet18": 512, "ResNet50": 2048, "ResNet101": 2048, "ResNet152": 2048, "VGG16": 512}
DEFAULT_BACKBONE = "ResNet50"
DEFAULT_DIM = 2048
SHORT_SIDE = 480
SHORT_SIDE_RANGE = (32, 4096)
# Bumped when the recipe changes. 2: 16-bit greyscale is scaled by its bit depth (1
# clipped it to a white image).
RECIPE_VERSION = "2"


class L2Norm(torch.nn.Module):
    """Unit L2 norm along ``dim``."""

    def __init__(self, dim: int = 1) -> None:
        super().__init__()
        self.dim = dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.normalize(x, p=2.0, dim=self.dim)


class GeM(torch.nn.Module):
    """Generalised-mean pooling, ``(B, C, H, W)`` -> ``(B, C, 1, 1)``, learnt exponent ``p``."""

    def __init__(self, p: float = 3.0, eps: float = 1e-6) -> None:
        super().__init__()
        self.p = torch.nn.Parameter(torch.ones(1) * p)
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.avg_pool2d(x.clamp(min=self.eps).pow(self.p), (x.size(-2), x.size(-1))).pow(1.0 / self.p)


class Flatten(torch.nn.Module):
    """``(B, C, 1, 1)`` -> ``(B, C)``."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x[:, :, 0, 0]


def build_backbone(backbone: str) -> torch.nn.Sequential:
    """The repositories' trunk, randomly initialised: ResNet without avgpool and fc, VGG16 ``features[:-2]``."""
    net = getattr(torchvision.models, backbone.lower())(weights=None)
    if backbone.startswith("ResNet"):
        layers = list(net.children())[:-2]
    else:
        layers = list(net.features.children())[:-2]
    return torch.nn.Sequential(*layers)


class GeoLocalizationNet(torch.nn.Module):
    """``(B, 3, H, W)`` -> ``(B, fc_output_dim)`` unit descriptors; CosPlace's and EigenPlaces' network."""

    def __init__(self, backbone: str, fc_output_dim: int) -> None:
        super().__init__()
        self.backbone = build_backbone(backbone)
        self.aggregation = torch.nn.Sequential(
            L2Norm(),
            GeM(),
            Flatten(),
            torch.nn.Linear(CHANNELS_IN_LAST_CONV[backbone], fc_output_dim),
            L2Norm(),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.aggregation(self.backbone(x))


def load_network(path: Path, spec: WeightsSpec, backbone: str, fc_output_dim: int) -> tuple[GeoLocalizationNet, str]:
    """The network loaded strictly from ``path``; and the file's sha256.

    Raises:
        VPRInputError: naming ``path`` when its keys or shapes are not this backbone's
            and dimension's (e.g. a 512-d file asked for as 2048-d).
    """
    state, digest = read_checkpoint(path, f"{spec.file_name} ({spec.label})")
    net = GeoLocalizationNet(backbone, fc_output_dim)
    fix = f"use {spec.file_name} ({spec.url}) or pass the backbone and fc_output_dim the file was trained with"
    fc = state.get("aggregation.3.weight")
    if fc is not None and fc.dim() == 2 and fc.shape[0] != fc_output_dim:
        fix = f"the file holds {fc.shape[0]}-d descriptors: pass fc_output_dim={fc.shape[0]}, or use {spec.file_name}"
    load_strict(net, state, path, f"{backbone} {fc_output_dim}-d GeoLocalizationNet", fix)
    return net, digest


def _check_short_side(short_side: int) -> None:
    low, high = SHORT_SIDE_RANGE
    if isinstance(short_side, bool) or not isinstance(short_side, int) or not low <= short_side <= high:
        raise VPRInputError(f"short_side={short_side!r}: must be a whole number of pixels from {low} to {high}")


def _build(method: str, spec: WeightsSpec, path: Path, backbone: str, fc_output_dim: int, short_side: int,
           device: torch.device, precision) -> TorchExtractor:
    net, digest = load_network(path, spec, backbone, fc_output_dim)
    recipe = DeviceRecipe(normalisation=Normalisation.IMAGENET, short_side=short_side)
    return TorchExtractor(
        name=method,
        version=f"{RECIPE_VERSION}.{backbone}-{fc_output_dim}.s{short_side}.{digest[:12]}",
        dim=fc_output_dim,
        model=prepare(net, device, channels_last=True),
        load=recipe.load,
        device=device,
        precision=precision,
        recipe=recipe,
    )


def place_extractor(
    method: str,
    backbone: str = DEFAULT_BACKBONE,
    fc_output_dim: int = DEFAULT_DIM,
    short_side: int = SHORT_SIDE,
    weights: str | os.PathLike[str] | None = None,
    download: bool = False,
    device: str = "auto",
    precision: str = "fp32",
) -> TorchExtractor:
    """A CosPlace or EigenPlaces extractor (shared per weights file and options).

    Args:
        method: ``"cosplace"`` or ``"eigenplaces"``.
        backbone, fc_output_dim: a published pair (:data:`PUBLISHED_MODELS`); default
            ResNet-50, 2048-d, as in VPR_Tutorial.
        short_side: pixels of the shorter image side fed to the network.
        weights: the checkpoint (``.pth``, the official state dict); default: the
            ``VPR_EXPLORER_<METHOD>_WEIGHTS`` file or folder, else torch hub's cache.
        download: fetch the official file into torch hub's folder when it is missing.
        device, precision: see :func:`~vpr_explorer.descriptors.alexnet.alexnet_conv3`.

    Raises:
        VPRInputError: an unpublished pair, no weights (saying where to put them), a
            bad file, a bad option.
    """
    spec = place_weights(method, backbone, fc_output_dim)
    _check_short_side(short_side)
    path = locate_weights(spec, weights, download)
    resolved = resolve_device(device)
    mode = resolve_precision(precision, resolved)
    key = (method, backbone, fc_output_dim, short_side, file_identity(path), str(resolved), mode)
    return shared(key, lambda: _build(method, spec, path, backbone, fc_output_dim, short_side, resolved, mode))


cosplace = functools.partial(place_extractor, "cosplace")
eigenplaces = functools.partial(place_extractor, "eigenplaces")
