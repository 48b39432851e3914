"""Extractors by name: one entry per extractor, dispatched through a dict.

Adding a built-in extractor is one line in ``_REGISTRY``: a factory (called with the
user's options), a check that says why it cannot run here, if it cannot (called with
the same options), and the options accepted. Modules that import torch are imported
inside their factory, so listing the extractors (a selectbox) stays cheap.

Users' own models join the built-ins by name: :func:`register_extractor` in code, or the
settings file named by ``VPR_EXPLORER_MODELS`` (see :mod:`~vpr_explorer.descriptors.custom`).
Any torch.hub repository is one by the name ``hub:DIR[:ENTRY]`` (see
:mod:`~vpr_explorer.descriptors.hub`): accepted by :func:`get_extractor` and
:func:`extractor_options`, never listed (there is one per folder); a settings file's table
``model = "hub:DIR[:ENTRY]"`` lists it under that table's name, with its options fixed there.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from dataclasses import dataclass

from vpr_explorer.descriptors import checkpoints, custom, hub
from vpr_explorer.descriptors.base import Extractor
from vpr_explorer.errors import VPRInputError

# Options of every extractor that runs a torch model.
RUNTIME_OPTIONS = ("device", "precision")
WEIGHTS_OPTIONS = ("weights", "download")
PLACE_OPTIONS = ("backbone", "fc_output_dim", "short_side")


@dataclass(frozen=True)
class ExtractorEntry:
    """How to make one extractor.

    Attributes:
        factory: ``factory(**options) -> Extractor``.
        unavailable: ``unavailable(**options) -> None`` when usable here, else the reason
            it is not (a sentence naming the missing file and where to get it).
        options: the keyword options ``factory`` accepts (checked before calling it).
    """

    factory: Callable[..., Extractor]
    unavailable: Callable[..., str | None]
    options: tuple[str, ...] = ()


def _always_available(**_options: object) -> None:
    return None


def _needs(*modules: str) -> str | None:
    from importlib.util import find_spec

    for module in modules:
        if find_spec(module) is None:
            return f"{module} is not installed: pip install {module}"
    return None


def _pixels() -> Extractor:
    from vpr_explorer.descriptors.pixels import PixelsExtractor

    return PixelsExtractor()


def _efficientnet_lite0(**options: object) -> Extractor:
    from vpr_explorer.descriptors.efficientnet import efficientnet_lite0

    return efficientnet_lite0(**options)


def _efficientnet_lite0_unavailable(**_options: object) -> str | None:
    # Checks the weights file without importing torch or timm.
    from vpr_explorer.descriptors.efficientnet_weights import unavailable_reason

    return _needs("torch", "timm") or unavailable_reason()


def _alexnet_conv3(**options: object) -> Extractor:
    from vpr_explorer.descriptors.alexnet import alexnet_conv3

    return alexnet_conv3(**options)


def _alexnet_conv3_unavailable(weights: object = None, download: object = False, **_runtime: object) -> str | None:
    return checkpoints.unavailable_reason(checkpoints.ALEXNET, weights, download is True)


def _place(method: str, **options: object) -> Extractor:
    from vpr_explorer.descriptors.gem_resnet import place_extractor

    return place_extractor(method, **options)


def _place_unavailable(
    method: str,
    backbone: object = "ResNet50",
    fc_output_dim: object = 2048,
    weights: object = None,
    download: object = False,
    **_others: object,
) -> str | None:
    spec = checkpoints.place_weights(method, backbone, fc_output_dim)  # raises for an unpublished pair
    return checkpoints.unavailable_reason(spec, weights, download is True)


_REGISTRY: dict[str, ExtractorEntry] = {
    "pixels": ExtractorEntry(_pixels, _always_available),
    "efficientnet-lite0": ExtractorEntry(_efficientnet_lite0, _efficientnet_lite0_unavailable, RUNTIME_OPTIONS),
    "alexnet-conv3": ExtractorEntry(
        _alexnet_conv3, _alexnet_conv3_unavailable, WEIGHTS_OPTIONS + RUNTIME_OPTIONS
    ),
    "cosplace": ExtractorEntry(
        functools.partial(_place, "cosplace"),
        functools.partial(_place_unavailable, "cosplace"),
        PLACE_OPTIONS + WEIGHTS_OPTIONS + RUNTIME_OPTIONS,
    ),
    "eigenplaces": ExtractorEntry(
        functools.partial(_place, "eigenplaces"),
        functools.partial(_place_unavailable, "eigenplaces"),
        PLACE_OPTIONS + WEIGHTS_OPTIONS + RUNTIME_OPTIONS,
    ),
}

# The built-in extractors; extractor_names() adds the users' models.
EXTRACTOR_NAMES: tuple[str, ...] = tuple(_REGISTRY)

# Models registered in code, by name (they win over the settings file's of that name).
_USER_MODELS: dict[str, custom.CustomModel] = {}


def _custom_entry(spec: custom.CustomModel | custom.HubSetting) -> ExtractorEntry:
    if isinstance(spec, custom.HubSetting):
        return ExtractorEntry(
            functools.partial(hub.build_extractor, spec.descriptor, **dict(spec.options)),
            lambda **_runtime: hub.unavailable_reason(spec.descriptor),
            RUNTIME_OPTIONS,
        )
    return ExtractorEntry(
        functools.partial(custom.build_extractor, spec),
        lambda **_runtime: custom.unavailable_reason(spec),
        RUNTIME_OPTIONS,
    )


def _entry(name: str, entries: dict[str, ExtractorEntry]) -> ExtractorEntry:
    """``name``'s entry: a listed one, or a ``hub:DIR[:ENTRY]`` model.

    Raises:
        VPRInputError: for an unknown name, listing the choices.
    """
    if name in entries:
        return entries[name]
    if hub.is_hub_name(name):
        return ExtractorEntry(
            functools.partial(hub.build_extractor, name),
            functools.partial(hub.unavailable_reason, name),
            hub.OPTIONS + RUNTIME_OPTIONS,
        )
    raise VPRInputError(
        f"descriptor {name!r} is unknown: choose one of {', '.join(entries)}, or hub:DIR[:ENTRY] (a torch.hub "
        "repository folder)"
    )


def _entries() -> dict[str, ExtractorEntry]:
    """Built-ins, then the settings file's models, then those registered in code."""
    users = {**custom.settings_models(), **_USER_MODELS}
    clash = sorted(set(users) & set(_REGISTRY))
    if clash:
        raise VPRInputError(
            f"model name {clash[0]!r} in {custom.MODELS_ENV}={os.environ.get(custom.MODELS_ENV)} is a built-in "
            "descriptor's; rename it"
        )
    return {**_REGISTRY, **{name: _custom_entry(spec) for name, spec in users.items()}}


def register_extractor(
    name: str,
    model: str | os.PathLike[str],
    *,
    input_size: int | tuple[int, int] = 224,
    normalisation: str = "imagenet",
    dim: int | None = None,
    version: str = "",
) -> None:
    """Make a user's model available as ``get_extractor(name)`` in this process.

    Args:
        name: new name (letters, digits, ``. _ -``); registering it again replaces it.
        model: a TorchScript file, a torch.export program (``.pt2``), or an entry point ``"package.module:function"`` or
            ``"path/to/file.py:function"`` whose function returns a callable mapping a
            ``(B, 3, H, W)`` float batch to ``(B, D)`` descriptors.
        input_size: ``(width, height)`` or one number for a square.
        normalisation: ``"imagenet"``, ``"unit"`` or ``"signed"``.
        dim: expected descriptor length (checked), or ``None``.
        version: a tag that is part of the cache key (bump it when weights change that
            the model file does not contain).

    Nothing is loaded until ``get_extractor(name)``.

    Raises:
        VPRInputError: a bad or built-in name, or a bad option.
    """
    if name in _REGISTRY:
        raise VPRInputError(f"name={name!r} is a built-in descriptor; choose another name")
    _USER_MODELS[name] = custom.custom_model(
        name, model, input_size=input_size, normalisation=normalisation, dim=dim, version=version
    )


def unregister_extractor(name: str) -> None:
    """Forget a model registered with :func:`register_extractor` (no error if it was not)."""
    _USER_MODELS.pop(name, None)


def extractor_names() -> tuple[str, ...]:
    """Every name ``get_extractor`` accepts now: the built-ins, then the users' models."""
    return tuple(_entries())


def extractor_options(name: str) -> tuple[str, ...]:
    """The keyword options ``get_extractor(name, ...)`` accepts (``()`` for ``pixels``).

    Raises:
        VPRInputError: for an unknown name, listing the choices.
    """
    return _entry(name, _entries()).options


def cache_name(name: str) -> str:
    """The name of ``get_extractor(name)``'s extractor, which its cache keys begin with (``<name>-<version>``).

    ``name`` itself, but for ``hub:DIR[:ENTRY]`` and a settings file's hub model:
    ``hub.<folder>.<entry>``.
    """
    if hub.is_hub_name(name):
        return hub.cache_name(name)
    spec = custom.settings_models().get(name) if name not in _USER_MODELS else None
    return hub.cache_name(spec.descriptor) if isinstance(spec, custom.HubSetting) else name


def available_extractors() -> dict[str, str | None]:
    """``{name: None}`` for extractors usable here, ``{name: reason}`` for the others.

    Each built-in is checked with its default options; a reason names the file that is
    missing, where it is published and where to put it.
    """
    return {name: entry.unavailable() for name, entry in _entries().items()}


def get_extractor(name: str, **options: object) -> Extractor:
    """The extractor registered as ``name``, made with ``options``.

    Raises:
        VPRInputError: for an unknown name or option (listing the choices), or when the
            extractor cannot run here (saying why).
    """
    entry = _entry(name, _entries())
    unknown = sorted(set(options) - set(entry.options))
    if unknown:
        accepted = ", ".join(entry.options) if entry.options else "none"
        raise VPRInputError(f"descriptor {name!r} has no option {', '.join(unknown)}: it accepts {accepted}")
    reason = entry.unavailable(**options)
    if reason is not None:
        raise VPRInputError(f"descriptor {name!r} is unavailable here: {reason}")
    return entry.factory(**options)
