"""Extractors by name: one entry per extractor, dispatched through a dict.

Adding an extractor is one line in ``_REGISTRY``: a factory (called with the user's
options) and a check that says why it cannot run here, if it cannot. Modules that
import torch are imported inside their factory, so listing the extractors (a
selectbox) stays cheap.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from vpr_explorer.descriptors.base import Extractor
from vpr_explorer.errors import VPRInputError


@dataclass(frozen=True)
class ExtractorEntry:
    """How to make one extractor.

    Attributes:
        factory: ``factory(**options) -> Extractor``.
        unavailable: ``() -> None`` when usable here, else the reason it is not.
        options: the keyword options ``factory`` accepts (checked before calling it).
    """

    factory: Callable[..., Extractor]
    unavailable: Callable[[], str | None]
    options: tuple[str, ...] = ()


def _always_available() -> None:
    return None


def _pixels() -> Extractor:
    from vpr_explorer.descriptors.pixels import PixelsExtractor

    return PixelsExtractor()


def _efficientnet_lite0() -> Extractor:
    from vpr_explorer.descriptors.efficientnet import efficientnet_lite0

    return efficientnet_lite0()


def _efficientnet_lite0_unavailable() -> str | None:
    # Checks the weights file without importing torch or timm.
    from importlib.util import find_spec

    for module in ("torch", "timm"):
        if find_spec(module) is None:
            return f"{module} is not installed: pip install {module}"
    from vpr_explorer.descriptors.efficientnet_weights import unavailable_reason

    return unavailable_reason()


_REGISTRY: dict[str, ExtractorEntry] = {
    "pixels": ExtractorEntry(_pixels, _always_available),
    "efficientnet-lite0": ExtractorEntry(_efficientnet_lite0, _efficientnet_lite0_unavailable),
}

EXTRACTOR_NAMES: tuple[str, ...] = tuple(_REGISTRY)


def available_extractors() -> dict[str, str | None]:
    """``{name: None}`` for extractors usable here, ``{name: reason}`` for the others."""
    return {name: entry.unavailable() for name, entry in _REGISTRY.items()}


def get_extractor(name: str, **options: object) -> Extractor:
    """The extractor registered as ``name``, made with ``options``.

    Raises:
        VPRInputError: for an unknown name or option (listing the choices), or when the
            extractor cannot run here (saying why).
    """
    entry = _REGISTRY.get(name)
    if entry is None:
        raise VPRInputError(f"descriptor {name!r} is unknown: choose one of {', '.join(EXTRACTOR_NAMES)}")
    unknown = sorted(set(options) - set(entry.options))
    if unknown:
        accepted = ", ".join(entry.options) if entry.options else "none"
        raise VPRInputError(f"descriptor {name!r} has no option {', '.join(unknown)}: it accepts {accepted}")
    reason = entry.unavailable()
    if reason is not None:
        raise VPRInputError(f"descriptor {name!r} is unavailable here: {reason}")
    return entry.factory(**options)
