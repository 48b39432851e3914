"""Where the paper's model weights come from and where they are looked for; torch-free.

No weights ship with the package and none are fetched behind the user's back. A model's
weights file is looked for, in this order:

1. the extractor's ``weights=PATH`` option;
2. its environment variable (``VPR_EXPLORER_ALEXNET_WEIGHTS``,
   ``VPR_EXPLORER_COSPLACE_WEIGHTS``, ``VPR_EXPLORER_EIGENPLACES_WEIGHTS``): a file, or a
   folder holding the file under its official name;
3. torch hub's checkpoint folder (``$TORCH_HOME/hub/checkpoints``, default
   ``~/.cache/torch/hub/checkpoints``), under the official file name: where
   ``torch.hub`` / torchvision put it when it was downloaded once, on any machine.

Only ``download=True`` goes to the network, through torch hub's own downloader, into
that same folder. Everything here is cheap and imports no torch, so the app can list
which extractors are usable without loading a model.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from vpr_explorer.errors import VPRInputError

# Published (backbone -> descriptor dimensions) pairs, as in each repository's hubconf.py
# (gmberton/CosPlace, gmberton/EigenPlaces: AVAILABLE_TRAINED_MODELS).
PUBLISHED_MODELS: dict[str, dict[str, tuple[int, ...]]] = {
    "cosplace": {
        "VGG16": (64, 128, 256, 512),
        "ResNet18": (32, 64, 128, 256, 512),
        "ResNet50": (32, 64, 128, 256, 512, 1024, 2048),
        "ResNet101": (32, 64, 128, 256, 512, 1024, 2048),
        "ResNet152": (32, 64, 128, 256, 512, 1024, 2048),
    },
    "eigenplaces": {
        "VGG16": (512,),
        "ResNet18": (256, 512),
        "ResNet50": (128, 256, 512, 1024, 2048),
        "ResNet101": (128, 256, 512, 1024, 2048),
    },
}
# Repository spellings, for the release URL and the weights file name.
_REPOSITORIES = {"cosplace": "CosPlace", "eigenplaces": "EigenPlaces"}


@dataclass(frozen=True)
class WeightsSpec:
    """One published weights file.

    Attributes:
        label: what it is, for messages.
        file_name: its official name (the last part of ``url``).
        url: where it is published.
        env: the environment variable that may point at it.
        sha256_prefix: leading hex digits of its sha256 where the publisher states them
            (torchvision does, in the file name); checked after a download.
    """

    label: str
    file_name: str
    url: str
    env: str
    sha256_prefix: str | None = None


ALEXNET = WeightsSpec(
    label="torchvision's AlexNet_Weights.IMAGENET1K_V1",
    file_name="alexnet-owt-7be5be79.pth",
    url="https://download.pytorch.org/models/alexnet-owt-7be5be79.pth",
    env="VPR_EXPLORER_ALEXNET_WEIGHTS",
    sha256_prefix="7be5be79",
)


def place_weights(method: str, backbone: str, fc_output_dim: int) -> WeightsSpec:
    """The published CosPlace / EigenPlaces checkpoint for one backbone and dimension.

    Raises:
        VPRInputError: for a pair the authors did not publish, listing the ones they did.
    """
    published = PUBLISHED_MODELS[method]
    if backbone not in published:
        raise VPRInputError(
            f"backbone={backbone!r}: {_REPOSITORIES[method]} publishes no such model; "
            f"choose one of {', '.join(published)}"
        )
    if isinstance(fc_output_dim, bool) or not isinstance(fc_output_dim, int) or fc_output_dim not in published[backbone]:
        raise VPRInputError(
            f"fc_output_dim={fc_output_dim!r}: {_REPOSITORIES[method]} {backbone} is published with "
            f"{', '.join(map(str, published[backbone]))} dimensions; choose one of those"
        )
    repo = _REPOSITORIES[method]
    file_name = f"{backbone}_{fc_output_dim}_{method}.pth"
    return WeightsSpec(
        label=f"{repo} {backbone} {fc_output_dim}-d, gmberton/{repo} release v1.0",
        file_name=file_name,
        url=f"https://github.com/gmberton/{repo}/releases/download/v1.0/{file_name}",
        env=f"VPR_EXPLORER_{method.upper()}_WEIGHTS",
    )


def torch_hub_dir() -> Path:
    """torch hub's folder, computed as ``torch.hub.get_dir()`` does, without importing torch.

    ``$TORCH_HOME/hub``, else ``$XDG_CACHE_HOME/torch/hub``, else ``~/.cache/torch/hub``
    (``torch.hub.set_dir`` in the same process is not seen).
    """
    home = os.environ.get("TORCH_HOME") or os.path.join(os.environ.get("XDG_CACHE_HOME", "~/.cache"), "torch")
    return Path(home).expanduser() / "hub"


def hub_checkpoint(spec: WeightsSpec) -> Path:
    """Where torch hub keeps ``spec``'s file once downloaded."""
    return torch_hub_dir() / "checkpoints" / spec.file_name


def _where_to_get(spec: WeightsSpec) -> str:
    # What works from the command line and the app comes first: a file in a folder or an
    # environment variable. The keyword options only exist for Python callers.
    return (
        f"expected {spec.file_name} ({spec.label}): download {spec.url} and put it at {hub_checkpoint(spec)}, "
        f"or set the environment variable {spec.env} to the file (or to a folder holding it) before "
        "starting the command or the app (from Python, the weights=PATH and download=True options also work)"
    )


def find_weights(spec: WeightsSpec, path: str | os.PathLike[str] | None = None) -> Path | str:
    """The weights file to load, or the reason there is none (a sentence naming the file).

    ``path`` (the ``weights`` option) wins over the environment variable, which wins
    over torch hub's folder; a path that is given but missing is an error, not a reason
    to look elsewhere.
    """
    if path is not None:
        given = Path(path).expanduser()
        if given.is_dir():
            given = given / spec.file_name
        return given if given.is_file() else f"weights={str(path)!r}: no such file; {_where_to_get(spec)}"
    value = os.environ.get(spec.env)
    if value:
        given = Path(value).expanduser()
        if given.is_dir():
            given = given / spec.file_name
        return given if given.is_file() else f"{spec.env}={value}: no such file; {_where_to_get(spec)}"
    cached = hub_checkpoint(spec)
    return cached if cached.is_file() else f"no weights file: {_where_to_get(spec)}"


def unavailable_reason(spec: WeightsSpec, path: str | os.PathLike[str] | None = None, download: bool = False) -> str | None:
    """``None`` when the weights can be had (found, or ``download`` asked for), else why not."""
    from importlib.util import find_spec

    for module in ("torch", "torchvision"):
        if find_spec(module) is None:
            return f"{module} is not installed: pip install {module}"
    found = find_weights(spec, path)
    if isinstance(found, Path) or (download and path is None):
        return None
    return found


def locate_weights(spec: WeightsSpec, path: str | os.PathLike[str] | None = None, download: bool = False) -> Path:
    """The weights file, downloading it into torch hub's folder first when asked and missing.

    Raises:
        VPRInputError: when it cannot be found (or downloaded), saying where to put it.
    """
    if not isinstance(download, bool):
        raise VPRInputError(f"download={download!r}: must be True or False")
    found = find_weights(spec, path)
    if isinstance(found, Path):
        return found
    if not download or path is not None:
        raise VPRInputError(found)
    target = hub_checkpoint(spec)
    import torch.hub

    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        torch.hub.download_url_to_file(spec.url, str(target), hash_prefix=spec.sha256_prefix, progress=False)
    except (OSError, RuntimeError, ValueError) as exc:  # URLError is an OSError
        raise VPRInputError(f"could not download {spec.url} ({exc}); {_where_to_get(spec)}") from exc
    return target
